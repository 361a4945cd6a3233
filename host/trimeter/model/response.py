"""The background response: how a slab's diffuse observable depends on the background behind it."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

# The reference backgrounds of a map recipe unless it names its own (black, white): where a map's
# std-errors are reported; where a bounce series' return coefficient is matched (trimeter.forward.transport).
REFERENCE_RHOS = (0.02, 0.9)


def background_response(A: np.ndarray | float, B: np.ndarray | float, C: np.ndarray | float,
                        rho: ArrayLike) -> np.ndarray:
    """I(ρ) = A + B·ρ / (1 − C·ρ): the diffuse observable against a Lambertian background of
    reflectance ρ (A: the slab's own reflectance, B: T_down·T_up, C: the slab's diffuse reflectance
    seen from below; exact for the ideal geometry, verified against renders for the device)."""
    rho = np.asarray(rho, dtype=float)
    return A + B * rho / (1.0 - C * rho)
