"""The paper's observables per wavelength (I_b, I_w, I_c at the backgrounds ρ_b, ρ_w), with their
standard errors where the capture had a frame spread."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
