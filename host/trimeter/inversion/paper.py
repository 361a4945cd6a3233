"""`paper`: the inversion of Iser et al. 2022, Sec. 4.3, as written — the baseline of every figure.

The map's grid points are placed at (I_b, I_w, log10 I_c) for the bins' backgrounds, triangulated
(Delaunay, scipy), and (α, σt, g) interpolated linearly (barycentric) on the tetrahedra. For
robustness, `samples` random points in an ε-cube around each measurement (in the same coordinates)
are interpolated and the median taken; several thicknesses pool their samples before the median.
`samples=0` is the plain interpolation.

Per-wavelength backgrounds: the triangulation depends on ρ_b, ρ_w, so one is built per distinct
(ρ_b, ρ_w) pair, rounded to 1e-3 (≈0.1 s each; kept in the map's artifacts' cache, `cache` below),
and bins are grouped by pair.

Memory: the ε-samples take ~27 KB per bin at 250 samples, so `paper_medians` works through the bins
in chunks of CHUNK_POINTS interpolated points and keeps only the medians: bounded whatever the row
count. Bin r's ε-offsets are draws r·3k … (r+1)·3k − 1 of one PCG64 stream, so the result does not
depend on the chunk size.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Sequence

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.parameters import FitResult
from trimeter.inversion import finish
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.strategy import Method
from trimeter.model.response import background_response

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.fit_model import FitModel
    from trimeter.inversion.kernel import Kernel
    from scipy.interpolate import LinearNDInterpolator

_LOG_IC_FLOOR = 1e-12   # I_c below this is treated as this, so log10 stays finite
_RHO_DECIMALS = 3
CACHE_SIZE = 16  # triangulations kept per map
CHUNK_POINTS = 500_000  # interpolated points per chunk: ~60 MB of working arrays


def coordinates(I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray) -> np.ndarray:
    """The space the paper triangulates and interpolates in: (I_b, I_w, log10 I_c), shape (N, 3)."""
    return np.column_stack([I_b, I_w, np.log10(np.maximum(I_c, _LOG_IC_FLOOR))])


def interpolator(amap: AppearanceMap, rho_b: float, rho_w: float,
                 cache: OrderedDict[tuple[float, float], LinearNDInterpolator] | None = None) -> LinearNDInterpolator:
    """The paper's interpolant of `amap` (its nodes, arrays A, B, C and collimated_measured) at these
    backgrounds; `cache`: the map's triangulations by (ρ_b, ρ_w), least recently used dropped first."""
    from scipy.interpolate import LinearNDInterpolator

    cache = OrderedDict() if cache is None else cache
    key = (rho_b, rho_w)
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    aa, ss, gg = (v.ravel() for v in np.meshgrid(amap.alpha, amap.sigma_t, amap.g, indexing="ij"))
    # the map's own nodes, straight from its arrays (not evaluated through AppearanceMap.query: the
    # Delaunay of these nearly coplanar points changes with their last bits)
    A, B, C = (v.ravel() for v in (amap.A, amap.B, amap.C))
    I_b, I_w = (background_response(A, B, C, rho) for rho in (rho_b, rho_w))
    I_c = amap.collimated_measured(aa, ss, gg)  # with the map's in-scattering, if it has a table
    interp = LinearNDInterpolator(coordinates(I_b, I_w, I_c), np.column_stack([aa, ss, gg]))
    cache[key] = interp
    if len(cache) > CACHE_SIZE:
        cache.popitem(last=False)
    return interp


def background_pairs(rho_b: np.ndarray, rho_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct (ρ_b, ρ_w) pairs as the triangulations are keyed (rounded), and each bin's pair's index;
    non-finite pairs are left out (those bins cannot be placed)."""
    pairs = np.round(np.column_stack([rho_b, rho_w]), _RHO_DECIMALS)
    unique, group = np.unique(pairs[np.all(np.isfinite(pairs), axis=1)], axis=0, return_inverse=True)
    return unique, group.ravel()


def triangulated_nodes(amap: AppearanceMap, rho_b: ArrayLike, rho_w: ArrayLike) -> int:
    """What a fit of these bins' backgrounds costs before any bin is placed: one Delaunay triangulation of
    the map's nodes per distinct background pair, counted in nodes triangulated."""
    unique, _ = background_pairs(np.asarray(rho_b, dtype=float), np.asarray(rho_w, dtype=float))
    return len(unique) * int(np.size(amap.alpha) * np.size(amap.sigma_t) * np.size(amap.g))


def paper_samples(amap: AppearanceMap, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
                  rho_w: np.ndarray, samples: int = 250, epsilon: float = 0.01, seed: int = 0, first_row: int = 0,
                  cache: OrderedDict[tuple[float, float], LinearNDInterpolator] | None = None) -> np.ndarray:
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
    unique, group = background_pairs(rho_b[ok], rho_w[ok])
    rows = np.flatnonzero(ok)
    for j, (rb, rw) in enumerate(unique):  # one triangulation per distinct background pair
        sel = rows[group == j]
        interp = interpolator(amap, float(rb), float(rw), cache)
        out[sel] = interp(np.broadcast_to(pts[sel], (len(sel), k, 3)).reshape(-1, 3)).reshape(len(sel), k, 3)
    return out


def paper_medians(amaps: Sequence[AppearanceMap], inputs: Sequence[tuple[np.ndarray, ...]], samples: int = 250,
                  epsilon: float = 0.01, seed: int = 0, chunk_points: int = CHUNK_POINTS,
                  caches: Sequence[OrderedDict[tuple[float, float], LinearNDInterpolator] | None] | None = None,
                  first_row: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """The ε-median (α, σt, g) of each bin, (N, 3): pooled over the maps (several thicknesses of one
    material) and each map's own, for inputs[i] = (I_b, I_w, I_c, rho_b, rho_w) over the same N bins
    for amaps[i] (map i samples with seed + i). Bins are processed in chunks of about `chunk_points`
    interpolated points, so memory does not grow with N beyond the (N, 3) results. caches: one
    triangulation cache per map (interpolator), or None. first_row: the bins' position in a larger input
    fitted in parts (their samples are then those of a fit of the whole)."""
    n = len(inputs[0][0])
    caches = [OrderedDict() for _ in amaps] if caches is None else caches
    k = max(int(samples), 1)
    chunk = max(1, int(chunk_points) // (k * len(amaps)))
    pooled = np.full((n, 3), np.nan)
    own = [np.full((n, 3), np.nan) for _ in amaps]
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        parts = [paper_samples(amap, *_rows(arrays, start, stop), samples=samples, epsilon=epsilon,
                               seed=seed + i, first_row=first_row + start, cache=caches[i])
                 for i, (amap, arrays) in enumerate(zip(amaps, inputs, strict=True))]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins: outside the hull, flagged by the caller
            pooled[start:stop] = np.nanmedian(np.concatenate(parts, axis=1), axis=1)
            for median, part in zip(own, parts, strict=True):
                median[start:stop] = np.nanmedian(part, axis=1)
    return pooled, own


Rows = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _rows(arrays: tuple[np.ndarray, ...], start: int, stop: int) -> Rows:
    """(I_b, I_w, I_c, rho_b, rho_w) of bins start…stop."""
    I_b, I_w, I_c, rho_b, rho_w = (np.asarray(v)[start:stop] for v in arrays)
    return I_b, I_w, I_c, rho_b, rho_w


def fit_paper(models: list[FitModel], arrays: list[tuple[np.ndarray, ...]], stds: list[np.ndarray],
              thickness_rel: list[float], *, kernel: Kernel, samples: int, epsilon: float, seed: int,
              noise_rel: float, noise_abs: float, ic_floor: float, alpha_min_g: float,
              inscatter_rel_std: float, first_row: int = 0) -> FitResult:
    """The paper method over all thicknesses (trimeter.inversion.api.fit's arguments, shaped): each
    thickness's flags and stds on its own ε-median, the estimate on the pooled one."""
    amaps = [m.map for m in models]
    inputs, singles = [], []
    for amap, (I_b, I_w, I_c, rho_b, rho_w) in zip(amaps, arrays, strict=True):
        flags = finish.input_flags(I_b, I_w, I_c, rho_b, rho_w)
        usable = (flags & int(UNUSABLE)) == 0
        inputs.append((np.where(usable, I_b, np.nan), I_w, I_c, rho_b, rho_w))
        singles.append((amap, flags, usable, I_b, I_w, I_c, rho_b, rho_w))
    pooled_median, own_medians = paper_medians(amaps, inputs, samples=samples, epsilon=epsilon, seed=seed,
                                               caches=[m.paper_cache for m in models], first_row=first_row)
    results = []
    # Each thickness on its own median (the consistency check), the estimate on the pooled one.
    for i, (med, model, (amap, flags, usable, I_b, I_w, I_c, rho_b, rho_w)) in enumerate(
            zip(own_medians, models, singles, strict=True)):
        grid = model.grid
        ib, iw, ic = finish.sanitize(I_b, 0, 1, 0), finish.sanitize(I_w, 0, 1, 1), finish.sanitize(I_c, 0, 1, 1)
        ref = amap.reference_rhos
        rb, rw = np.where(usable, rho_b, ref[0]), np.where(usable, rho_w, ref[1])
        flags = flags | np.where(usable & (ic < ic_floor), int(FitFlag.IC_BELOW_FLOOR), 0)
        outside = usable & ~np.all(np.isfinite(med), axis=1)
        flags |= np.where(outside, int(FitFlag.OUTSIDE_MAP) | int(FitFlag.NOT_CONVERGED), 0)
        alpha, sigma_t, g = med[:, 0], med[:, 1], med[:, 2]
        coef_in = np.isfinite(alpha)
        I_model = grid.intensities(np.nan_to_num(alpha), np.nan_to_num(sigma_t, nan=1.0), np.nan_to_num(g), rb, rw)
        residual = np.where(coef_in, np.hypot(I_model[0] - ib, I_model[1] - iw), np.inf)
        sigma_beer = model.setup.beer_lambert_sigma_t(I_c)
        floor_sd = np.column_stack([noise_rel * ib + noise_abs, noise_rel * iw + noise_abs, noise_rel * ic + noise_abs])
        sd = stds[i] if stds[i] is not None else floor_sd
        # the ε-median has no separate in-scattering correction to propagate: its map's I_c holds it.
        # The interpolated median does not solve the map exactly: STD_APPROXIMATE's re-fits start from
        # the map's own intensities there, so that its residual does not count as the map's bend.
        r = finish.finish(grid, flags, usable, ib, iw, ic, rb, rw, alpha, sigma_t, g, residual, sigma_beer,
                    method="paper", kernel=kernel, sd=sd, sigma_t_solved=sigma_t, inscatter_ds=None,
                    inscatter_rel_std=inscatter_rel_std, thickness_rel_std=thickness_rel[i], alpha_min_g=alpha_min_g,
                    solved=(alpha, g, I_model[0], I_model[1]), floor_sd=floor_sd)
        for name in ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std"):
            getattr(r, name)[outside] = np.nan
        results.append(r)
    if len(results) == 1:
        return results[0]
    combined = finish.combine(results, "paper")
    # As written: the pooled median is the estimate; the stds come from the inverse-variance combination.
    med = pooled_median
    combined.alpha, combined.sigma_t, combined.g = med[:, 0], med[:, 1], med[:, 2]
    combined.g = np.where((combined.flags & int(FitFlag.G_UNDEFINED)) != 0, np.nan, combined.g)
    return combined


METHOD = Method("paper", "Iser et al. 2022 as written: Delaunay + linear interpolation, the ε-median (the baseline)",
                fit_all=fit_paper, default_polish=0,
                bench_variants=(("", dict(samples=0)), ("-median", dict(samples=250, epsilon=0.01))))
