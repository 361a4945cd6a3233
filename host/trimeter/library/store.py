"""The material library: named materials made of measurements, in an SQLite file beside the history.

    lib = Library.open()                       # <data dir>/library.sqlite (TRIMETER_DATA_DIR or the user's)
    lib.add("cyan batch 3", ["results/2026…-cyan", "results/2026…-cyan-2"], tags=["ink"])
    lib.get("cyan batch 3").export(to="mitsuba", out_dir="cyan-mitsuba")
    lib.export("cyan batch 3", "cyan.material")   # the open format (trimeter.library.format)

The results directories stay the source of truth: a row keeps the combined spectra and, per member,
its path and the SHA-256 of its parameters.json and calibration.json as they were when added. Before a
material leaves the library (export), its members are checked: one that is gone or has changed since
is an error naming it, and the material stays as it was. An imported material's members live in
another laboratory: they are provenance only (`origin` "imported"). Every change is one transaction.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trimeter.errors import InputError, OutputError
from trimeter.library.combine import DISAGREE_P, FLAG_MEANING, PARAMETERS, Combined, combine
from trimeter.library.format import (COLUMN_NAMES, NAME_PATTERN, TAG_PATTERN, MaterialDocument, read_material,
                                     write_material)
from trimeter.results.reader import PARAMETERS_FILE, load
from trimeter.results.writer import Parameters

if TYPE_CHECKING:
    from trimeter.results.medium import SpectralMaterial

DB_FILE = "library.sqlite"
SCHEMA_VERSION = 1
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS materials (
    name TEXT PRIMARY KEY,
    origin TEXT NOT NULL,        -- 'local' (members here) or 'imported' (members are provenance only)
    created_utc TEXT NOT NULL,
    document TEXT NOT NULL       -- MaterialDocument.to_json()
);
"""


def default_path() -> Path:
    """Beside the history: the data directory's library.sqlite."""
    from trimeter.paths import data_dir

    return data_dir() / DB_FILE


def _sha256(path: Path) -> str | None:
    from trimeter.tables import MAX_RESULT_FILE_BYTES, open_checked

    if not path.exists():
        return None
    digest = hashlib.sha256()
    with open_checked(path, max_bytes=MAX_RESULT_FILE_BYTES, follow_symlinks=False, binary=True) as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise InputError(f"material name {name!r}: 1-64 letters, digits, spaces or . _ + -, starting with a letter "
                         "or digit")
    return name


def check_tags(tags: Sequence[str]) -> list[str]:
    for tag in tags:
        if not TAG_PATTERN.fullmatch(tag):
            raise InputError(f"tag {tag!r}: 1-32 letters, digits or . _ -, starting with a letter or digit")
    return sorted(set(tags))


def member_record(m: object) -> dict:
    """A member's provenance, as the format stores it (a trimeter.load result)."""
    from trimeter.results.reader import Measurement

    assert isinstance(m, Measurement)
    rec = m.record
    checksums = rec.get("map_checksums")
    device = rec.get("device")
    params_sha = _sha256(m.path / PARAMETERS_FILE)
    assert params_sha is not None  # load() read it
    return {"measurement": m.name, "path": str(m.path.resolve()), "sample": m.sample, "label": m.label,
            "written_utc": m.written_utc, "thicknesses_mm": m.thicknesses_mm, "method": m.method, "maps": m.maps,
            "map_checksums": [c if isinstance(c, str) else None for c in checksums]
            if isinstance(checksums, list) else [None] * len(m.maps),
            "parameters_sha256": params_sha, "calibration_sha256": _sha256(m.path / "calibration.json"),
            "device": device if isinstance(device, dict) else None}


def document_of(name: str, combined: Combined, members: list[dict], *, notes: str = "",
                tags: Sequence[str] = ()) -> MaterialDocument:
    """The bins with a combined α, σt and g, as a library material."""
    keep = np.isfinite(combined.values["alpha"]) & np.isfinite(combined.values["sigma_t"]) & np.isfinite(
        combined.values["g"])
    if keep.sum() < 2:
        raise InputError(f"material {name!r}: fewer than two wavelengths where the members give α, σt and g")
    columns = {"wavelength_nm": combined.wavelengths_nm}
    for p in PARAMETERS:
        columns.update({p: combined.values[p], f"{p}_std": combined.stds[p], f"{p}_spread": combined.spreads[p],
                        f"{p}_chi2_p": combined.chi2_p[p]})
    columns.update({"members": combined.members, "flags": combined.flags, "fit_flags": combined.fit_flags})
    columns = {k: np.asarray(columns[k], float)[keep] for k in COLUMN_NAMES}
    combination = {"method": combined.method, "thicknesses_mm": combined.thicknesses_mm, "disagree_p": DISAGREE_P,
                   "flags": {str(int(f)): text for f, text in FLAG_MEANING.items()}}
    return MaterialDocument(name=name, columns=columns, combination=combination, members=members, notes=notes,
                            tags=check_tags(tags),
                            created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"))


@dataclass
class LibraryMaterial:
    """A material of the library: its document, and the parameters-with-stds an export or a prediction takes."""
    document: MaterialDocument
    origin: str

    @property
    def name(self) -> str:
        return self.document.name

    @property
    def parameters(self) -> Parameters:
        from trimeter.domain.parameters import FitResult

        c = self.document.columns
        fit = FitResult(c["alpha"], c["sigma_t"], c["g"], c["alpha_std"], c["sigma_t_std"], c["g_std"],
                        c["fit_flags"].astype(np.int64), np.full(len(c["alpha"]), np.nan),
                        str(self.document.combination.get("method", "")))
        return Parameters.from_fit(c["wavelength_nm"], fit)

    def material(self) -> SpectralMaterial:
        """The material (trimeter.results.medium.SpectralMaterial) for predictions and mixtures."""
        from trimeter.results.medium import SpectralMaterial

        return SpectralMaterial.from_parameters(self.parameters)

    def source(self) -> dict:
        """What an export's provenance says about where the material came from."""
        thicknesses = self.document.combination.get("thicknesses_mm") or []
        return {"library_material": self.name, "sample": self.name, "origin": self.origin,
                "combination": self.document.combination.get("method"), "thicknesses_mm": thicknesses,
                "members": [{k: m.get(k) for k in ("measurement", "path", "maps", "parameters_sha256",
                                                   "calibration_sha256")} for m in self.document.members]}

    def export(self, to: str, out_dir: str | Path, **options: object) -> dict:
        """Files for a renderer (trimeter.results.export), as Measurement.export writes them for a measurement."""
        from trimeter.results.export import export, loaded_parameters

        result = loaded_parameters(self.parameters, self.source(), f"library material {self.name!r}")
        options.setdefault("reference_thickness_mm", result.measured_thickness_mm() or 1.0)
        return export(result, to, out_dir, **options)  # type: ignore[arg-type]

    def missing_members(self) -> list[str]:
        """Members whose directory is gone or whose parameters/calibration changed since they were added."""
        if self.origin != "local":
            return []
        problems = []
        for m in self.document.members:
            path = Path(m["path"])
            if not path.is_dir():
                problems.append(f"{m['measurement']} ({path}) no longer exists")
            elif _sha256(path / PARAMETERS_FILE) != m["parameters_sha256"]:
                problems.append(f"{m['measurement']} ({path}): its {PARAMETERS_FILE} changed since it was added")
            elif _sha256(path / "calibration.json") != m["calibration_sha256"]:
                problems.append(f"{m['measurement']} ({path}): its calibration.json changed since it was added")
        return problems


class Library:
    """The SQLite library at `db_path` (default: beside the history)."""

    def __init__(self, db_path: str | Path | None = None) -> None:
        self.db_path = Path(db_path) if db_path is not None else default_path()
        try:
            self.db_path.parent.mkdir(parents=True, exist_ok=True)
            self._con = sqlite3.connect(self.db_path, timeout=10.0, isolation_level=None)
            self._con.execute("PRAGMA journal_mode=WAL")
            self._con.execute("PRAGMA synchronous=FULL")
            self._con.executescript(_SCHEMA)
            row = self._con.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
            if row is None:
                self._con.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
            elif row[0] != str(SCHEMA_VERSION):
                raise InputError(f"{self.db_path}: a library of schema {row[0]}, this trimeter reads {SCHEMA_VERSION}")
        except sqlite3.DatabaseError as exc:
            raise InputError(f"{self.db_path}: not a usable library database ({exc})") from None
        except OSError as exc:
            raise OutputError(f"{self.db_path}: cannot open ({exc.strerror or exc})") from None

    def close(self) -> None:
        self._con.close()

    def __enter__(self) -> Library:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------ reading
    def names(self) -> list[str]:
        return [r[0] for r in self._con.execute("SELECT name FROM materials ORDER BY name")]

    def get(self, name: str) -> LibraryMaterial:
        row = self._con.execute("SELECT document, origin FROM materials WHERE name=?", (name,)).fetchone()
        if row is None:
            have = ", ".join(self.names()) or "none"
            raise InputError(f"no material {name!r} in the library {self.db_path} (have: {have})")
        return LibraryMaterial(MaterialDocument.from_json(json.loads(row[0])), row[1])

    def summaries(self) -> list[dict]:
        out = []
        for name in self.names():
            m = self.get(name)
            c = m.document.columns
            out.append({"name": name, "origin": m.origin, "members": len(m.document.members),
                        "thicknesses_mm": m.document.combination.get("thicknesses_mm"),
                        "combination": m.document.combination.get("method"), "tags": m.document.tags,
                        "notes": m.document.notes, "created_utc": m.document.created_utc,
                        "bins": len(c["wavelength_nm"]),
                        "disagreeing_bins": int(np.count_nonzero(c["flags"].astype(int) & 1))})
        return out

    # ------------------------------------------------------------------------------ changing
    def _put(self, doc: MaterialDocument, origin: str, *, replace: bool) -> None:
        text = json.dumps(doc.to_json(), allow_nan=False)
        with self._con:  # one transaction
            self._con.execute("BEGIN IMMEDIATE")
            exists = self._con.execute("SELECT 1 FROM materials WHERE name=?", (doc.name,)).fetchone()
            if exists and not replace:
                raise InputError(f"the library already has a material {doc.name!r} (replace it with --replace, or "
                                 "choose another name)")
            self._con.execute("INSERT OR REPLACE INTO materials VALUES (?, ?, ?, ?)",
                              (doc.name, origin, doc.created_utc, text))

    def add(self, name: str, results: Sequence[str | Path], *, notes: str = "", tags: Sequence[str] = (),
            joint: bool = True, replace: bool = False) -> LibraryMaterial:
        """Combine the results directories `results` into the material `name` (trimeter.library.combine)."""
        check_name(name)
        if not results:
            raise InputError("a material needs at least one results directory")
        members = [load(r) for r in results]
        paths = [m.path.resolve() for m in members]
        if len(set(paths)) != len(paths):
            raise InputError("a results directory is listed twice")
        doc = document_of(name, combine(members, joint=joint), [member_record(m) for m in members],
                          notes=notes, tags=tags)
        self._put(doc, "local", replace=replace)
        return self.get(name)

    def annotate(self, name: str, *, notes: str | None = None, add_tags: Sequence[str] = (),
                 remove_tags: Sequence[str] = ()) -> LibraryMaterial:
        m = self.get(name)
        doc = m.document
        if notes is not None:
            doc.notes = notes
        doc.tags = check_tags([t for t in (*doc.tags, *add_tags) if t not in set(remove_tags)])
        self._put(doc, m.origin, replace=True)
        return self.get(name)

    def remove(self, name: str) -> None:
        self.get(name)  # an unknown name is an error, not a silent no-op
        with self._con:
            self._con.execute("DELETE FROM materials WHERE name=?", (name,))

    def export(self, name: str, out_dir: str | Path) -> Path:
        """The material in the open format (trimeter.library.format), its members checked first."""
        m = self.get(name)
        problems = m.missing_members()
        if problems:
            raise InputError(f"material {name!r}: member {problems[0]}"
                             + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")
                             + "; the library keeps the material as it was: add it again from the members that "
                               "exist (library add --replace)")
        return write_material(m.document, out_dir)

    def import_(self, path: str | Path, *, name: str | None = None, replace: bool = False) -> LibraryMaterial:
        """A material exported by `export` (here or in another lab), under its name or `name`."""
        doc = read_material(path)
        if name is not None:
            doc.name = check_name(name)
        self._put(doc, "imported", replace=replace)
        return self.get(doc.name)
