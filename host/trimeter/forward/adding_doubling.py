"""Prahl's adding-doubling (iadpython) for the `ideal` geometry: exact for an infinite slab on a Lambertian
background under uniform hemispherical light, seen along the normal. It makes the small test maps and the
ideal held-out sets, never a shipped map; iadpython is a dev dependency the device side does not have.

Per material, `Sample(a=α, b=σt·ℓ, g, d=ℓ, n, n_above=1, n_below=1).rt()` gives (UR1, UT1, URU, UTU), and
I(ρ) = A + Bρ/(1 − Cρ) with A = UR1, B = UT1·UTU, C = URU (see trimeter.formats.appearance).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from trimeter.errors import BuildError

# iadpython's default of 4 quadrature points is too few behind an n = 1.5 boundary (clear and dark turbid slabs
# come out visibly off); 32 agree with twice as many to below a map's Monte Carlo std-error
# (tests/forward/test_adding_doubling.py checks it), and iadpython itself breaks down far above that.
IAD_QUAD_POINTS = 32


def ideal_abc(alpha: ArrayLike, sigma_t: ArrayLike, g: ArrayLike, *, thickness_mm: float, n: float,
              quad_points: int = IAD_QUAD_POINTS) -> np.ndarray:
    """Exact (A, B, C) per material as a (count, 3) array from flat α, σt [1/mm], g."""
    try:
        from iadpython import Sample
    except ImportError as exc:
        raise BuildError("adding-doubling needs iadpython (pip install 'trimeter[dev]')") from exc
    alpha, sigma_t, g = np.broadcast_arrays(*(np.asarray(v, dtype=float).ravel() for v in (alpha, sigma_t, g)))
    out = np.empty((alpha.size, 3))
    for i, (a, s, gi) in enumerate(zip(alpha, sigma_t, g, strict=True)):  # iadpython is scalar per material
        ur1, ut1, uru, utu = Sample(a=float(a), b=float(s) * thickness_mm, g=float(gi), d=thickness_mm,
                                    n=n, n_above=1, n_below=1, quad_pts=quad_points).rt()
        out[i] = (ur1, ut1 * utu, uru)
    return out
