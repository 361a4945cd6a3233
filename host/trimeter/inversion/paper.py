"""`paper`: the inversion of Iser et al. 2022, Sec. 4.3, as written — the baseline of every figure.

The map's grid points are placed at (I_b, I_w, log10 I_c) for the bins' backgrounds, triangulated
(Delaunay, scipy), and (α, σt, g) interpolated linearly (barycentric) on the tetrahedra. For
robustness, `samples` random points in an ε-cube around each measurement (in the same coordinates)
are interpolated and the median taken; several thicknesses pool their samples before the median.
`samples=0` is the plain interpolation.

Per-wavelength backgrounds: the triangulation depends on ρ_b, ρ_w, so one is built per distinct
(ρ_b, ρ_w) pair, rounded to 1e-3 (≈0.1 s each; cached per map), and bins are grouped by pair.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from trimeter.maps.appearance import background_response

_LOG_IC_FLOOR = 1e-12   # I_c below this is treated as this, so log10 stays finite
_RHO_DECIMALS = 3
_CACHE: "OrderedDict[tuple, object]" = OrderedDict()
_CACHE_SIZE = 16


def coordinates(I_b, I_w, I_c) -> np.ndarray:
    """The space the paper triangulates and interpolates in: (I_b, I_w, log10 I_c), shape (N, 3)."""
    return np.column_stack([I_b, I_w, np.log10(np.maximum(I_c, _LOG_IC_FLOOR))])


def _interpolator(amap, rho_b: float, rho_w: float):
    from scipy.interpolate import LinearNDInterpolator

    inscatter = amap.inscatter  # the nodes' I_c include it
    key = (amap.checksum or id(amap), inscatter.checksum if inscatter is not None else None, rho_b, rho_w)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    aa, ss, gg = (v.ravel() for v in np.meshgrid(amap.alpha, amap.sigma_t, amap.g, indexing="ij"))
    # the map's own nodes, straight from its arrays (not evaluated through AppearanceMap.query: the
    # Delaunay of these nearly coplanar points changes with their last bits)
    A, B, C = (v.ravel() for v in (amap.A, amap.B, amap.C))
    I_b, I_w = (background_response(A, B, C, rho) for rho in (rho_b, rho_w))
    I_c = amap.collimated_measured(aa, ss, gg)
    interp = LinearNDInterpolator(coordinates(I_b, I_w, I_c), np.column_stack([aa, ss, gg]))
    _CACHE[key] = interp
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return interp


def paper_samples(amap, I_b, I_w, I_c, rho_b, rho_w, samples=250, epsilon=0.01, seed=0):
    """Interpolated (α, σt, g) for each bin: shape (N, max(samples, 1), 3), NaN outside the hull."""
    I_b, I_w, I_c, rho_b, rho_w = (np.asarray(v, dtype=float) for v in (I_b, I_w, I_c, rho_b, rho_w))
    n = len(I_b)
    k = max(int(samples), 1)
    out = np.full((n, k, 3), np.nan)
    coords = coordinates(I_b, I_w, I_c)
    ok = np.all(np.isfinite(coords), axis=1) & np.isfinite(rho_b) & np.isfinite(rho_w)
    if not ok.any():
        return out
    pairs = np.round(np.column_stack([rho_b, rho_w])[ok], _RHO_DECIMALS)
    unique, group = np.unique(pairs, axis=0, return_inverse=True)
    rows = np.flatnonzero(ok)
    rng = np.random.default_rng(seed)
    for j, (rb, rw) in enumerate(unique):  # one triangulation per distinct background pair
        sel = rows[group.ravel() == j]
        interp = _interpolator(amap, float(rb), float(rw))
        if samples and samples > 0:
            pts = coords[sel][:, None, :] + rng.uniform(-epsilon, epsilon, (len(sel), k, 3))
        else:
            pts = coords[sel][:, None, :]
        out[sel] = interp(pts.reshape(-1, 3)).reshape(len(sel), k, 3)
    return out
