"""Re-fitting a stored measurement with another map or method: a new results directory, the original untouched.

The capture is read back from the original's files (calibration, raw spectra, reflectances), fitted
again and written by the results writer like any measurement, so the new record is complete and
atomic; its measurement.json names the record it came from (`refit_of`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from trimeter.errors import InputError, OutputError
from trimeter.inversion.api import METHODS
from trimeter.inversion.flags import advice
from trimeter.maps.appearance import AppearanceMap
from trimeter.results import Measurement
from trimeter.results.writer import _tags as file_tags, write_measurement
from trimeter.sequences.measure import check_map_thicknesses, fit_reflectances, preflight
from trimeter.sequences.reflectance import Calibration, Capture, RawSample, Reflectances

SETUPS = ("black", "white", "collimated")


def read_columns(path: Path) -> dict[str, np.ndarray]:
    """A results CSV (one header line of names, then numbers) as columns."""
    try:
        with open(path) as f:
            names = f.readline().strip().split(",")
            table = np.loadtxt(f, delimiter=",", ndmin=2)
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path.name}: cannot be read back ({exc})") from None
    if table.shape[1] != len(names):
        raise InputError(f"{path.name}: {table.shape[1]} columns for {len(names)} names")
    return {name: table[:, i] for i, name in enumerate(names)}


def _capture(columns: dict) -> Capture:
    times = [int(n[len("signal_"):-2]) for n in columns if n.startswith("signal_") and n.endswith("us")]
    rate = columns["rate_counts_per_s"]
    return Capture(rate=rate, saturated=np.zeros(rate.shape, bool), integration_times_us=np.asarray(times, float),
                   signals=np.stack([columns[f"signal_{t}us"] for t in times]),
                   darks=np.stack([columns[f"dark_{t}us"] for t in times]))


def _reflectances(columns: dict) -> Reflectances:
    return Reflectances(columns["wavelength_nm"], columns["I_b"], columns["I_w"], columns["I_c"], columns["rho_b"],
                        columns["rho_w"], columns["capture_flags"].astype(np.int32),
                        *(columns.get(name) for name in ("I_b_std", "I_w_std", "I_c_std")))


def load_capture(directory: Path) -> tuple[Calibration, list[RawSample], list[Reflectances], dict]:
    """(calibration, raw samples, reflectances, measurement.json) of a results directory."""
    try:
        meta = json.loads((directory / "measurement.json").read_text())
        thicknesses = [float(t) for t in meta["thicknesses_mm"]]
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise InputError(f"{directory.name}: its measurement.json cannot be read ({exc})") from None
    calibration = Calibration.load(directory)
    raws, refls = [], []
    try:
        for tag in file_tags(thicknesses):
            captures = {s: _capture(read_columns(directory / f"raw_{s}{tag}.csv")) for s in SETUPS}
            refl = _reflectances(read_columns(directory / f"reflectances{tag}.csv"))
            raws.append(RawSample(refl.wavelengths_nm, **captures))
            refls.append(refl)
    except KeyError as exc:
        raise InputError(f"{directory.name}: a capture file lacks the column {exc}") from None
    return calibration, raws, refls, meta


def refit(directory: Path, maps: list[AppearanceMap], method: str) -> Path:
    """Fit `directory`'s capture again with `maps` (one per thickness) and `method`; write a new results
    directory beside it and return its path."""
    if method not in METHODS:
        raise InputError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    calibration, raws, refls, meta = load_capture(directory)
    declared = meta.get("declared_thicknesses_mm") or meta["thicknesses_mm"]
    if len(maps) != len(refls):
        raise InputError(f"{len(maps)} map(s) for {len(refls)} measured thickness(es)")
    check_map_thicknesses(declared, maps)
    preflight(maps, method)
    combined, per = fit_reflectances(refls, maps, method=method)
    new_meta = {key: value for key, value in meta.items()
                if key not in ("written_utc", "figure", "medium", "timing", "advice", "link")}
    new_meta.update({"method": method, "maps": [m.name for m in maps], "map_checksums": [m.checksum for m in maps],
                     "map_thicknesses_mm": [m.thickness_mm for m in maps], "refit_of": directory.name,
                     "advice": advice(combined.flags, len(maps))})
    try:
        return write_measurement(directory.parent, Measurement(calibration, raws, refls, [float(t) for t in
                                                               meta["thicknesses_mm"]], combined, per, meta=new_meta),
                                 label=meta.get("label") or None)
    except OSError as exc:
        raise OutputError(f"the re-fit could not be written to {directory.parent} ({exc})") from None
