"""The inverse grid of a device table (trimeter.maps.device_table, the `.tlut` file): the `lut` method's
first guess, for each σt node of a forward grid, of (α, g) over a regular (u, v) grid in [0, 1]², where
(u, v) is an affine image of (x, y) = (√I_b, √I_w) at the reference backgrounds, aligned with that
slice's gamut (its principal axes), so the grid covers the gamut tightly. The codes are u16:
α = α_0 + (α_last − α_0) · q / 65535, likewise g.
"""

from __future__ import annotations

import numpy as np

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

    from trimeter.inversion.kernel import default_kernel

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
