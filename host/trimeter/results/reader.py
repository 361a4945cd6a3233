"""The one reader of a results directory (what trimeter.results.writer writes): `trimeter.load(path)`.

    >>> m = trimeter.load("results/20260101T120000Z-cyan")
    >>> m.wavelength_nm, m.alpha, m.alpha_std          # numpy arrays over wavelength
    >>> m.advice                                       # what to do about flagged bins
    >>> m.export(to="mitsuba")                         # files for a renderer

measurement.json and parameters.json are read when the directory is loaded; the calibration, the raw
spectra and the reflectances when first asked for. Every file is read only if it is a regular file (not
a symbolic link, a FIFO or a device) within MAX_RESULT_FILE_BYTES; anything else, and a directory that
is missing, foreign or damaged, is an InputError naming the file.
"""

from __future__ import annotations

import json
import math
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.domain import Calibration, Capture, Provenance, RawSample, Reflectances
from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.tables import MAX_RESULT_FILE_BYTES, open_checked, read_columns, read_text
from trimeter.results.export import LoadedResult, loaded_parameters
from trimeter.results.medium import SpectralMaterial
from trimeter.results.writer import PARAMETER_COLUMNS, Parameters, file_tags

MEASUREMENT_FILE = "measurement.json"
PARAMETERS_FILE = "parameters.json"
CALIBRATION_FILES = ("calibration.json", "calibration.csv")
SETUPS = ("black", "white", "collimated")
ESSENTIAL_COLUMNS = ("wavelength_nm", "alpha", "sigma_t", "g")   # what any parameters.json has


def _json_file(path: Path) -> Any:
    try:
        return json.loads(read_text(path, max_bytes=MAX_RESULT_FILE_BYTES, follow_symlinks=False))
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: not JSON ({exc})") from None


def _results_dir(path: str | Path) -> Path:
    directory = Path(path)
    if not directory.exists():
        raise InputError(f"{directory}: no such results directory")
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory (a results directory holds {MEASUREMENT_FILE}, "
                         f"{PARAMETERS_FILE}, …)")
    if not (directory / MEASUREMENT_FILE).exists() and not (directory / MEASUREMENT_FILE).is_symlink():
        raise InputError(f"{directory}: not a trimeter results directory (no {MEASUREMENT_FILE})")
    return directory


def read_record(path: str | Path) -> dict[str, Any]:
    """The measurement.json of the results directory `path`, as written (an object); InputError when
    the directory is not one or the file is damaged."""
    directory = _results_dir(path)
    record = _json_file(directory / MEASUREMENT_FILE)
    if not isinstance(record, dict):
        raise InputError(f"{directory / MEASUREMENT_FILE}: does not hold an object")
    return record


def json_numbers(values: object, name: str, path: Path) -> np.ndarray:
    """A JSON list of numbers (null: NaN) as a float array."""
    if not isinstance(values, list):
        raise InputError(f"{path}: {name} must be a list of numbers")
    out = np.empty(len(values))
    for i, v in enumerate(values):
        if v is None:
            out[i] = math.nan
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[i] = float(v)
        else:
            raise InputError(f"{path}: {name}[{i}] is not a number")
    return out


def parameters_from_json(doc: object, path: Path, method: str = "") -> Parameters:
    """One estimate of a parameters.json ({"wavelength_nm": […], "alpha": […], …, "thickness_mm": …})."""
    if not isinstance(doc, dict):
        raise InputError(f"{path}: an estimate must be an object")
    missing = [k for k in ESSENTIAL_COLUMNS if k not in doc]
    if missing:
        raise InputError(f"{path}: an estimate lacks {', '.join(missing)}")
    columns = {k: json_numbers(doc[k], k, path) for k in ("wavelength_nm", *PARAMETER_COLUMNS) if k in doc}
    if len({len(v) for v in columns.values()}) != 1:
        raise InputError(f"{path}: the columns of an estimate differ in length")
    n = len(columns["wavelength_nm"])
    for name in PARAMETER_COLUMNS:  # an older writer's file: what it did not record is unknown (NaN, no flags)
        columns.setdefault(name, np.zeros(n) if name == "flags" else np.full(n, math.nan))
    flags = columns.pop("flags")
    if not np.all(np.isfinite(flags)) or np.any(flags != np.round(flags)) or np.any(flags < 0) \
            or np.any(flags >= 2.0**63):  # beyond an int64 word: no FitFlag value, and astype would wrap it
        raise InputError(f"{path}: flags must be non-negative integer words (below 2**63)")
    thickness = doc.get("thickness_mm")
    if thickness is not None and not (isinstance(thickness, (int, float)) and not isinstance(thickness, bool)
                                      and math.isfinite(thickness) and thickness > 0):
        raise InputError(f"{path}: thickness_mm must be a positive number or null")
    wavelengths = columns.pop("wavelength_nm")
    result = FitResult(columns["alpha"], columns["sigma_t"], columns["g"], columns["alpha_std"],
                       columns["sigma_t_std"], columns["g_std"], flags.astype(np.int64), columns["sigma_t_beer"],
                       method)
    return Parameters.from_fit(wavelengths, result, thickness_mm=None if thickness is None else float(thickness))


def read_parameters(path: str | Path, method: str = "") -> tuple[Parameters, list[Parameters]]:
    """(combined, per thickness) of a results directory's parameters.json (per thickness: empty for one)."""
    file = _results_dir(path) / PARAMETERS_FILE
    if not file.exists() and not file.is_symlink():
        raise InputError(f"{file}: missing (the directory is not a complete results directory)")
    doc = _json_file(file)
    if not isinstance(doc, dict) or "combined" not in doc:
        raise InputError(f"{file}: expected an object with 'combined' and 'per_thickness'")
    per = doc.get("per_thickness") or []
    if not isinstance(per, list):
        raise InputError(f"{file}: per_thickness must be a list")
    return parameters_from_json(doc["combined"], file, method), [parameters_from_json(p, file, method) for p in per]


def _capture(columns: dict[str, np.ndarray], path: Path) -> Capture:
    """One setup's exposures from its raw_*.csv (signal_<t>us, dark_<t>us per integration time, rate)."""
    times = [n[len("signal_"):-2] for n in columns if n.startswith("signal_") and n.endswith("us")]
    try:
        rate = columns["rate_counts_per_s"]
        return Capture(rate=rate, saturated=np.zeros(rate.shape, bool),
                       integration_times_us=np.asarray([float(t) for t in times]),
                       signals=np.stack([columns[f"signal_{t}us"] for t in times]),
                       darks=np.stack([columns[f"dark_{t}us"] for t in times]))
    except KeyError as exc:
        raise InputError(f"{path}: lacks the column {exc}") from None
    except ValueError:
        raise InputError(f"{path}: no signal_<time>us columns with their dark_<time>us") from None


REFLECTANCE_COLUMNS = ("wavelength_nm", "I_b", "I_w", "I_c", "rho_b", "rho_w", "capture_flags")
REFLECTANCE_STDS = ("I_b_std", "I_w_std", "I_c_std")
REFLECTANCE_OPTIONAL = (*REFLECTANCE_STDS, "thickness_mm")  # the declared thickness (older results lack it)


def _reflectances(path: Path) -> Reflectances:
    c = read_columns(path, required=REFLECTANCE_COLUMNS, optional=REFLECTANCE_OPTIONAL, follow_symlinks=False)
    return Reflectances(c["wavelength_nm"], c["I_b"], c["I_w"], c["I_c"], c["rho_b"], c["rho_w"],
                        np.nan_to_num(c["capture_flags"]).astype(np.int32), c.get("I_b_std"), c.get("I_w_std"),
                        c.get("I_c_std"))


class Measurement:
    """A results directory read back: `trimeter.load(path)`.

    The fitted parameters over wavelength (the combined estimate when two thicknesses were measured;
    each thickness's own in `per_thickness`) are numpy arrays of the same length as `wavelength_nm`:
    `alpha` (single-scattering albedo), `sigma_t` (extinction coefficient, 1/mm), `g` (Henyey-Greenstein
    anisotropy), their standard deviations `alpha_std`, `sigma_t_std`, `g_std` (NaN where none was
    computed), `sigma_t_beer` (σt from the collimated transmittance alone, a consistency check) and
    `flags` (trimeter.inversion.flags.FitFlag words per bin, 0: nothing to report; `flag_names` spells
    them out, `advice` says what to do about them). NaN marks a bin the fit could not use.

    Attributes
    ----------
    path : pathlib.Path
        The results directory.
    record : dict
        Its measurement.json as written (sample, label, method, maps, timing, device, …).
    parameters : trimeter.results.Parameters
        The (combined) estimate the arrays above come from.
    per_thickness : list of trimeter.results.Parameters
        One estimate per measured thickness when there were two or more, else empty.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = _results_dir(path)
        self.record = read_record(self.path)
        thicknesses = self.record.get("thicknesses_mm")
        if not (isinstance(thicknesses, list) and thicknesses and all(
                isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t > 0
                for t in thicknesses)):
            raise InputError(f"{self.path / MEASUREMENT_FILE}: thicknesses_mm must be a list of positive numbers")
        self._thicknesses = [float(t) for t in thicknesses]
        self.parameters, self.per_thickness = read_parameters(self.path, str(self.record.get("method") or ""))

    def __repr__(self) -> str:
        return (f"<trimeter.Measurement {self.path.name}: {len(self.wavelength_nm)} bins, "
                f"{'+'.join(f'{t:g}' for t in self.thicknesses_mm)} mm, method {self.method or '?'}>")

    # ----------------------------------------------------------------------- what was measured
    @property
    def name(self) -> str:
        """The directory's name (its UTC time stamp and label): the measurement's id in the web page."""
        return self.path.name

    @property
    def sample(self) -> str | None:
        """What was measured, when named."""
        value = self.record.get("sample")
        return value if isinstance(value, str) else None

    @property
    def label(self) -> str | None:
        value = self.record.get("label")
        return value if isinstance(value, str) else None

    @property
    def method(self) -> str:
        """The inversion method (lut, mlp or paper)."""
        return str(self.record.get("method") or "")

    @property
    def maps(self) -> list[str]:
        """The appearance maps or device tables fitted with, one per thickness."""
        value = self.record.get("maps")
        return [str(v) for v in value] if isinstance(value, list) else []

    @property
    def thicknesses_mm(self) -> list[float]:
        """The sample thicknesses measured (mm), one per sample."""
        return list(self._thicknesses)

    @property
    def thickness_mm(self) -> float:
        """The thickness when one sample was measured; ValueError for several (see thicknesses_mm)."""
        if len(self._thicknesses) != 1:
            raise ValueError(f"{len(self._thicknesses)} thicknesses were measured: see thicknesses_mm")
        return self._thicknesses[0]

    @property
    def written_utc(self) -> str | None:
        value = self.record.get("written_utc")
        return value if isinstance(value, str) else None

    @cached_property
    def provenance(self) -> Provenance:
        """How the measurement came about (method, label, instrument, timing, advice, re-fit origin, …)."""
        return Provenance.from_record(self.record)

    # ----------------------------------------------------------------------- the parameters
    @property
    def wavelength_nm(self) -> np.ndarray:
        """The wavelength of each bin, nm."""
        return self.parameters.wavelengths_nm

    @property
    def alpha(self) -> np.ndarray:
        """Single-scattering albedo per bin."""
        return self.parameters.fit.alpha

    @property
    def sigma_t(self) -> np.ndarray:
        """Extinction coefficient per bin, 1/mm."""
        return self.parameters.fit.sigma_t

    @property
    def g(self) -> np.ndarray:
        """Henyey-Greenstein anisotropy per bin."""
        return self.parameters.fit.g

    @property
    def alpha_std(self) -> np.ndarray:
        """Standard deviation of alpha per bin."""
        return self.parameters.fit.alpha_std

    @property
    def sigma_t_std(self) -> np.ndarray:
        """Standard deviation of sigma_t per bin, 1/mm."""
        return self.parameters.fit.sigma_t_std

    @property
    def g_std(self) -> np.ndarray:
        """Standard deviation of g per bin."""
        return self.parameters.fit.g_std

    @property
    def sigma_t_beer(self) -> np.ndarray:
        """σt from the collimated transmittance alone (Beer-Lambert), 1/mm: a consistency check."""
        return self.parameters.fit.sigma_t_beer

    @property
    def flags(self) -> np.ndarray:
        """FitFlag words per bin (trimeter.inversion.flags; 0: nothing to report)."""
        return self.parameters.fit.flags

    @property
    def flag_names(self) -> list[str]:
        """Each bin's flags by name, e.g. 'IC_BELOW_FLOOR|G_UNDEFINED' ('NONE' for none)."""
        from trimeter.inversion.flags import describe

        return [describe(int(f)) for f in self.flags]

    @property
    def advice(self) -> list[str]:
        """What to do about the flagged bins: one sentence per kind of problem (empty when nothing)."""
        from trimeter.inversion.flags import advice

        return advice(self.flags, len(self._thicknesses))

    def parameters_document(self) -> dict:
        """parameters.json's content ({"combined": …, "per_thickness": […]}) as the writer wrote it."""
        return {"combined": self.parameters.to_json(), "per_thickness": [p.to_json() for p in self.per_thickness]}

    # ----------------------------------------------------------------------- the capture
    def _file(self, name: str) -> Path:
        return self.path / name

    @cached_property
    def calibration(self) -> Calibration:
        """The calibration the measurement used (diffuse and collimated reference spectra, ρ_black, flags)."""
        for name in CALIBRATION_FILES:  # the same checks as every other file, before Calibration reads them
            open_checked(self._file(name), max_bytes=MAX_RESULT_FILE_BYTES, follow_symlinks=False).close()
        return Calibration.load(self.path)

    @cached_property
    def reflectances(self) -> list[Reflectances]:
        """Per thickness: I_b, I_w, I_c, the backgrounds ρ_b, ρ_w and the capture flags per wavelength."""
        return [_reflectances(self._file(f"reflectances{tag}.csv")) for tag in file_tags(self._thicknesses)]

    @cached_property
    def raw(self) -> list[RawSample]:
        """Per thickness: the raw counts (every exposure's signal and dark frame) of the black, white and
        collimated set-ups."""
        out = []
        for tag in file_tags(self._thicknesses):
            captures: dict[str, Capture] = {}
            wavelengths: np.ndarray | None = None
            for setup in SETUPS:
                path = self._file(f"raw_{setup}{tag}.csv")
                columns = read_columns(path, required=("wavelength_nm", "rate_counts_per_s"), follow_symlinks=False)
                if wavelengths is not None and not np.array_equal(columns["wavelength_nm"], wavelengths):
                    raise InputError(f"{path}: not over the wavelengths of raw_{SETUPS[0]}{tag}.csv")
                wavelengths = columns["wavelength_nm"]
                captures[setup] = _capture(columns, path)
            assert wavelengths is not None
            out.append(RawSample(wavelengths, black=captures["black"], white=captures["white"],
                                 collimated=captures["collimated"]))
        return out

    # ----------------------------------------------------------------------- onward
    def material(self) -> Any:
        """The measured material (trimeter.results.medium.SpectralMaterial: the bins with finite α, σt, g)."""
        from trimeter.results.medium import SpectralMaterial

        try:
            return SpectralMaterial.from_parameters(self.parameters)
        except InputError as exc:
            raise InputError(f"{self.path}: {exc}") from None

    def export(self, to: str, out_dir: str | Path | None = None, **options: Any) -> dict:
        """Write the material for a renderer: `to` one of mitsuba, pbrt, blender, rgb (trimeter.results.export).

        Parameters
        ----------
        to : str
            The format.
        out_dir : str or Path, optional
            Where to write; default: `export-<to>` inside the results directory.
        **options
            step_nm, reference_thickness_mm (default: the measured thickness), illuminant, scene_unit_mm.

        Returns
        -------
        dict
            The provenance written beside the files (its "files" lists them).
        """
        from trimeter.results.export import export

        result = loaded_measurement(self)
        options.setdefault("reference_thickness_mm", result.measured_thickness_mm() or 1.0)
        return export(result, to, self.path / f"export-{to}" if out_dir is None else out_dir, **options)


def load(path: str | Path) -> Measurement:
    """Read the results directory `path` (what `trimeter measure`, the button or the web page wrote).

    Parameters
    ----------
    path : str or Path
        The results directory (e.g. ``results/20260101T120000Z-cyan``).

    Returns
    -------
    Measurement
        Its parameters as numpy arrays over wavelength, flags and advice, provenance; the calibration,
        reflectances and raw spectra on first use.

    Raises
    ------
    trimeter.errors.InputError
        The directory is missing, not a results directory, or one of its files is damaged, too large,
        a symbolic link or not a regular file.
    """
    return Measurement(path)


# ------------------------------------------------------------- what an export takes: a material and its origin
PARAMETER_NAMES = ("wavelength_nm", "alpha", "sigma_t", "g")
SOURCE_KEYS = ("sample", "label", "method", "maps", "map_checksums", "thicknesses_mm", "written_utc", "device")


def loaded_measurement(m: Measurement) -> LoadedResult:
    """A results directory read by trimeter.load, as an export takes it."""
    source: dict = {"path": str(m.path.resolve()), "measurement": m.name}
    source.update({k: m.record[k] for k in SOURCE_KEYS if k in m.record})
    if m.parameters.thickness_mm is not None:
        source["thickness_mm"] = m.parameters.thickness_mm
    return loaded_parameters(m.parameters, source, m.path / "parameters.json")


def _from_json(path: Path) -> tuple[SpectralMaterial, dict]:
    try:
        doc = json.loads(read_text(path, max_bytes=MAX_RESULT_FILE_BYTES))
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: not JSON ({exc})") from None
    if isinstance(doc, dict) and isinstance(doc.get("combined"), dict):     # a results directory's parameters.json
        doc = doc["combined"]
    elif isinstance(doc, dict) and isinstance(doc.get("columns"), dict):    # `trimeter fit --json`'s output
        doc = {**doc["columns"], "thickness_mm": doc.get("thickness_mm")}
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected an object with wavelength_nm, alpha, sigma_t, g")
    columns = {k: json_numbers(doc[k], k, path) for k in PARAMETER_NAMES if k in doc}
    return _material_of_columns(columns, path), {"thickness_mm": doc.get("thickness_mm")}


def _from_csv(path: Path) -> tuple[SpectralMaterial, dict]:
    columns = read_columns(path, optional=PARAMETER_NAMES, max_bytes=MAX_RESULT_FILE_BYTES, min_rows=2)
    return _material_of_columns(columns, path), {}


def _material_of_columns(columns: dict, path: Path) -> SpectralMaterial:
    missing = [k for k in PARAMETER_NAMES if k not in columns]
    if missing:
        raise InputError(f"{path}: no {', '.join(missing)} column (a trimeter parameters file has wavelength_nm, "
                         "alpha, sigma_t, g)")
    if len({len(v) for v in columns.values()}) != 1:
        raise InputError(f"{path}: columns of different lengths")
    return loaded_parameters(_Columns(columns), {}, path).material


class _Columns:
    """Columns of a parameters CSV, as SpectralMaterial.from_parameters reads them."""

    def __init__(self, columns: dict) -> None:
        self.wavelengths_nm, self.alpha = columns["wavelength_nm"], columns["alpha"]
        self.sigma_t, self.g = columns["sigma_t"], columns["g"]


def load_result(path: str | Path) -> LoadedResult:
    """The material of a measurement directory or a parameters file, with what is known of its origin."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such measurement directory or parameters file")
    if path.is_dir():
        return loaded_measurement(load(path))
    material, extra = _from_json(path) if path.suffix.lower() == ".json" else _from_csv(path)
    source = {"path": str(path.resolve())}
    source.update({k: v for k, v in extra.items() if v is not None})
    return LoadedResult(material, source)
