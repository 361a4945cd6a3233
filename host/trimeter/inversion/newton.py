"""The numpy reference of the solve (invert.c mirrors it operation for operation): a batched 2×2
damped Gauss-Newton (Levenberg-Marquardt) solve of (I_b, I_w) for (α, g) at a known σt on a
trimeter.model.grid.ForwardGrid, the in-scattering correction and first-order uncertainty propagation.

Why (α, g) at known σt: the unscattered beam, I_c's main part, depends on σt alone
(trimeter.model.collimated), so the square 3×3 system's solution takes σt from I_c (Beer-Lambert with
Fresnel, exact inverse) and leaves two equations in two unknowns. The light scattered into the
detector's aperture (trimeter.model.inscatter) depends on α and g too: with a map's in-scattering
table, σt and then (α, g) are corrected for it once (α, g) are solved, to first order
(correct_inscatter). No Python loop per bin: every step is a gather + array arithmetic.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from trimeter.inversion import native
from trimeter.model.grid import ForwardGrid, SigmaCell

def solve_alpha_g(grid: ForwardGrid, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell, rho_b: np.ndarray,
                  rho_w: np.ndarray, alpha0: np.ndarray, g0: np.ndarray, iterations: int = 5, step_tol: float = 0.0,
                  step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Damped Gauss-Newton for (α, g) with I_b, I_w matched at the bins' own ρ_b, ρ_w. Steps are
    projected onto the map's box (hold_at_edges) and clamped to it. At most `iterations` steps; a
    bin stops once a step was small in both α and g: at most `step_tol`, or (with step_var, per bin (κ σ_I)², see
    polish_step_var) below κ of that parameter's noise std, where further steps only move it
    along what the data cannot tell apart. step_tol 0 and no step_var: every bin takes every
    step. Returns (α, g, residual norm, Jacobian at the solution). Where a bin's polish ended on
    a small step within one cell of the map, these come from that step's evaluation (no
    evaluation more): its Jacobian, a step below κ of the noise std from the solution, and its
    residuals carried along the step taken (after the clamps) to first order; elsewhere (out of
    steps, none, or the last step crossed into another cell, where the derivatives jump) they are
    evaluated at the solution. invert.c does the same."""
    alpha = np.clip(alpha0, *grid.alpha_range)
    g = np.clip(g0, *grid.g_range)
    active = np.ones(alpha.shape, dtype=bool)
    last_a = last_g = np.zeros(alpha.shape)
    var: float | np.ndarray = 0.0 if step_var is None else step_var
    J = np.zeros((len(alpha), 3, 3))
    residual2 = np.zeros(len(alpha))
    evaluated = np.zeros(len(alpha), dtype=bool)
    for _ in range(iterations):  # a vectorised step over all bins, not a per-bin loop
        if not active.any():
            break
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite intensities: NaN, as in C
            new_alpha, new_g, step_a, step_g, (det, h11, h22), (r, J_step) = _newton_step(
                grid, I_b, I_w, cell, rho_b, rho_w, alpha, g)
        # converged bins keep their value: exactly what the C loop does by dropping them
        d_alpha, d_g = np.where(active, new_alpha - alpha, 0.0), np.where(active, new_g - g, 0.0)
        # the map's derivatives jump between cells: a step that left its cell is evaluated again
        (ia, ig), (ia_new, ig_new) = grid.alpha_g_cells(alpha, g), grid.alpha_g_cells(new_alpha, new_g)
        same_cell = (ia == ia_new) & (ig == ig_new)
        alpha, g = np.where(active, new_alpha, alpha), np.where(active, new_g, g)
        # var(α) = σ²·h22/det, var(g) = σ²·h11/det
        small = (step_is_small(step_a, last_a, step_tol, var, h22, det)
                 & step_is_small(step_g, last_g, step_tol, var, h11, det))
        last_a, last_g = np.abs(step_a), np.abs(step_g)
        done = active & small & same_cell
        carried = r + J_step[:, :, 0] * d_alpha[:, None] + J_step[:, :, 2] * d_g[:, None]
        residual2 = np.where(done, carried[:, 0] ** 2 + carried[:, 1] ** 2, residual2)
        J[:, :2] = np.where(done[:, None, None], J_step, J[:, :2])
        evaluated |= done
        active &= ~small
    residual, J_end = grid.residual_and_jacobian(I_b, I_w, cell, rho_b, rho_w, alpha, g)
    J[:, 2, 1] = J_end[:, 2, 1]
    J = np.where(evaluated[:, None, None], J, J_end)
    return alpha, g, np.where(evaluated, np.sqrt(residual2), residual), J


def correct_inscatter(grid: ForwardGrid, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray,
                      J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(α, σt, g) once the in-scattered light is taken out of I_c (invert.c correct_inscatter,
    operation for operation): σt up by L/ℓ (ln T falls by ℓ per unit σt; the Fresnel stack adds at
    most 3.6e-3 of that slope), L taken again at the moved σt, and (α, g) following to first order
    so that (I_b, I_w) stay fitted: J2·δ(α, g) = −∂I/∂σt·δσt, solved as a Newton step (lm_step).
    J: (N, 3, 3) at the solution; it stays that of the result. Also returns the correction of σt
    (0 where nothing moved), whose own uncertainty the fit propagates."""
    s0 = sigma_t
    L = grid.inscatter_log1p(alpha, s0, g)
    s = s0 + L / grid.thickness_mm
    with np.errstate(invalid="ignore"):
        # L again at the moved σt: it changes σt by ~L·dL/dτ, below 1e-6 of σt where L ≤ INSCATTER_ONCE
        again = L > native.INSCATTER_ONCE
        s = np.where(again, s0 + grid.inscatter_log1p(alpha, s, g) / grid.thickness_mm, s)
        ds = np.where((L > 0.0) & (s - s0 > 0.0), s - s0, 0.0)  # nothing scattered in (or a NaN): no move
    # the residual the σt move alone would leave in (I_b, I_w), taken out by one step in (α, g)
    step_a, step_g = lm_step(J[:, 0, 0], J[:, 0, 2], J[:, 1, 0], J[:, 1, 2], J[:, 0, 1] * ds,
                                   J[:, 1, 1] * ds)[:2]
    moved = ds > 0.0
    alpha = np.where(moved, np.minimum(np.maximum(alpha + step_a, grid.alpha_range[0]), grid.alpha_range[1]), alpha)
    g = np.where(moved, np.minimum(np.maximum(g + step_g, grid.g_range[0]), grid.g_range[1]), g)
    return alpha, np.where(moved, s, s0), g, ds


def lm_step(j11: np.ndarray, j12: np.ndarray, j21: np.ndarray, j22: np.ndarray, rb: np.ndarray,
            rw: np.ndarray) -> tuple[np.ndarray, ...]:
    """(step_a, step_g, h11, h22, det): the damped Gauss-Newton (Levenberg-Marquardt) step on the
    2×2 normal equations of (I_b, I_w) in (α, g) for residuals (rb, rw), capped to a trust region
    (invert.c lm_step), and the right-hand sides b1, b2 (hold_at_edges)."""
    # The damping keeps it finite where ∂I/∂g → 0 (α → 0).
    h11, h22, h12 = j11 * j11 + j21 * j21, j12 * j12 + j22 * j22, j11 * j12 + j21 * j22
    mu = 1e-9 + 1e-6 * (h11 + h22)
    h11, h22 = h11 + mu, h22 + mu
    b1, b2 = j11 * rb + j21 * rw, j12 * rb + j22 * rw
    det = h11 * h22 - h12 * h12
    # Trust region: a piecewise-trilinear map is only locally linear; cap the step at a few cells.
    step_a = np.minimum(np.maximum(-(h22 * b1 - h12 * b2) / det, -0.25), 0.25)
    step_g = np.minimum(np.maximum(-(h11 * b2 - h12 * b1) / det, -0.5), 0.5)
    return step_a, step_g, h11, h22, det, b1, b2


def hold_at_edges(grid: ForwardGrid, alpha: np.ndarray, g: np.ndarray,
                  step: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """The polish's step projected onto the map's box (invert_internal.h hold_at_edges, operation for
    operation). `step`: lm_step's (step_a, step_g, h11, h22, det, b1, b2) from (α, g). A parameter at
    an edge of the box whose step points out of it is held there (step 0) and the other takes the
    Gauss-Newton step of its own (−b/h, capped as in lm_step): the 2×2 step assumed the held one moves,
    so clamped it only crawls towards the solution on the edge. The other's variance per unit intensity
    variance is then 1/h (returned as h' = 1, det' = h, for step_is_small); both held: both steps 0.
    Returns (step_a, step_g, h11, h22, det) as lm_step's."""
    step_a, step_g, h11, h22, det, b1, b2 = step
    (a_lo, a_hi), (g_lo, g_hi) = grid.alpha_range, grid.g_range
    hold_a = ((alpha <= a_lo) & (step_a < 0.0)) | ((alpha >= a_hi) & (step_a > 0.0))
    hold_g = ((g <= g_lo) & (step_g < 0.0)) | ((g >= g_hi) & (step_g > 0.0))
    only_a, only_g = hold_a & ~hold_g, hold_g & ~hold_a
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        along_a = np.minimum(np.maximum(-b1 / h11, -0.25), 0.25)
        along_g = np.minimum(np.maximum(-b2 / h22, -0.5), 0.5)
    new_a = np.where(hold_a, 0.0, np.where(only_g, along_a, step_a))
    new_g = np.where(hold_g, 0.0, np.where(only_a, along_g, step_g))
    new_det = np.where(only_g, h11, np.where(only_a, h22, det))
    return (new_a, new_g, np.where(only_a, 1.0, h11), np.where(only_g, 1.0, h22), new_det)


def _newton_step(grid: ForwardGrid, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell, rho_b: np.ndarray,
                 rho_w: np.ndarray, alpha: np.ndarray, g: np.ndarray) -> tuple[Any, ...]:
    """One damped Gauss-Newton step from (α, g): the new (α, g), the steps, (det, h11, h22) of the
    normal equations, and this evaluation's residuals (N, 2) and ∂(I_b, I_w)/∂(α, σt, g) (N, 2, 3)."""
    coef, d_a, d_g, d_ls = grid.coefficients(alpha, cell, g, with_sigma_derivative=True)
    Ib, fb, hb = grid.diffuse(coef, rho_b)
    Iw, fw, hw = grid.diffuse(coef, rho_w)
    rb, rw = Ib - I_b, Iw - I_w
    j11, j12 = grid.directional(fb, hb, d_a), grid.directional(fb, hb, d_g)
    j21, j22 = grid.directional(fw, hw, d_a), grid.directional(fw, hw, d_g)
    step_a, step_g, h11, h22, det = hold_at_edges(grid, alpha, g, lm_step(j11, j12, j21, j22, rb, rw))
    (a_lo, a_hi), (g_lo, g_hi) = grid.alpha_range, grid.g_range
    s = np.exp(cell.log_sigma_t)
    J_step = np.stack([np.stack([j11, grid.directional(fb, hb, d_ls) / s, j12], axis=-1),
                       np.stack([j21, grid.directional(fw, hw, d_ls) / s, j22], axis=-1)], axis=1)
    return (np.minimum(np.maximum(alpha + step_a, a_lo), a_hi), np.minimum(np.maximum(g + step_g, g_lo), g_hi),
            step_a, step_g, (det, h11, h22), (np.stack([rb, rw], axis=-1), J_step))



def first_order_holds(grid: ForwardGrid, alpha: np.ndarray, cell: SigmaCell, g: np.ndarray, I_b: np.ndarray,
                      I_w: np.ndarray, rho_b: np.ndarray, rho_w: np.ndarray, J: np.ndarray, sigma_b: np.ndarray,
                      sigma_w: np.ndarray, std_a: np.ndarray, std_g: np.ndarray, sigmas: float,
                      tol: float) -> np.ndarray:
    """Whether the first-order stds std_a, std_g hold over ±`sigmas` σ (invert.c check_first_order,
    operation for operation). From the polish's solution (α, g) at σt's cell and its Jacobian J
    (N, 3, 3), the measured (I_b, I_w) are moved by ±sigmas·σ in I_b, then in I_w (σ: sigma_b,
    sigma_w, the stds propagated); each move's linear prediction (α, g) + J2⁻¹·δI, clamped to the
    map's box, is corrected by one Newton step there: where a re-fit from the moved intensities
    lands, up to the square of its distance from the prediction. A bin holds where correction and
    clamp stay within tol·sigmas of each std for all four moves: two evaluations per move, where
    solving the re-fits took up to six."""
    (a_lo, a_hi), (g_lo, g_hi) = grid.alpha_range, grid.g_range
    j11, j12, j21, j22 = J[:, 0, 0], J[:, 0, 2], J[:, 1, 0], J[:, 1, 2]
    limit_a, limit_g = tol * sigmas * std_a, tol * sigmas * std_g
    holds = np.ones(len(alpha), dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        det = j11 * j22 - j12 * j21
        for move in range(4):
            on_b = move < 2
            dI = (-sigmas if move & 1 else sigmas) * (sigma_b if on_b else sigma_w)
            # J2⁻¹'s column for I_b is (j22, −j21)/det, for I_w (−j12, j11)/det
            da = (j22 * dI) / det if on_b else (-j12 * dI) / det
            dg = (-j21 * dI) / det if on_b else (j11 * dI) / det
            a1 = np.minimum(np.maximum(alpha + da, a_lo), a_hi)
            g1 = np.minimum(np.maximum(g + dg, g_lo), g_hi)
            coef, e_a, e_g = grid.coefficients(a1, cell, g1)
            Ib, gb, kb = grid.diffuse(coef, rho_b)
            Iw, gw, kw = grid.diffuse(coef, rho_w)
            rb = Ib - (I_b + dI) if on_b else Ib - I_b
            rw = Iw - I_w if on_b else Iw - (I_w + dI)
            step_a, step_g = lm_step(grid.directional(gb, kb, e_a), grid.directional(gb, kb, e_g),
                                           grid.directional(gw, kw, e_a), grid.directional(gw, kw, e_g), rb, rw)[:2]
            a2 = np.minimum(np.maximum(a1 + step_a, a_lo), a_hi)
            g2 = np.minimum(np.maximum(g1 + step_g, g_lo), g_hi)
            holds &= (np.abs(a2 - alpha - da) <= limit_a) & (np.abs(g2 - g - dg) <= limit_g)
    return holds



def propagate(J: np.ndarray, sigma_I: np.ndarray,
              sigma_t_var: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Standard deviations of (α, σt, g) from independent intensity noise sigma_I (N, 3), to
    first order: cov = J⁻¹ Σ J⁻ᵀ, using the block structure (row I_c has only ∂/∂σt).
    sigma_t_var (N,): further variance of σt that (α, g) follow as they follow I_c's (the
    in-scattering correction's). Infinite where the (α, g) block is singular."""
    var_s = (sigma_I[:, 2] / J[:, 2, 1]) ** 2
    if sigma_t_var is not None:
        var_s = var_s + sigma_t_var
    # δ(α, g) = J2⁻¹ (δI_bw − J_s δσt), J2 = ∂(I_b, I_w)/∂(α, g)
    a, b, c, d = J[:, 0, 0], J[:, 0, 2], J[:, 1, 0], J[:, 1, 2]
    det = a * d - b * c
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.stack([d, -b], -1), np.stack([-c, a], -1)], 1) / det[:, None, None]
    sb, sw = sigma_I[:, 0] ** 2, sigma_I[:, 1] ** 2
    cov_bw = np.zeros((len(det), 2, 2))
    cov_bw[:, 0, 0] = sb + J[:, 0, 1] ** 2 * var_s
    cov_bw[:, 1, 1] = sw + J[:, 1, 1] ** 2 * var_s
    cov_bw[:, 0, 1] = cov_bw[:, 1, 0] = J[:, 0, 1] * J[:, 1, 1] * var_s
    with np.errstate(invalid="ignore", over="ignore"):
        cov = inv @ cov_bw @ np.swapaxes(inv, 1, 2)
        std_a = np.sqrt(np.abs(cov[:, 0, 0]))
        std_g = np.sqrt(np.abs(cov[:, 1, 1]))
    return np.where(np.isnan(std_a), np.inf, std_a), np.sqrt(var_s), np.where(np.isnan(std_g), np.inf, std_g)



def step_is_small(step: np.ndarray, last: np.ndarray, step_tol: float, step_var: float | np.ndarray, h: np.ndarray,
                  det: np.ndarray) -> np.ndarray:
    """Whether a polish step in one parameter ends that parameter's polish (invert.c step_is_small,
    operation for operation): |step| ≤ step_tol; or below κ of its noise std (step² ≤ step_var·h/det,
    step_var = (κ σ_I)², h/det its variance per unit intensity variance); or at most native.STEP_RATIO of
    the previous step `last` with the next one, ≈ |step|·|step/last|, below κ of that std. The last
    rule saves the step that would only confirm convergence. Multiplied out: no division."""
    a = np.abs(step)
    with np.errstate(invalid="ignore", over="ignore"):
        d2 = a * a * det
        lim = step_var * h
        tail = (a <= native.STEP_RATIO * last) & (d2 * a * a <= lim * last * last)
        return (a <= step_tol) | ((det > 0) & ((d2 <= lim) | tail))


def polish_step_var(I_b: np.ndarray, I_w: np.ndarray, noise_rel: float, noise_abs: float, mc_stderr: float,
                    kappa: float, sd: np.ndarray | None = None) -> np.ndarray:
    """solve_alpha_g's step_var: (κ σ)² per bin, σ² the mean of I_b's and I_w's variance under the
    noise model σ_I = noise_rel·I + noise_abs (or their given stds, sd (N, 3)), with the map's MC
    std-error in quadrature."""
    sb, sw = (noise_rel * I_b + noise_abs, noise_rel * I_w + noise_abs) if sd is None else (sd[:, 0], sd[:, 1])
    return kappa * kappa * (0.5 * (sb * sb + sw * sw + 2.0 * mc_stderr * mc_stderr))

