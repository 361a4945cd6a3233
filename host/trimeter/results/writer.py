"""One directory per measurement, written completely under a temporary name and then renamed.

    <results root>/<UTC time>[-<label>]/
        measurement.json      what, when, sample, thicknesses, map(s), method, timings, device identity
        calibration.json/.csv the calibration used (diffuse + collimated spectra, ρ_black, flags)
        raw_<setup>[_<ℓ>].csv raw counts: every exposure's mean signal and its dark frame
        reflectances[_<ℓ>].csv I_b, I_w, I_c, ρ_b, ρ_w, capture flags, declared thickness per wavelength
        parameters.csv/.json  α, σt, g with std, flags, the Beer's-law σt (per thickness too, if two)
        figure.png            like the paper's Fig. 10
        medium.xml / .json    a spectral Mitsuba 3 homogeneous medium, ready to render
A crash, a reset or Ctrl-C at any point leaves at most a `.partial-<pid>-<name>` directory, never a
result that looks complete (the rename is the commit; every file is fsynced before it, so the renamed
directory survives a power cut whole). trimeter.results.spool recovers such leftovers.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from trimeter.atomic import atomic_output, atomic_write, fsync_directory
from trimeter.domain.parameters import FitResult
from trimeter.domain import Capture, Measurement

PARAMETER_COLUMNS = FitResult.COLUMNS  # the fit's output columns, declared once in trimeter.inversion


@dataclass(frozen=True)
class Parameters:
    """trimeter.fit's result over the wavelengths it was fitted at (σt in 1/mm; NaN where the fit
    flags a bin unusable). The columns (alpha, sigma_t, g, their stds, flags, sigma_t_beer) are the
    FitResult's own, read through: they are declared once, in trimeter.inversion."""

    wavelengths_nm: np.ndarray
    fit: FitResult
    thickness_mm: float | None = None   # None for a combined estimate

    @classmethod
    def from_fit(cls, wavelengths_nm: ArrayLike, result: FitResult, *,
                 thickness_mm: float | None = None) -> Parameters:
        wavelengths_nm = np.asarray(wavelengths_nm, float)
        if len(result) != len(wavelengths_nm):
            raise ValueError(f"{len(result)} fitted bins for {len(wavelengths_nm)} wavelengths")
        return cls(wavelengths_nm, result, thickness_mm)

    def __getattr__(self, name: str) -> Any:
        # only called for names not found otherwise; the guard keeps copy/replace (no `fit` yet) finite
        if name in PARAMETER_COLUMNS and "fit" in self.__dict__:
            return getattr(self.fit, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def columns(self) -> dict:
        out = {"wavelength_nm": self.wavelengths_nm}
        out.update({name: getattr(self, name) for name in PARAMETER_COLUMNS})
        return out

    def to_json(self) -> dict:
        def clean(a: ArrayLike) -> list[float | None]:
            return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]
        d: dict[str, object] = {"thickness_mm": self.thickness_mm, "wavelength_nm": clean(self.wavelengths_nm)}
        for name in PARAMETER_COLUMNS:
            d[name] = [int(v) for v in self.flags] if name == "flags" else clean(getattr(self, name))
        return d


def write_csv(path: Path, columns: dict) -> None:
    names = list(columns)
    table = np.column_stack([np.asarray(columns[n], dtype=float) for n in names])
    fmt = ["%d" if "flags" in n else "%.8g" for n in names]
    fmt[0] = "%.4f"
    with atomic_output(path) as f:
        np.savetxt(f, table, delimiter=",", header=",".join(names), comments="", fmt=fmt)


def _raw_columns(wavelengths: np.ndarray, capture: Capture) -> dict:
    cols = {"wavelength_nm": wavelengths}
    for i, t in enumerate(capture.integration_times_us):
        cols[f"signal_{int(t)}us"] = capture.signals[i]
        cols[f"dark_{int(t)}us"] = capture.darks[i]
    cols["rate_counts_per_s"] = capture.rate
    return cols


def new_name(label: str | None = None) -> str:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    return f"{stamp}-{label}" if label else stamp


PARTIAL_PREFIX = ".partial-"


def partial_name(final_name: str, pid: int | None = None) -> str:
    """The in-progress name of a results directory; the writer's pid tells a live write from a leftover."""
    return f"{PARTIAL_PREFIX}{os.getpid() if pid is None else pid}-{final_name}"


def write_measurement(root: str | Path, measurement: Measurement, *, label: str | None = None,
                      figure: bool = True, medium: bool = True) -> Path:
    """Write under `root/.partial-<pid>-<name>`, then rename to `root/<name>` (unique); return the final path."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = new_name(label)
    suffix = 1
    while True:
        final = root / (name if suffix == 1 else f"{name}-{suffix}")
        partial = root / partial_name(final.name)
        if not final.exists():
            try:
                partial.mkdir()  # the claim: another thread of this process (another instrument) may want this name
                break
            except FileExistsError:
                pass
        suffix += 1
    try:
        _write_all(partial, measurement, figure=figure, medium=medium)
        _fsync_tree(partial)
        os.rename(partial, final)
    except Exception:
        # A failed write is removed: the caller still holds the measurement (results.spool keeps it). Ctrl-C
        # leaves the partial directory, which the next start moves to the spool.
        shutil.rmtree(partial, ignore_errors=True)
        raise
    fsync_directory(root)
    return final


def _fsync_tree(directory: Path) -> None:
    """Flush every file of a finished directory (some, like the calibration's, are written by others)."""
    for path in directory.iterdir():
        if path.is_file():
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    fsync_directory(directory)


# Upper bounds per file kind for `expected_size_bytes`: a CSV cell is at most ~16 characters, a raw CSV has
# two columns per exposure (at most five with hdr_decades ≤ 4) plus wavelength and rate, and every file
# takes at least one file-system block.
_CELL_BYTES = 16
_BLOCK_BYTES = 4096
_RAW_COLUMNS = 2 * 5 + 2
_FIGURE_BYTES = 2_500_000


def expected_size_bytes(n_bins: int, n_samples: int) -> int:
    """A generous estimate of one results directory's size (`n_samples` thicknesses, `n_bins` wavelengths)."""
    columns = (7                                            # calibration.csv
               + n_samples * (3 * _RAW_COLUMNS + 10)         # raw_*.csv, reflectances*.csv
               + (1 + n_samples) * 9 * 2                     # parameters*.csv, parameters.json
               + 2 * 3)                                      # medium.xml / .json
    files = 6 + 4 * n_samples + n_samples
    return _CELL_BYTES * n_bins * columns + files * _BLOCK_BYTES + _FIGURE_BYTES


def file_tags(thicknesses: Sequence[float | None]) -> list[str]:
    """File-name suffixes per sample: none for one, `_0.4mm` per thickness, `_2_0.4mm` if one repeats."""
    if len(thicknesses) < 2:
        return [""] * len(thicknesses)
    unique = len(set(thicknesses)) == len(thicknesses)
    return [f"_{t:g}mm" if unique else f"_{i + 1}_{t:g}mm" for i, t in enumerate(thicknesses)]


def _write_all(out: Path, m: Measurement, *, figure: bool, medium: bool) -> None:
    tags = file_tags(m.thicknesses_mm)
    m.calibration.save(out)
    for capture, tag in zip(m.captures, tags, strict=True):
        for setup in ("black", "white", "collimated"):
            write_csv(out / f"raw_{setup}{tag}.csv",
                      _raw_columns(capture.raw.wavelengths_nm, getattr(capture.raw, setup)))
        # the declared thickness travels with the capture: `trimeter fit --input` this file checks its map by it
        columns = capture.reflectances.as_columns()
        columns["thickness_mm"] = np.full(len(columns["wavelength_nm"]), capture.sample.thickness_mm)
        write_csv(out / f"reflectances{tag}.csv", columns)
    write_csv(out / "parameters.csv", m.parameters.columns())
    for p, tag in zip(m.per_thickness, file_tags([p.thickness_mm for p in m.per_thickness]), strict=True):
        write_csv(out / f"parameters{tag}.csv", p.columns())
    atomic_write(out / "parameters.json", json.dumps(
        {"combined": m.parameters.to_json(), "per_thickness": [p.to_json() for p in m.per_thickness]}, indent=1))
    meta = m.record()
    meta["written_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    meta["thicknesses_mm"] = m.thicknesses_mm
    if figure:
        from trimeter.results.figure import plot_parameters

        plot_parameters(out / "figure.png", m.parameters, m.per_thickness,
                        title=m.provenance.sample_name or m.provenance.label or "")
        meta["figure"] = "figure.png"
    if medium:
        from trimeter.results.medium import write_medium

        meta["medium"] = write_medium(out, m.parameters)
    atomic_write(out / "measurement.json", json.dumps(meta, indent=2, default=str))
