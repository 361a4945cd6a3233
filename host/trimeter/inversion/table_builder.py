"""Building a map's device table (the `.tlut` file, trimeter.formats.device_table): build_from_map and the
inverse grid it stores. It sits with the inversion because that grid is the `lut` method's own first guess,
polished by the inversion's Newton kernel; the map pipeline's tlut stage (trimeter.maps.pipeline) and a fit
from a map without a current `.tlut` (trimeter.inversion.artifacts) both build it here.

The inverse grid: for each σt node of a forward grid, (α, g) over a regular (u, v) grid in [0, 1]², where
(u, v) is an affine image of (x, y) = (√I_b, √I_w) at the reference backgrounds, aligned with that
slice's gamut (its principal axes), so the grid covers the gamut tightly. The codes are u16:
α = α_0 + (α_last − α_0) · q / 65535, likewise g.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from trimeter.errors import MapFileError
from trimeter.formats.appearance import AppearanceMap, map_model_variance
from trimeter.formats.device_table import MAX_BYTES, MIN_NODES, DeviceTable, geometry_bytes, table_size
from trimeter.inversion.kernel import default_kernel
from trimeter.model.cells import refine_axis
from trimeter.model.grid import ForwardGrid

_Q = 65535.0


def _quantize(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    scaled = np.round((np.asarray(values, dtype=np.float64) - lo) / max(hi - lo, 1e-30) * _Q)
    return np.clip(np.nan_to_num(scaled, nan=0.0), 0, _Q).astype(np.uint16)


def inverse_grid(grid: ForwardGrid, nxy: int, reference_rhos: tuple[float, float]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse slices of a forward grid at the reference backgrounds, as a map table stores them:
    (frames f32 (ns, 6), α codes u16 (ns, nxy, nxy), g codes u16 (ns, nxy, nxy)).

    For each σt node, (α, g) at every (x, y) = (√I_b, √I_w) grid point of the slice's bounding box.
    Start from the nearest of a dense forward sample (the grid's axes refined), then polish with the
    forward kernel's Newton solve, so stored entries are the map's own inverse (projected onto the
    gamut where a grid point lies outside it)."""
    from scipy.spatial import cKDTree

    rho_b, rho_w = reference_rhos
    alpha_axis, log_s_axis, g_axis = grid.alpha, grid.log_sigma_t, grid.g
    ns = len(log_s_axis)
    aa, gg = (v.ravel() for v in np.meshgrid(refine_axis(alpha_axis, 2), refine_axis(g_axis, 2), indexing="ij"))
    frames = np.zeros((ns, 6), dtype=np.float32)
    starts_a, starts_g = np.zeros((ns, nxy, nxy)), np.zeros((ns, nxy, nxy))
    targets = np.zeros((ns, nxy, nxy, 2))
    uv = np.linspace(0.0, 1.0, nxy)
    for k in range(ns):  # one KD-tree per σt node (build time only)
        cell = grid.sigma_cell(np.full(aa.shape, np.exp(log_s_axis[k])))
        coef, _, _ = grid.coefficients(aa, cell, gg)
        xy = np.sqrt(np.clip(np.column_stack([grid.diffuse(coef, rho_b)[0], grid.diffuse(coef, rho_w)[0]]), 0, None))
        frame = _gamut_frame(xy)
        frames[k] = frame
        uu, vv = np.meshgrid(uv, uv)  # (n_y, n_x): u along x-index, v along y-index
        gxy = _from_frame(frames[k].astype(np.float64), uu.ravel(), vv.ravel())
        _, nearest = cKDTree(xy).query(gxy)
        starts_a[k] = aa[nearest].reshape(nxy, nxy)
        starts_g[k] = gg[nearest].reshape(nxy, nxy)
        targets[k] = (np.clip(gxy, 0, 1) ** 2).reshape(nxy, nxy, 2)
    node = np.broadcast_to(np.exp(log_s_axis)[:, None, None], (ns, nxy, nxy)).ravel()
    m = node.size
    alpha_sol, g_sol, _, _ = default_kernel().solve_alpha_g(
        grid, targets[..., 0].ravel(), targets[..., 1].ravel(), grid.sigma_cell(node), np.full(m, rho_b),
        np.full(m, rho_w), starts_a.ravel(), starts_g.ravel(), iterations=12)
    inv_a = _quantize(alpha_sol, alpha_axis[0], alpha_axis[-1]).reshape(ns, nxy, nxy)
    inv_g = _quantize(g_sol, g_axis[0], g_axis[-1]).reshape(ns, nxy, nxy)
    return frames, inv_a, inv_g


def _gamut_frame(xy: np.ndarray) -> np.ndarray:
    """(x0, y0, m00, m01, m10, m11): the affine map taking the point cloud's principal-axes bounding
    box onto [0, 1]², u along the major axis."""
    centre = xy.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((xy - centre).T) + 1e-18 * np.eye(2))
    rot = vecs[:, ::-1].T  # rows: major, minor axis
    proj = (xy - centre) @ rot.T
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    span = np.maximum(hi - lo, 1e-7)
    m = rot / span[:, None]
    origin = centre + rot.T @ lo  # the point mapping to (u, v) = (0, 0)
    return np.array([origin[0], origin[1], m[0, 0], m[0, 1], m[1, 0], m[1, 1]])


def _from_frame(frame: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Inverse of the frame: (u, v) → (x, y), shape (N, 2)."""
    m = frame[2:].reshape(2, 2)
    return frame[:2] + np.column_stack([u, v]) @ np.linalg.inv(m).T


# A map without the device's in-scattering (an ideal map) stores the smallest all-zero section: no correction.
_NO_INSCATTER: tuple[np.ndarray, tuple[float, float, float], dict[str, Any]] = (
    np.zeros((2, 2, 2)), (1.0, 1.0, 1.0), {})


def largest_inverse_side(na: int, ns: int, ng: int, inscatter_shape: tuple[int, int, int], geometry_len: int) -> int:
    """The largest inverse grid side that fits the slot with these counts (MapFileError: none does)."""
    fits = [k for k in range(2, 129) if table_size(na, ns, ng, k, *inscatter_shape, geometry_len) <= MAX_BYTES]
    if not fits:
        raise MapFileError(f"a {na}×{ns}×{ng} map does not fit the {MAX_BYTES}-byte slot")
    return max(fits)


def too_coarse(amap: AppearanceMap) -> str | None:
    """Why a map cannot have a device table (too few nodes for its splines), or None."""
    shape = amap.A.shape
    if any(n < least for n, least in zip(shape, MIN_NODES, strict=True)):
        return (f"a device table needs at least {MIN_NODES[0]} α, {MIN_NODES[1]} σt and {MIN_NODES[2]} g nodes; "
                f"the map has {shape[0]}×{shape[1]}×{shape[2]}")
    return None


def build_from_map(amap: AppearanceMap, n_inverse: int | None = None) -> DeviceTable:
    """The device table of an AppearanceMap and its in-scattering table (.tins, when the map has one);
    n_inverse: the inverse grid's side (default: the largest that fits the slot)."""
    if why := too_coarse(amap):
        raise MapFileError(f"map {amap.name}: {why}")
    tins = amap.inscatter
    if tins is None:
        L, ends, geometry = _NO_INSCATTER
        tins_sha = ""
    else:
        if abs(tins.n - amap.n) > 1e-6 or abs(tins.thickness_mm - amap.thickness_mm) > 1e-6:
            raise MapFileError(f"{amap.name}: its .tins was traced for n {tins.n}, ℓ {tins.thickness_mm}, the map "
                               f"is for n {amap.n}, ℓ {amap.thickness_mm}")
        L, ends, geometry = tins.L, (tins.u_max, tins.tau_max, tins.v_max), tins.geometry_params
        tins_sha = tins.checksum or ""
    na, ns, ng = amap.A.shape
    geometry_len = len(geometry_bytes(geometry))
    nu, nt, nv = L.shape
    if n_inverse is None:
        n_inverse = largest_inverse_side(na, ns, ng, (nu, nt, nv), geometry_len)
    elif n_inverse < 2 or table_size(na, ns, ng, n_inverse, nu, nt, nv, geometry_len) > MAX_BYTES:
        raise MapFileError(f"an inverse grid of {n_inverse}×{n_inverse} is below 2×2 or does not fit the "
                           f"{MAX_BYTES}-byte slot")
    # the inverse slices over the map's own σt nodes, the axes the table stores
    frames, inv_a, inv_g = inverse_grid(ForwardGrid.from_map(amap), n_inverse, amap.reference_rhos)
    var, _axes = map_model_variance(amap)
    return DeviceTable.build(
        name=amap.name, parent_sha256=amap.checksum or "", inscatter_sha256=tins_sha, n=amap.n,
        thickness_mm=amap.thickness_mm, cover_slide_n=amap.cover_slide_n, reference_rhos=amap.reference_rhos,
        mc_stderr=float(np.median(np.concatenate([amap.std_b.ravel(), amap.std_w.ravel()]))),
        alpha=amap.alpha, log_sigma_t=np.log(amap.sigma_t), g=amap.g, nodes=np.stack([amap.A, amap.B, amap.C], -1),
        model_std=np.sqrt(var), inscatter_L=L, inscatter_ends=ends, inv_frame=frames, inv_alpha_q=inv_a,
        inv_g_q=inv_g, geometry=geometry)
