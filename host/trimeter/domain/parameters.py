"""The fitted parameters: α, σt, g per wavelength bin with their standard deviations and flags."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FitResult:
    """α, σt [1/mm], g with per-bin standard deviations and FitFlag words (trimeter.inversion.flags),
    over the input bins."""
    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray
    alpha_std: np.ndarray
    sigma_t_std: np.ndarray
    g_std: np.ndarray
    flags: np.ndarray
    sigma_t_beer: np.ndarray        # the consistency column: σt from I_c alone (paper Eq. 2)
    method: str
    per_thickness: list = field(default_factory=list)  # FitResult per map when several were given
    # α's and g's std with the intensities' stds at least the noise model's: what UNDERDETERMINED is
    # judged on (None: the stds above)
    conditioning_alpha_std: np.ndarray | None = None
    conditioning_g_std: np.ndarray | None = None
    # bins where the method's own first guess (the MLP's) was not finite and the table's was used instead:
    # their result is the lut fit's, whatever method is named (over all thicknesses when several)
    guess_fallback_bins: int = 0

    COLUMNS = ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "flags", "sigma_t_beer")

    def __len__(self) -> int:
        return len(self.alpha)

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.COLUMNS}

