"""`paper`: the inversion of Iser et al. 2022, Sec. 4.3, as written — the baseline of every figure.

The map's grid points are placed at (I_b, I_w, log10 I_c) for the bins' backgrounds, triangulated
(Delaunay, scipy), and (α, σt, g) interpolated linearly (barycentric) on the tetrahedra. For
robustness, `samples` random points in an ε-cube around each measurement (in the same coordinates)
are interpolated and the median taken; several thicknesses pool their samples before the median.
`samples=0` is the plain interpolation.

Per-wavelength backgrounds: the triangulation depends on ρ_b, ρ_w, so one is built per distinct
(ρ_b, ρ_w) pair, rounded to 1e-3 (≈0.1 s each; cached per map), and bins are grouped by pair.

Memory: the ε-samples take ~27 KB per bin at 250 samples, so `paper_medians` works through the bins
in chunks of CHUNK_POINTS interpolated points and keeps only the medians: bounded whatever the row
count. Bin r's ε-offsets are draws r·3k … (r+1)·3k − 1 of one PCG64 stream, so the result does not
depend on the chunk size.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict

import numpy as np

from trimeter.maps.appearance import background_response

_LOG_IC_FLOOR = 1e-12   # I_c below this is treated as this, so log10 stays finite
_RHO_DECIMALS = 3
_CACHE: "OrderedDict[tuple, object]" = OrderedDict()
_CACHE_SIZE = 16
CHUNK_POINTS = 500_000  # interpolated points per chunk: ~60 MB of working arrays


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


def paper_samples(amap, I_b, I_w, I_c, rho_b, rho_w, samples=250, epsilon=0.01, seed=0, first_row=0):
    """Interpolated (α, σt, g) for each bin: shape (N, max(samples, 1), 3), NaN outside the hull.
    `first_row`: the bins' position in the whole input (which ε-offsets of the seed's stream are theirs)."""
    I_b, I_w, I_c, rho_b, rho_w = (np.asarray(v, dtype=float) for v in (I_b, I_w, I_c, rho_b, rho_w))
    n = len(I_b)
    k = max(int(samples), 1)
    out = np.full((n, k, 3), np.nan)
    coords = coordinates(I_b, I_w, I_c)
    ok = np.all(np.isfinite(coords), axis=1) & np.isfinite(rho_b) & np.isfinite(rho_w)
    if not ok.any():
        return out
    pts = coords[:, None, :]
    if samples and samples > 0:  # PCG64 draws one 64-bit word per double: bin r's offsets start at word 3k·r
        stream = np.random.Generator(np.random.PCG64(seed).advance(3 * k * int(first_row)))
        pts = pts + stream.uniform(-epsilon, epsilon, (n, k, 3))
    pairs = np.round(np.column_stack([rho_b, rho_w])[ok], _RHO_DECIMALS)
    unique, group = np.unique(pairs, axis=0, return_inverse=True)
    rows = np.flatnonzero(ok)
    for j, (rb, rw) in enumerate(unique):  # one triangulation per distinct background pair
        sel = rows[group.ravel() == j]
        interp = _interpolator(amap, float(rb), float(rw))
        out[sel] = interp(np.broadcast_to(pts[sel], (len(sel), k, 3)).reshape(-1, 3)).reshape(len(sel), k, 3)
    return out


def paper_medians(amaps, inputs, samples=250, epsilon=0.01, seed=0, chunk_points=CHUNK_POINTS):
    """The ε-median (α, σt, g) of each bin, (N, 3): pooled over the maps (several thicknesses of one
    material) and each map's own, for inputs[i] = (I_b, I_w, I_c, rho_b, rho_w) over the same N bins
    for amaps[i] (map i samples with seed + i). Bins are processed in chunks of about `chunk_points`
    interpolated points, so memory does not grow with N beyond the (N, 3) results."""
    n = len(inputs[0][0])
    k = max(int(samples), 1)
    chunk = max(1, int(chunk_points) // (k * len(amaps)))
    pooled = np.full((n, 3), np.nan)
    own = [np.full((n, 3), np.nan) for _ in amaps]
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        parts = [paper_samples(amap, *(np.asarray(v)[start:stop] for v in arrays), samples=samples, epsilon=epsilon,
                               seed=seed + i, first_row=start)
                 for i, (amap, arrays) in enumerate(zip(amaps, inputs, strict=True))]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins: outside the hull, flagged by the caller
            pooled[start:stop] = np.nanmedian(np.concatenate(parts, axis=1), axis=1)
            for median, part in zip(own, parts, strict=True):
                median[start:stop] = np.nanmedian(part, axis=1)
    return pooled, own
