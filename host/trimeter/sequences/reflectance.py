"""Raw spectra → calibration → reflectances, exactly as the paper's Sec. 4.2 defines them.

Calibration (no sample, all rates dark-subtracted, in counts/s):
    diffuse(λ)    = white(λ) / ρ_white_ref          (ρ_white_ref: hardware/geometry.toml, 0.99)
    ρ_black(λ)    = black(λ) / diffuse(λ)
    collimated(λ) = open slot, collimated LED
Sample:
    I_b = black_sample / diffuse,  I_w = white_sample / diffuse,  I_c = collimated_sample / collimated
and the map is queried at the measured backgrounds ρ_b = ρ_black(λ), ρ_w = ρ_white_ref.

Bad bins never raise: a bin that saturated in every exposure, read NaN, or had no reference light
gets NaN (and a CaptureFlag bit); the fit flags NaN inputs as unusable.
"""

from __future__ import annotations

import enum
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from trimeter.errors import InputError
from trimeter.sequences import lamp_monitor

CALIBRATION_FORMAT_VERSION = 1
MIN_REFERENCE_FRACTION = 1e-3   # reference rate below this fraction of its median: no usable light in that bin


class CaptureFlag(enum.IntFlag):
    NONE = 0
    SATURATED = 1 << 0          # every exposure of this bin saturated
    NONFINITE = 1 << 1          # the spectrometer returned NaN/inf
    NO_REFERENCE_LIGHT = 1 << 2  # the calibration saw (almost) no light in this bin: ratios meaningless


@dataclass
class Capture:
    """One set-up, HDR-merged: rate in counts/s per bin (NaN where unusable) and what it came from."""

    rate: np.ndarray
    saturated: np.ndarray
    integration_times_us: np.ndarray
    signals: np.ndarray = field(repr=False)   # (exposures, bins) mean counts
    darks: np.ndarray = field(repr=False)
    rate_std: np.ndarray | None = field(default=None, repr=False)  # standard error of `rate` (frame spread)
    lamp_monitor: dict | None = field(default=None, repr=False)  # lamp_monitor.record() of this set-up

    def relative_std(self) -> np.ndarray:
        if self.rate_std is None:
            return np.full_like(self.rate, np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.abs(self.rate_std / self.rate)

    def flags(self) -> np.ndarray:
        out = np.where(self.saturated, int(CaptureFlag.SATURATED), 0)
        out |= np.where(~np.isfinite(self.rate) & ~self.saturated, int(CaptureFlag.NONFINITE), 0)
        return out.astype(np.int32)


@dataclass
class RawSample:
    wavelengths_nm: np.ndarray
    black: Capture
    white: Capture
    collimated: Capture
    device_time_s: float = 0.0
    lamp_monitor: dict = field(default_factory=dict)  # set-up → lamp_monitor.record(), incl. "dark"


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
    device: dict = field(default_factory=dict)    # identity of the instrument it was taken on
    lamp_monitor: dict = field(default_factory=dict)  # set-up → lamp_monitor.record(): the lamps' references

    @classmethod
    def from_captures(cls, wavelengths_nm, captures: dict, *, white_reference_reflectance: float,
                      device_time_s: float = 0.0, spectrometer: dict | None = None,
                      device: dict | None = None, lamp_monitor: dict | None = None) -> "Calibration":
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
                   white.relative_std(), coll.relative_std(), dark_counts, dict(device or {}),
                   dict(lamp_monitor or {}))

    # -------------------------------------------------------------------------------- files
    def save(self, directory: str | Path) -> Path:
        """calibration.json (meta) + calibration.csv (per bin); written next to each other."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        meta = {"format_version": CALIBRATION_FORMAT_VERSION, "rho_white": self.rho_white,
                "device_time_s": self.device_time_s, "created_utc": self.created_utc,
                "spectrometer": self.spectrometer, "bins": int(len(self.wavelengths_nm)),
                "dark_counts": None if not np.isfinite(self.dark_counts) else self.dark_counts, "device": self.device,
                "lamp_monitor": self.lamp_monitor}
        (directory / "calibration.json").write_text(json.dumps(meta, indent=2))
        nan = np.full_like(self.diffuse, np.nan)
        table = np.column_stack([self.wavelengths_nm, self.diffuse, self.collimated, self.rho_black, self.flags,
                                 nan if self.diffuse_rel_std is None else self.diffuse_rel_std,
                                 nan if self.collimated_rel_std is None else self.collimated_rel_std])
        np.savetxt(directory / "calibration.csv", table, delimiter=",",
                   fmt=["%.4f", "%.8g", "%.8g", "%.8g", "%d", "%.4g", "%.4g"],
                   header="wavelength_nm,diffuse_counts_per_s,collimated_counts_per_s,rho_black,flags,"
                          "diffuse_rel_std,collimated_rel_std", comments="")
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> "Calibration":
        directory = Path(directory)
        try:
            meta = json.loads((directory / "calibration.json").read_text())
            table = np.loadtxt(directory / "calibration.csv", delimiter=",", skiprows=1, ndmin=2)
        except FileNotFoundError:
            raise InputError(f"no calibration in {directory}: run `trimeter calibrate` with the holder empty") from None
        except (ValueError, json.JSONDecodeError) as exc:
            raise InputError(f"calibration in {directory} is corrupt ({exc}); run `trimeter calibrate` again") from None
        if not isinstance(meta, dict) or meta.get("format_version") != CALIBRATION_FORMAT_VERSION \
                or table.shape[1] != 7 or table.shape[0] != meta.get("bins"):
            raise InputError(f"calibration in {directory} has an unknown format or is truncated; calibrate again")
        try:
            dark = meta.get("dark_counts")
            return cls(table[:, 0], table[:, 1], table[:, 2], table[:, 3], float(meta["rho_white"]),
                       table[:, 4].astype(np.int32), float(meta.get("device_time_s", 0.0)),
                       str(meta.get("created_utc", "")), dict(meta.get("spectrometer") or {}), table[:, 5],
                       table[:, 6], float("nan") if dark is None else float(dark), dict(meta.get("device") or {}),
                       dict(meta.get("lamp_monitor") or {}))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"calibration in {directory} has a bad field ({exc}); calibrate again") from None


@dataclass
class Reflectances:
    wavelengths_nm: np.ndarray
    I_b: np.ndarray
    I_w: np.ndarray
    I_c: np.ndarray
    rho_b: np.ndarray
    rho_w: np.ndarray
    flags: np.ndarray   # CaptureFlag per bin
    I_b_std: np.ndarray | None = None   # standard errors from the frame-to-frame spread (sample and reference)
    I_w_std: np.ndarray | None = None
    I_c_std: np.ndarray | None = None
    lamp_light: dict | None = None      # the lamps during the shot against the calibration (lamp_monitor)

    def as_columns(self) -> dict:
        cols = {"wavelength_nm": self.wavelengths_nm, "I_b": self.I_b, "I_w": self.I_w, "I_c": self.I_c,
                "rho_b": self.rho_b, "rho_w": self.rho_w, "capture_flags": self.flags}
        for name in ("I_b_std", "I_w_std", "I_c_std"):
            if getattr(self, name) is not None:
                cols[name] = getattr(self, name)
        return cols

    def noise_rel(self) -> float | None:
        """Median relative standard error of I_b and I_w over the usable bins (for the fit's noise model)."""
        if self.I_w_std is None or self.I_b_std is None:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.concatenate([self.I_b_std / self.I_b, self.I_w_std / self.I_w])
        rel = rel[np.isfinite(rel)]
        return float(np.median(rel)) if rel.size else None


# A bin's frame spread comes from a few frames (settings.frames, default 2: one degree of freedom), so
# its own std is a poor estimate of its noise: a ±1σ from it covers far less than 68 % (Student's t).
# The noise level changes slowly with wavelength (shot and read noise of a smooth spectrum), so each
# bin takes the mean relative variance of this many neighbours (~5 nm here): tens of degrees of freedom.
STD_POOL_BINS = 15
# The part of a lamp's drift since the calibration that the monitor's correction leaves, relative to the
# correction (see lamp_correction): a warming white LED dims by a few % and its phosphor shifts by 1-2 nm
# (paper Sec. 4.2; the twin's Led model), so on the flanks of the pump's and the phosphor's peaks a
# bin's light moves about as much as the dimming the photodiode sees, and near their centres hardly.
LAMP_SPECTRAL_REL = 1.0


def pooled_relative_std(rel_std) -> np.ndarray:
    """Relative stds pooled over STD_POOL_BINS neighbouring bins (root of their mean square, NaN bins
    left out and left NaN)."""
    rel = np.asarray(rel_std, dtype=float)
    ok = np.isfinite(rel)
    kernel = np.ones(min(STD_POOL_BINS, max(len(rel), 1)))
    total = np.convolve(np.where(ok, rel * rel, 0.0), kernel, mode="same")
    count = np.convolve(ok.astype(float), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, np.sqrt(total / count), np.nan)


def lamp_correction(light: dict | None, setup: str) -> tuple[float, float]:
    """(fraction, its relative std) of the calibrated light the lamps of one set-up gave during its shot,
    from the lamp monitor (lamp_monitor.relative_light): the mean of its open lamps' readings (after the
    shutters settled and after the last exposure: the exposures lie between them). The shot is divided
    by the fraction; its std is half the readings' range (how far the light moved during the shot), in
    quadrature with the part of a drift the photodiodes cannot see: a warming LED's spectrum also shifts,
    which a broadband photodiode does not tell from dimming (LAMP_SPECTRAL_REL of the correction).
    (1, 0) without readings or when they cannot be compared (the shot checks refuse those)."""
    if not light or "error" in light or setup not in light:
        return 1.0, 0.0
    entry = light[setup]
    readings = [f for lamp, values in entry["fractions"].items()
                if (entry["collimated"] if lamp == "collimated" else entry["panels"]) for f in values]
    values = np.asarray(readings, dtype=float)
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values <= lamp_monitor.DEAD_FRACTION):
        return 1.0, 0.0
    fraction = float(values.mean())
    spread = 0.5 * float(values.max() - values.min()) / fraction
    return fraction, float(np.hypot(spread, LAMP_SPECTRAL_REL * abs(fraction - 1.0)))


def reflectances(calibration: Calibration, sample: RawSample) -> Reflectances:
    """The paper's ratios, vectorised over bins; unusable bins become NaN with a flag, never an error."""
    if len(sample.wavelengths_nm) != len(calibration.wavelengths_nm) or not np.allclose(
            sample.wavelengths_nm, calibration.wavelengths_nm, rtol=0, atol=1e-3):
        raise InputError("the calibration was taken with another spectrometer or wavelength set: calibrate again")
    flags = calibration.flags | sample.black.flags() | sample.white.flags() | sample.collimated.flags()
    light = lamp_monitor.relative_light(calibration.lamp_monitor, sample.lamp_monitor)
    (f_b, d_b), (f_w, d_w), (f_c, d_c) = (lamp_correction(light, key) for key in ("black", "white", "collimated"))
    with np.errstate(invalid="ignore", divide="ignore"):
        i_b = sample.black.rate / calibration.diffuse / f_b
        i_w = sample.white.rate / calibration.diffuse / f_w
        i_c = sample.collimated.rate / calibration.collimated / f_c
    bad = flags != 0
    nan = np.float64("nan")

    def std(value, capture, reference_rel, lamp_rel):
        if reference_rel is None or capture.rate_std is None:
            return None
        with np.errstate(invalid="ignore"):
            rel = np.hypot(np.hypot(pooled_relative_std(capture.relative_std()), pooled_relative_std(reference_rel)),
                           lamp_rel)
            return np.where(bad, nan, np.abs(value) * rel)

    return Reflectances(calibration.wavelengths_nm.copy(), np.where(bad, nan, i_b), np.where(bad, nan, i_w),
                        np.where(bad, nan, i_c), calibration.rho_black.copy(),
                        np.full_like(calibration.rho_black, calibration.rho_white), flags.astype(np.int32),
                        std(i_b, sample.black, calibration.diffuse_rel_std, d_b),
                        std(i_w, sample.white, calibration.diffuse_rel_std, d_w),
                        std(i_c, sample.collimated, calibration.collimated_rel_std, d_c), light)
