"""The instrument's calibration (no sample, all rates dark-subtracted, in counts/s; paper Sec. 4.2):
    diffuse(λ)    = white(λ) / ρ_white_ref          (ρ_white_ref: hardware/geometry.toml, 0.99)
    ρ_black(λ)    = black(λ) / diffuse(λ)
    collimated(λ) = open slot, collimated LED
with its files: calibration.json (meta) + calibration.csv (per bin).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.capture import Capture, CaptureFlag
from trimeter.domain.instrument import InstrumentInfo
from trimeter.errors import InputError
from trimeter.tables import read_columns, read_text

CALIBRATION_FORMAT_VERSION = 1
CALIBRATION_COLUMNS = ("wavelength_nm", "diffuse_counts_per_s", "collimated_counts_per_s", "rho_black", "flags",
                       "diffuse_rel_std", "collimated_rel_std")
MIN_REFERENCE_FRACTION = 1e-3   # reference rate below this fraction of its median: no usable light in that bin


def _reference_ok(rate: np.ndarray) -> np.ndarray:
    finite = np.isfinite(rate)
    if not finite.any():
        return finite
    scale = np.nanmedian(np.abs(rate[finite]))
    return finite & (rate > MIN_REFERENCE_FRACTION * max(scale, 1e-30))


@dataclass
class Calibration:
    wavelengths_nm: np.ndarray
    diffuse: np.ndarray           # counts/s of the diffuse illumination (white / ρ_white_ref)
    collimated: np.ndarray        # counts/s of the collimated beam
    rho_black: np.ndarray         # black background reflectance per bin
    rho_white: float              # white reference reflectance (declared, hardware/geometry.toml)
    flags: np.ndarray             # CaptureFlag per bin
    device_time_s: float = 0.0    # device uptime when it finished (staleness, reset detection)
    created_utc: str = ""
    spectrometer: dict = field(default_factory=dict)
    diffuse_rel_std: np.ndarray | None = None     # relative standard errors (frame spread)
    collimated_rel_std: np.ndarray | None = None
    dark_counts: float = float("nan")   # median dark frame (every shutter closed), counts
    device: InstrumentInfo | None = None          # the instrument it was taken on
    lamp_monitor: dict = field(default_factory=dict)  # set-up → lamp_monitor.record(): the lamps' references

    @classmethod
    def from_captures(cls, wavelengths_nm: ArrayLike, captures: dict[str, Capture], *,
                      white_reference_reflectance: float, device_time_s: float = 0.0, spectrometer: dict | None = None,
                      device: InstrumentInfo | None = None, lamp_monitor: dict | None = None) -> "Calibration":
        white, black, coll = captures["white"], captures["black"], captures["collimated"]
        flags = white.flags() | black.flags() | coll.flags()
        diffuse = white.rate / white_reference_reflectance
        no_light = ~_reference_ok(diffuse) | ~_reference_ok(coll.rate)
        flags |= np.where(no_light, int(CaptureFlag.NO_REFERENCE_LIGHT), 0).astype(np.int32)
        with np.errstate(invalid="ignore", divide="ignore"):
            rho_black = np.where(no_light, np.nan, black.rate / diffuse)
        darks = np.concatenate([c.darks.ravel() for c in (white, black, coll)])
        dark_counts = float(np.nanmedian(darks)) if np.isfinite(darks).any() else float("nan")
        return cls(np.asarray(wavelengths_nm, float), np.where(no_light, np.nan, diffuse),
                   np.where(no_light, np.nan, coll.rate), rho_black, float(white_reference_reflectance),
                   flags.astype(np.int32), float(device_time_s),
                   datetime.now(timezone.utc).isoformat(timespec="seconds"), dict(spectrometer or {}),
                   white.relative_std(), coll.relative_std(), dark_counts, device,
                   dict(lamp_monitor or {}))

    # -------------------------------------------------------------------------------- files
    def save(self, directory: str | Path) -> Path:
        """calibration.json (meta) + calibration.csv (per bin); written next to each other."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        meta = {"format_version": CALIBRATION_FORMAT_VERSION, "rho_white": self.rho_white,
                "device_time_s": self.device_time_s, "created_utc": self.created_utc,
                "spectrometer": self.spectrometer, "bins": int(len(self.wavelengths_nm)),
                "dark_counts": None if not np.isfinite(self.dark_counts) else self.dark_counts,
                "device": {} if self.device is None else self.device.to_json(),
                "lamp_monitor": self.lamp_monitor}
        (directory / "calibration.json").write_text(json.dumps(meta, indent=2))
        nan = np.full_like(self.diffuse, np.nan)
        table = np.column_stack([self.wavelengths_nm, self.diffuse, self.collimated, self.rho_black, self.flags,
                                 nan if self.diffuse_rel_std is None else self.diffuse_rel_std,
                                 nan if self.collimated_rel_std is None else self.collimated_rel_std])
        np.savetxt(directory / "calibration.csv", table, delimiter=",",
                   fmt=["%.4f", "%.8g", "%.8g", "%.8g", "%d", "%.4g", "%.4g"],
                   header=",".join(CALIBRATION_COLUMNS), comments="")
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> "Calibration":
        directory = Path(directory)
        if not all((directory / name).exists() for name in ("calibration.json", "calibration.csv")):
            raise InputError(f"no calibration in {directory}: run `trimeter calibrate` with the holder empty")
        try:
            meta = json.loads(read_text(directory / "calibration.json"))
            table = read_columns(directory / "calibration.csv", required=CALIBRATION_COLUMNS)
        except (ValueError, RecursionError) as exc:  # an InputError of the reader, or not JSON
            raise InputError(f"calibration in {directory} is corrupt ({exc}); run `trimeter calibrate` again") from None
        except OSError as exc:  # a FIFO, a link or a device in place of a file, or unreadable
            raise InputError(f"calibration in {directory} cannot be read ({exc.strerror or exc}: "
                             f"{Path(exc.filename or '').name}); run `trimeter calibrate` again") from None
        if not isinstance(meta, dict) or meta.get("format_version") != CALIBRATION_FORMAT_VERSION \
                or len(table["wavelength_nm"]) != meta.get("bins"):
            raise InputError(f"calibration in {directory} has an unknown format or is truncated; calibrate again")
        try:
            dark = meta.get("dark_counts")
            c = [table[name] for name in CALIBRATION_COLUMNS]
            return cls(c[0], c[1], c[2], c[3], float(meta["rho_white"]),
                       np.nan_to_num(c[4]).astype(np.int32), float(meta.get("device_time_s", 0.0)),
                       str(meta.get("created_utc", "")), dict(meta.get("spectrometer") or {}), c[5],
                       c[6], float("nan") if dark is None else float(dark),
                       InstrumentInfo.from_json(meta.get("device")), dict(meta.get("lamp_monitor") or {}))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"calibration in {directory} has a bad field ({exc}); calibrate again") from None
