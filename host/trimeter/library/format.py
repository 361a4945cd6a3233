"""The material format, version 1: one directory per material, open and documented (docs/library.md).

    <name>/
        material.json   the manifest: name, notes, tags, how it was combined, every member's provenance
                        (its measurement, the maps and calibration it used, checksums), the spectra's
                        columns with units and meaning; checked against schema/material-v1.json
        spectra.csv     one row per wavelength: each parameter's value, std, spread between repeats and
                        χ² p-value, the members' count and the flags (trimeter.library.combine)

The manifest carries spectra.csv's SHA-256, so a changed or truncated table is refused. Numbers are
written with 17 significant digits: a material read back is the material written, bit for bit. Values
(α, σt, g) are finite in every row; an unknown std, spread or p-value is an empty cell.

The reader checks the manifest against the JSON Schema file itself (`validate`, a small interpreter of
the keywords the schema uses), then the table against the manifest.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.version import __version__
from trimeter.errors import InputError

FORMAT = "trimeter-material"
VERSION = 1
MANIFEST_FILE = "material.json"
SPECTRA_FILE = "spectra.csv"
SCHEMA_FILE = Path(__file__).resolve().parent / "schema" / f"material-v{VERSION}.json"
MAX_MANIFEST_BYTES = 10_000_000

# spectra.csv's columns, in order: (name, unit, meaning)
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("wavelength_nm", "nm", "wavelength of the bin"),
    *((f"{p}{suffix}", unit, f"{what} {label}") for p, unit, label in (
        ("alpha", "1", "single-scattering albedo α = σs/σt"),
        ("sigma_t", "1/mm", "extinction coefficient σt = σa + σs"),
        ("g", "1", "Henyey-Greenstein anisotropy g"))
      for suffix, unit, what in (
          ("", unit, "combined value of the"),
          ("_std", unit, "standard deviation, from the members' own stds, of the combined"),
          ("_spread", unit, "standard deviation between the repeated measurements of the"),
          ("_chi2_p", "1", "χ² p-value of the repeats about the combined value (small: they disagree) of the"))),
    ("members", "1", "members with a value in this bin"),
    ("flags", "bits", "library flags (combination.flags)"),
    ("fit_flags", "bits", "the members' FitFlag words OR-ed (trimeter.inversion.flags)"),
)
COLUMN_NAMES = tuple(c[0] for c in COLUMNS)
VALUE_COLUMNS = ("wavelength_nm", "alpha", "sigma_t", "g", "members", "flags", "fit_flags")  # never empty
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9 ._+-]{0,63}")
TAG_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,31}")


@dataclass
class MaterialDocument:
    """A library material: what the SQLite library stores and the export writes."""
    name: str
    columns: dict[str, np.ndarray]
    combination: dict
    members: list[dict]
    notes: str = ""
    tags: list[str] = field(default_factory=list)
    created_utc: str = ""
    trimeter_version: str = __version__

    def manifest(self, spectra_sha256: str) -> dict:
        return {"format": FORMAT, "version": VERSION, "name": self.name, "notes": self.notes, "tags": list(self.tags),
                "created_utc": self.created_utc, "trimeter_version": self.trimeter_version,
                "spectra": {"file": SPECTRA_FILE, "sha256": spectra_sha256, "bins": len(self.columns["wavelength_nm"]),
                            "columns": {n: {"unit": u, "meaning": m} for n, u, m in COLUMNS}},
                "combination": self.combination, "members": self.members}

    def spectra_csv(self) -> str:
        """spectra.csv's text: 17 significant digits (exact), integers as integers, unknown as empty."""
        def cell(name: str, v: float) -> str:
            if not math.isfinite(v):
                return ""
            return str(int(v)) if name in ("members", "flags", "fit_flags") else repr(float(v))
        rows = [",".join(COLUMN_NAMES)]
        table = [np.asarray(self.columns[n], float) for n in COLUMN_NAMES]
        for i in range(len(table[0])):
            rows.append(",".join(cell(n, col[i]) for n, col in zip(COLUMN_NAMES, table, strict=True)))
        return "\n".join(rows) + "\n"

    def to_json(self) -> dict:
        """The whole material as one JSON object (what the library's database row holds)."""
        doc = self.manifest("0" * 64)
        doc["spectra"]["data"] = {n: [None if not math.isfinite(v) else float(v) for v in np.asarray(c, float)]
                                  for n, c in self.columns.items()}
        return doc

    @classmethod
    def from_json(cls, doc: dict) -> MaterialDocument:
        from trimeter.results.reader import json_numbers

        data = doc["spectra"]["data"]
        columns = {n: json_numbers(data[n], n, Path("library")) for n in COLUMN_NAMES}
        return cls(name=doc["name"], columns=columns, combination=doc["combination"], members=doc["members"],
                   notes=doc["notes"], tags=list(doc["tags"]), created_utc=doc["created_utc"],
                   trimeter_version=doc["trimeter_version"])


# ------------------------------------------------------------------------------------ the schema
@lru_cache(maxsize=1)
def schema() -> dict:
    return json.loads(SCHEMA_FILE.read_text())


_TYPES: dict[str, Any] = {"object": dict, "array": list, "string": str, "null": type(None), "boolean": bool}


def _is_type(value: object, name: str) -> bool:
    if name == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if name == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return isinstance(value, _TYPES[name])


def validate(value: object, rule: dict, where: str = "") -> list[str]:
    """What in `value` breaks the JSON Schema `rule`, as 'path: reason' lines (empty: valid). Covers the
    keywords material-v1.json uses (type, const, enum, required, properties, additionalProperties,
    items, minItems, minLength, pattern, minimum, maximum, exclusiveMinimum); a test checks the schema
    uses no other."""
    at = where or "(top)"
    if "const" in rule and value != rule["const"]:
        return [f"{at}: must be {rule['const']!r}, not {value!r}"]
    if "enum" in rule and value not in rule["enum"]:
        return [f"{at}: must be one of {', '.join(map(repr, rule['enum']))}, not {value!r}"]
    if "type" in rule:
        types = rule["type"] if isinstance(rule["type"], list) else [rule["type"]]
        if not any(_is_type(value, t) for t in types):
            return [f"{at}: must be {' or '.join(types)}, not {type(value).__name__}"]
    problems: list[str] = []
    if isinstance(value, dict):
        problems += [f"{at}: lacks {k!r}" for k in rule.get("required", []) if k not in value]
        props = rule.get("properties", {})
        extra = rule.get("additionalProperties", True)
        for k, v in value.items():
            if k in props:
                problems += validate(v, props[k], f"{where}.{k}" if where else k)
            elif extra is False:
                problems.append(f"{at}: unknown key {k!r}")
            elif isinstance(extra, dict):
                problems += validate(v, extra, f"{where}.{k}" if where else k)
    if isinstance(value, list):
        if len(value) < rule.get("minItems", 0):
            problems.append(f"{at}: needs at least {rule['minItems']} item(s)")
        if "items" in rule:
            for i, v in enumerate(value):
                problems += validate(v, rule["items"], f"{at}[{i}]")
    if isinstance(value, str):
        if len(value) < rule.get("minLength", 0):
            problems.append(f"{at}: must not be empty")
        if "pattern" in rule and not re.search(rule["pattern"], value):
            problems.append(f"{at}: {value!r} does not match {rule['pattern']}")
    if _is_type(value, "number"):
        assert isinstance(value, (int, float))
        if "minimum" in rule and value < rule["minimum"]:
            problems.append(f"{at}: must be ≥ {rule['minimum']}")
        if "maximum" in rule and value > rule["maximum"]:
            problems.append(f"{at}: must be ≤ {rule['maximum']}")
        if "exclusiveMinimum" in rule and value <= rule["exclusiveMinimum"]:
            problems.append(f"{at}: must be > {rule['exclusiveMinimum']}")
    return problems


# ------------------------------------------------------------------------------------ write / read
def write_material(doc: MaterialDocument, out_dir: str | Path) -> Path:
    """The material as a directory `out_dir` (created whole under a temporary name, then renamed; an
    existing directory is an error, never overwritten)."""
    import os
    import shutil

    from trimeter.atomic import atomic_write, fsync_directory
    from trimeter.errors import OutputError

    out = Path(out_dir)
    if out.exists():
        raise OutputError(f"{out}: exists; choose another output or remove it")
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".partial-{os.getpid()}-{out.name}")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        text = doc.spectra_csv()
        atomic_write(partial / SPECTRA_FILE, text)
        manifest = doc.manifest(hashlib.sha256(text.encode()).hexdigest())
        problems = validate(manifest, schema())
        if problems:  # a writer bug, never the user's input
            raise OutputError(f"the manifest would not pass its own schema: {'; '.join(problems[:5])}")
        atomic_write(partial / MANIFEST_FILE, json.dumps(manifest, indent=1, ensure_ascii=False) + "\n")
        os.rename(partial, out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    fsync_directory(out.parent)
    return out


def read_material(path: str | Path) -> MaterialDocument:
    """A material directory (or its material.json) read and checked; InputError naming the first problem."""
    from trimeter.tables import read_columns, read_text

    path = Path(path)
    directory = path.parent if path.name == MANIFEST_FILE else path
    manifest_path = directory / MANIFEST_FILE
    if not manifest_path.exists():
        raise InputError(f"{directory}: not a trimeter material (no {MANIFEST_FILE})")
    try:
        manifest = json.loads(read_text(manifest_path, max_bytes=MAX_MANIFEST_BYTES, follow_symlinks=False))
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{manifest_path}: not JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise InputError(f"{manifest_path}: not a trimeter material manifest (format must be {FORMAT!r})")
    if manifest.get("version") != VERSION:
        raise InputError(f"{manifest_path}: format version {manifest.get('version')!r}; this trimeter "
                         f"({__version__}) reads version {VERSION} only")
    problems = validate(manifest, schema())
    if problems:
        raise InputError(f"{manifest_path}: does not match {SCHEMA_FILE.name}: " + "; ".join(problems[:5]))
    spectra_path = directory / SPECTRA_FILE
    if not spectra_path.exists():
        raise InputError(f"{directory}: the spectra ({SPECTRA_FILE}) are missing")
    columns = read_columns(spectra_path, required=COLUMN_NAMES, follow_symlinks=False, min_rows=2)
    for name in VALUE_COLUMNS:
        bad = ~np.isfinite(columns[name])
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"{spectra_path}: {name} is NaN or empty in data row {i + 1}: values must be numbers "
                             "(only a std, spread or p-value may be unknown)")
    if len(columns["wavelength_nm"]) != manifest["spectra"]["bins"]:
        raise InputError(f"{spectra_path}: {len(columns['wavelength_nm'])} rows, the manifest says "
                         f"{manifest['spectra']['bins']}")
    if not np.all(np.diff(columns["wavelength_nm"]) > 0):
        raise InputError(f"{spectra_path}: wavelengths must increase")
    digest = hashlib.sha256(read_text(spectra_path, follow_symlinks=False).encode()).hexdigest()
    if digest != manifest["spectra"]["sha256"]:
        raise InputError(f"{spectra_path}: its SHA-256 is not the manifest's: changed or damaged since written")
    return MaterialDocument(name=manifest["name"], columns={n: columns[n] for n in COLUMN_NAMES},
                            combination=manifest["combination"], members=manifest["members"],
                            notes=manifest["notes"], tags=list(manifest["tags"]), created_utc=manifest["created_utc"],
                            trimeter_version=manifest["trimeter_version"])
