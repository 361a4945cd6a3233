"""One set-up's HDR-merged spectrum (`Capture`) and a sample's three set-ups (`RawSample`)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


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
