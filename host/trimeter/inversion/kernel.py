"""The forward map as a fast, vectorised kernel shared by every method: trilinear A, B, C on a
(α, ln σt, g) grid (the map's, refined between its nodes: ForwardGrid.between_nodes) with analytic
derivatives, a batched 2×2 Newton (Levenberg-Marquardt)
solve of (I_b, I_w) for (α, g) at a known σt, and first-order uncertainty propagation.

Why (α, g) at known σt: the unscattered beam, I_c's main part, depends on σt alone
(trimeter.forward.collimated), so the square 3×3 system's solution takes σt from I_c (Beer-Lambert with
Fresnel, exact inverse) and leaves two equations in two unknowns. The light scattered into the
detector's aperture (up to ~20 % of I_c at the measurable gamut's edge, trimeter.forward.inscatter)
depends on α and g too: with a map's in-scattering table, σt and then (α, g) are corrected for it
once (α, g) are solved, to first order (ForwardGrid.correct_inscatter). No Python loop per bin:
every step is a gather + array arithmetic.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from trimeter.forward.collimated import (beer_lambert_limit, collimated_derivative, collimated_transmittance,
                                         stack_constants)
from trimeter.forward.inscatter import regular_cell, trilinear
from trimeter.inversion import native


@dataclass(frozen=True)
class SigmaCell:
    """Where each bin's σt sits on the grid (fixed during a Newton solve)."""
    index: np.ndarray        # int (N,) lower node
    weight: np.ndarray       # (N,) in [0, 1]
    log_sigma_t: np.ndarray  # (N,) clamped to the grid


# How a map is evaluated between its nodes — everywhere: the lut/mlp polish, the twin's virtual
# samples and `trimeter map query` (ForwardGrid.between_nodes): refined by these factors with cubic
# splines in α and ln σt and PCHIP in g, then trilinear. Measured with `trimeter bench fit` on the
# 16-node device maps, noise-free rendered held-out, lut p≤8 (l0.4 / l0.8): α p95 0.034 / 0.058 →
# 0.024 / 0.018, g p95 0.060 / 0.064 → 0.044 / 0.034; well-conditioned α 0.033 / 0.058 → 0.010 /
# 0.010, g 0.032 / 0.066 → 0.008 / 0.007; fit() time unchanged. Trilinear interpolation between the
# nodes (ln σt ×1.6 apart, 7 g) was the maps' main error, not their MC noise. (Chosen on that
# held-out set among σt ×2/×4 cubic or PCHIP and g ×2/×3/×4: PCHIP in g gave the same figures at
# every factor, a cubic spline in g did not. Checked on independent sets of 16 columns × 10 α, 8M
# paths, with the 8M-path maps: each refinement step lowered α and g p95 there too, to α 0.013 /
# 0.008 and g 0.010 / 0.008.)
# ln σt: ~121 nodes (was 61). Between the nodes of a refined axis the kernel is linear in B, while B
# (the light through the slab and back) falls like exp(−c·σt·ℓ): at 61 nodes (σt ×1.12 apart) a
# trilinear cell missed B by up to 3 % at σt·ℓ ≈ 2, an α error of 0.01-0.015 for dark samples
# (checked against fresh 32M-path traces 2-6 % off a node). Held-out l0.4 / l0.8, lut p≤8: α p95
# 0.0154 → 0.0120 (l0.4), well-conditioned α 0.0084 → 0.0074 / 0.0069, g 0.0056 → 0.0040 /
# 0.0113 → 0.0098; 241 nodes gained nothing more, α ×4 little (0.0120 → 0.0113) for twice the
# memory, g ×4 was worse. The refined l0.4 grid holds 22 MB of cell polynomials.
BETWEEN_NODES_ALPHA = 2
BETWEEN_NODES_SIGMA_NODES = 121  # ln σt refined to about this many nodes
BETWEEN_NODES_G = 2


def sigma_refine_factor(n_sigma: int) -> int:
    """The refinement that brings n_sigma nodes to about BETWEEN_NODES_SIGMA_NODES (1: none)."""
    return max(1, round((BETWEEN_NODES_SIGMA_NODES - 1) / max(n_sigma - 1, 1)))


class ForwardGrid:
    def __init__(self, alpha, log_sigma_t, g, coefficients, *, n, thickness_mm, cover_slide_n, mc_stderr=0.0):
        self.alpha = np.asarray(alpha, dtype=np.float64)
        self.log_sigma_t = np.asarray(log_sigma_t, dtype=np.float64)
        self.g = np.asarray(g, dtype=np.float64)
        coefficients = np.asarray(coefficients, dtype=np.float64)  # (na, ns, ng, 3)
        self._nodes = coefficients
        self.shape = coefficients.shape[:3]
        # Per grid cell, the trilinear polynomial in the cell weights (wa, ws, wg), terms ordered
        # 1, wa, ws, wg, wa·ws, wa·wg, ws·wg, wa·ws·wg: a bin's whole cell is one contiguous row.
        v = {(da, ds, dg): coefficients[da:coefficients.shape[0] - 1 + da, ds:coefficients.shape[1] - 1 + ds,
                                        dg:coefficients.shape[2] - 1 + dg]
             for da in (0, 1) for ds in (0, 1) for dg in (0, 1)}
        poly = [v[0, 0, 0], v[1, 0, 0] - v[0, 0, 0], v[0, 1, 0] - v[0, 0, 0], v[0, 0, 1] - v[0, 0, 0],
                v[1, 1, 0] - v[1, 0, 0] - v[0, 1, 0] + v[0, 0, 0], v[1, 0, 1] - v[1, 0, 0] - v[0, 0, 1] + v[0, 0, 0],
                v[0, 1, 1] - v[0, 1, 0] - v[0, 0, 1] + v[0, 0, 0],
                v[1, 1, 1] - v[1, 1, 0] - v[1, 0, 1] - v[0, 1, 1] + v[1, 0, 0] + v[0, 1, 0] + v[0, 0, 1] - v[0, 0, 0]]
        self._poly = np.ascontiguousarray(np.stack(poly, axis=-2).reshape(-1, 24))  # (cell, term·3 + coef)
        self._inv_da = 1.0 / np.diff(self.alpha)
        self._inv_ds = 1.0 / np.diff(self.log_sigma_t)
        self._inv_dg = 1.0 / np.diff(self.g)
        self.n, self.thickness_mm, self.cover_slide_n = float(n), float(thickness_mm), cover_slide_n
        self.mc_stderr = float(mc_stderr)
        self.alpha_range = (float(self.alpha[0]), float(self.alpha[-1]))
        self.g_range = (float(self.g[0]), float(self.g[-1]))
        self.sigma_t_range = (float(np.exp(self.log_sigma_t[0])), float(np.exp(self.log_sigma_t[-1])))
        # in-scattering into I_c (attach_inscatter): None means I_c is the unscattered beam alone
        self.inscatter_grid = None
        # the map's own error as variances of (I_b, I_w) on this grid's nodes (attach_model_variance), or None
        self.model_var = None

    @classmethod
    def from_map(cls, amap) -> "ForwardGrid":
        mc = float(np.median(np.concatenate([amap.std_b.ravel(), amap.std_w.ravel()])))
        return cls(amap.alpha, np.log(amap.sigma_t), amap.g, np.stack([amap.A, amap.B, amap.C], axis=-1),
                   n=amap.n, thickness_mm=amap.thickness_mm, cover_slide_n=amap.cover_slide_n, mc_stderr=mc)

    @classmethod
    def from_table(cls, table) -> "ForwardGrid":
        return cls(table.alpha, table.log_sigma_t, table.g, table.coefficients_grid, n=table.n,
                   thickness_mm=table.thickness_mm, cover_slide_n=table.cover_slide_n, mc_stderr=table.mc_stderr)

    def refined(self, alpha: int = 1, sigma: int = 1, g: int = 1) -> "ForwardGrid":
        """The same map on axes refined by these factors: cubic splines through the nodes along α
        and ln σt (smooth there: α^k polynomials per traced column; σt nodes dense), shape-preserving
        PCHIP along g (7 noisy nodes, steep towards g → 1: a cubic spline overshoots between them).
        Both reproduce the nodes. The trilinear kernel then follows the map's curvature."""
        coef, axes = self.coefficients_grid, [self.alpha, self.log_sigma_t, self.g]
        for axis, (factor, kind) in enumerate(((alpha, "cubic"), (sigma, "cubic"), (g, "pchip"))):
            if factor > 1:
                new = refine_axis(axes[axis], factor)
                coef = cubic_resample(coef, axes[axis], new, axis, kind=kind)
                axes[axis] = new
        if coef is self.coefficients_grid:
            return self
        coef[..., 2] = np.clip(coef[..., 2], 0.0, 0.999)  # C: a reflectance, and 1 − Cρ must stay positive
        return ForwardGrid(*axes, coef, n=self.n, thickness_mm=self.thickness_mm, cover_slide_n=self.cover_slide_n,
                           mc_stderr=self.mc_stderr)

    def between_nodes(self) -> "ForwardGrid":
        """This map as evaluated between its nodes everywhere (see BETWEEN_NODES_ALPHA)."""
        return self.refined(BETWEEN_NODES_ALPHA, sigma_refine_factor(len(self.log_sigma_t)), BETWEEN_NODES_G)

    @property
    def coefficients_grid(self) -> np.ndarray:
        """(na, ns, ng, 3): A, B, C at the nodes."""
        return self._nodes

    # ---------------------------------------------------------------------------------- helpers
    @staticmethod
    def _cell(axis, inv_d, x):
        # np.minimum/maximum: np.clip's Python wrapper costs more than the work at N ≈ 1000
        i = np.minimum(np.maximum(np.searchsorted(axis, x, side="right") - 1, 0), len(axis) - 2)
        w = np.minimum(np.maximum((x - axis[i]) * inv_d[i], 0.0), 1.0)
        return i, w

    def _alpha_g_cells(self, alpha, g):
        return self._cell(self.alpha, self._inv_da, alpha)[0], self._cell(self.g, self._inv_dg, g)[0]

    def sigma_cell(self, sigma_t) -> SigmaCell:
        with np.errstate(divide="ignore", invalid="ignore"):
            ls = np.log(np.asarray(sigma_t, dtype=np.float64))
        ls = np.clip(np.nan_to_num(ls, nan=self.log_sigma_t[0], posinf=self.log_sigma_t[-1],
                                   neginf=self.log_sigma_t[0]), self.log_sigma_t[0], self.log_sigma_t[-1])
        i, w = self._cell(self.log_sigma_t, self._inv_ds, ls)
        return SigmaCell(i, w, ls)

    def clamp_sigma_t(self, sigma_t):
        """σt clamped to the grid as sigma_cell does it (NaN → lowest node), without the cell."""
        lo, hi = self.sigma_t_range
        return np.minimum(np.where(sigma_t >= lo, sigma_t, lo), hi)

    def collimated(self, sigma_t):
        return collimated_transmittance(sigma_t, self.thickness_mm, self.n, self.cover_slide_n)

    def attach_inscatter(self, table) -> None:
        """Take in-scattered light into I_c into account (a trimeter.forward.inscatter.InscatterTable,
        or None): the table resampled onto this grid's own α and g nodes, at its evenly spaced optical
        depths, so that a bin's lookup reuses the polish's α and g cells (no logarithms per bin)."""
        if table is None:
            self.inscatter_grid = None
            return
        nt = table.L.shape[1]
        tau = np.linspace(0.0, table.tau_max, nt)
        a, t, g = np.meshgrid(self.alpha, tau, self.g, indexing="ij")
        L = np.ascontiguousarray(table.log1p_ratio(a, t / table.thickness_mm, g))
        self.inscatter_grid = (L, (nt - 1) / table.tau_max, float(table.tau_max))

    def attach_model_variance(self, node_var, alpha, log_sigma_t, g) -> None:
        """The map's own error (node_model_variance: (na, ns, ng, 2) variances of I_b, I_w on the
        map's nodes alpha, log_sigma_t, g), resampled linearly onto this grid's nodes, for the
        uncertainty at a solution (model_variance); None detaches it."""
        if node_var is None:
            self.model_var = None
            return
        var = np.asarray(node_var, dtype=np.float64)
        for axis, (old, new) in enumerate(((alpha, self.alpha), (log_sigma_t, self.log_sigma_t), (g, self.g))):
            var = linear_resample(var, np.asarray(old, dtype=np.float64), new, axis)
        self.model_var = np.ascontiguousarray(var)

    def model_variance(self, alpha, cell: SigmaCell, g):
        """(2, N): the map's error variance of I_b, I_w at (α, σt's cell, g), trilinear on the nodes
        (invert.c model_variance, operation for operation); zeros without attach_model_variance."""
        if self.model_var is None:
            return np.zeros((2, len(cell.index)))
        ia, wa = self._cell(self.alpha, self._inv_da, alpha)
        ig, wg = self._cell(self.g, self._inv_dg, g)
        # the nodes hold (I_b, I_w) pairs: the weights broadcast over that last axis
        return trilinear(self.model_var, ia, wa[:, None], cell.index, cell.weight[:, None], ig, wg[:, None]).T

    def inscatter_log1p(self, alpha, sigma_t, g):
        """L = ln(1 + r) at (α, σt, g) from inscatter_grid (invert.c inscatter_log1p, operation for
        operation): trilinear on the α and g nodes and the optical depths σt·ℓ (clamped to the table)."""
        L, inv_dt, tau_max = self.inscatter_grid
        ia, wa = self._cell(self.alpha, self._inv_da, alpha)
        ig, wg = self._cell(self.g, self._inv_dg, g)
        tau = np.asarray(sigma_t * self.thickness_mm, dtype=np.float64)
        tau = np.where(np.isfinite(tau), tau, 0.0)  # an unusable bin's NaN: any index will do, not a wild one
        it, wt = regular_cell(np.minimum(np.maximum(tau, 0.0), tau_max) * inv_dt, L.shape[1])
        return trilinear(L, ia, wa, it, wt, ig, wg)

    def correct_inscatter(self, alpha, sigma_t, g, J):
        """(α, σt, g) once the in-scattered light is taken out of I_c (invert.c correct_inscatter,
        operation for operation): σt up by L/ℓ (ln T falls by ℓ per unit σt; the Fresnel stack adds at
        most 3.6e-3 of that slope), L taken again at the moved σt, and (α, g) following to first order
        so that (I_b, I_w) stay fitted: J2·δ(α, g) = −∂I/∂σt·δσt, solved as a Newton step (_lm_step).
        J: (N, 3, 3) at the solution; it stays that of the result. Also returns the correction of σt
        (0 where nothing moved), whose own uncertainty the fit propagates."""
        s0 = sigma_t
        L = self.inscatter_log1p(alpha, s0, g)
        s = s0 + L / self.thickness_mm
        with np.errstate(invalid="ignore"):
            # L again at the moved σt: it changes σt by ~L·dL/dτ, below 1e-6 of σt where L ≤ INSCATTER_ONCE
            again = L > native.INSCATTER_ONCE
            s = np.where(again, s0 + self.inscatter_log1p(alpha, s, g) / self.thickness_mm, s)
            ds = np.where((L > 0.0) & (s - s0 > 0.0), s - s0, 0.0)  # nothing scattered in (or a NaN): no move
        # the residual the σt move alone would leave in (I_b, I_w), taken out by one step in (α, g)
        step_a, step_g = self._lm_step(J[:, 0, 0], J[:, 0, 2], J[:, 1, 0], J[:, 1, 2], J[:, 0, 1] * ds,
                                       J[:, 1, 1] * ds)[:2]
        moved = ds > 0.0
        alpha = np.where(moved, np.minimum(np.maximum(alpha + step_a, self.alpha_range[0]), self.alpha_range[1]), alpha)
        g = np.where(moved, np.minimum(np.maximum(g + step_g, self.g_range[0]), self.g_range[1]), g)
        return alpha, np.where(moved, s, s0), g, ds

    def collimated_measured(self, alpha, sigma_t, g):
        """I_c as the instrument reads it: the unscattered beam and, with an in-scattering table, the
        light scattered into the detector's aperture."""
        unscattered = self.collimated(sigma_t)
        if self.inscatter_grid is None:
            return unscattered
        return unscattered * np.exp(self.inscatter_log1p(alpha, sigma_t, g))

    @cached_property
    def transmittance_limits(self) -> tuple[float, float]:
        """(T(σt = 0), the largest I_c the Beer-Lambert inverse takes) of this grid's sample set-up:
        computed once (a Fresnel stack each), not per fit."""
        return float(self.collimated(0.0)), float(beer_lambert_limit(self.n, self.cover_slide_n))

    @property
    def stack_constants(self) -> tuple[float, float, float]:
        """(a, b, T(σt = 0)) of I_c = a·x / (1 − b·x²), x = exp(−σt ℓ)."""
        return stack_constants(self.n, self.cover_slide_n)

    def coefficients(self, alpha, cell: SigmaCell, g, with_sigma_derivative=False):
        """A, B, C stacked (3, N) and their derivatives in α and g (and ln σt if asked), each (3, N).
        Component-major layout: every operation below runs on contiguous rows of N."""
        ia, wa = self._cell(self.alpha, self._inv_da, alpha)
        ig, wg = self._cell(self.g, self._inv_dg, g)
        ns, ng = self.shape[1] - 1, self.shape[2] - 1
        P = self._poly[(ia * ns + cell.index) * ng + ig].T.copy().reshape(8, 3, -1)  # (term, coef, N)
        ws = cell.weight
        p0 = P[0] + P[2] * ws
        p1 = P[1] + P[4] * ws
        p3 = P[3] + P[6] * ws
        p5 = P[5] + P[7] * ws
        value = p0 + p1 * wa + (p3 + p5 * wa) * wg
        d_alpha = (p1 + p5 * wg) * self._inv_da[ia]
        d_g = (p3 + p5 * wa) * self._inv_dg[ig]
        if not with_sigma_derivative:
            return value, d_alpha, d_g
        d_ws = P[2] + P[4] * wa + (P[6] + P[7] * wa) * wg
        return value, d_alpha, d_g, d_ws * self._inv_ds[cell.index]

    @staticmethod
    def diffuse(coef, rho):
        """I(ρ) = A + Bρ/(1 − Cρ) and its gradient in (A, B, C) as (dI/dB, dI/dC), coef (3, N)."""
        A, B, C = coef
        f = rho / (1.0 - C * rho)
        return A + B * f, f, B * f * f

    @staticmethod
    def directional(grad_B, grad_C, d):
        """dI along one parameter from the (A, B, C) derivatives d (3, N)."""
        return d[0] + grad_B * d[1] + grad_C * d[2]

    def intensities(self, alpha, sigma_t, g, rho_b, rho_w):
        """(I_b, I_w, I_c) by the kernel (for training data and checks; σt clamped to the grid)."""
        cell = self.sigma_cell(sigma_t)
        alpha, g = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(g, float))
        coef, _, _ = self.coefficients(alpha.ravel(), cell, g.ravel())
        I_b = self.diffuse(coef, np.asarray(rho_b, float))[0]
        I_w = self.diffuse(coef, np.asarray(rho_w, float))[0]
        return I_b, I_w, self.collimated_measured(alpha, sigma_t, g)

    # ----------------------------------------------------------------------------------- solving
    @cached_property
    def native_solver(self):
        """The same solve in C (trimeter.inversion.native), or None when the library is not built."""
        return native.NativeSolver(self) if native.available() else None

    def solve_alpha_g(self, I_b, I_w, cell: SigmaCell, rho_b, rho_w, alpha0, g0, iterations=5, step_tol=0.0,
                      step_var=None):
        """Damped Gauss-Newton for (α, g) with I_b, I_w matched at the bins' own ρ_b, ρ_w. Steps are
        clamped to the map's box. At most `iterations` steps; a bin stops once a step was small in
        both α and g: at most `step_tol`, or (with step_var, per bin (κ σ_I)², see
        polish_step_var) below κ of that parameter's noise std, where further steps only move it
        along what the data cannot tell apart. step_tol 0 and no step_var: every bin takes every
        step. Returns (α, g, residual norm, Jacobian at the solution). Where a bin's polish ended on
        a small step within one cell of the map, these come from that step's evaluation (no
        evaluation more): its Jacobian, a step below κ of the noise std from the solution, and its
        residuals carried along the step taken (after the clamps) to first order; elsewhere (out of
        steps, none, or the last step crossed into another cell, where the derivatives jump) they are
        evaluated at the solution. invert.c does the same."""
        if self.native_solver is not None:
            return self.native_solver.solve(I_b, I_w, cell.log_sigma_t, rho_b, rho_w, max(int(iterations), 0),
                                            alpha0, g0, step_tol=step_tol, step_var=step_var)
        alpha = np.clip(alpha0, *self.alpha_range)
        g = np.clip(g0, *self.g_range)
        active = np.ones(alpha.shape, dtype=bool)
        last_a = last_g = np.zeros(alpha.shape)
        step_var = 0.0 if step_var is None else step_var
        J = np.zeros((len(alpha), 3, 3))
        residual2 = np.zeros(len(alpha))
        evaluated = np.zeros(len(alpha), dtype=bool)
        for _ in range(iterations):  # a vectorised step over all bins, not a per-bin loop
            if not active.any():
                break
            with np.errstate(invalid="ignore", over="ignore"):  # non-finite intensities: NaN, as in C
                new_alpha, new_g, step_a, step_g, (det, h11, h22), (r, J_step) = self._newton_step(
                    I_b, I_w, cell, rho_b, rho_w, alpha, g)
            # converged bins keep their value: exactly what the C loop does by dropping them
            d_alpha, d_g = np.where(active, new_alpha - alpha, 0.0), np.where(active, new_g - g, 0.0)
            # the map's derivatives jump between cells: a step that left its cell is evaluated again
            (ia, ig), (ia_new, ig_new) = self._alpha_g_cells(alpha, g), self._alpha_g_cells(new_alpha, new_g)
            same_cell = (ia == ia_new) & (ig == ig_new)
            alpha, g = np.where(active, new_alpha, alpha), np.where(active, new_g, g)
            # var(α) = σ²·h22/det, var(g) = σ²·h11/det
            small = (step_is_small(step_a, last_a, step_tol, step_var, h22, det)
                     & step_is_small(step_g, last_g, step_tol, step_var, h11, det))
            last_a, last_g = np.abs(step_a), np.abs(step_g)
            done = active & small & same_cell
            carried = r + J_step[:, :, 0] * d_alpha[:, None] + J_step[:, :, 2] * d_g[:, None]
            residual2 = np.where(done, carried[:, 0] ** 2 + carried[:, 1] ** 2, residual2)
            J[:, :2] = np.where(done[:, None, None], J_step, J[:, :2])
            evaluated |= done
            active &= ~small
        residual, J_end = self.residual_and_jacobian(I_b, I_w, cell, rho_b, rho_w, alpha, g)
        J[:, 2, 1] = J_end[:, 2, 1]
        J = np.where(evaluated[:, None, None], J, J_end)
        return alpha, g, np.where(evaluated, np.sqrt(residual2), residual), J

    def residual_and_jacobian(self, I_b, I_w, cell: SigmaCell, rho_b, rho_w, alpha, g):
        """|(I_b, I_w) − model| and ∂(I_b, I_w, I_c)/∂(α, σt, g) (N, 3, 3) from one evaluation."""
        coef, d_a, d_g, d_ls = self.coefficients(alpha, cell, g, with_sigma_derivative=True)
        s = np.exp(cell.log_sigma_t)
        J = np.zeros((len(s), 3, 3))
        res2 = 0.0
        for row, rho, target in ((0, rho_b, I_b), (1, rho_w, I_w)):
            I, f, h = self.diffuse(coef, rho)
            res2 = res2 + (I - target) ** 2
            J[:, row, 0] = self.directional(f, h, d_a)
            J[:, row, 1] = self.directional(f, h, d_ls) / s
            J[:, row, 2] = self.directional(f, h, d_g)
        J[:, 2, 1] = self.collimated_derivative(s)
        return np.sqrt(res2), J

    def collimated_derivative(self, s):
        return collimated_derivative(s, self.thickness_mm, self.n, self.cover_slide_n)

    @staticmethod
    def _lm_step(j11, j12, j21, j22, rb, rw):
        """(step_a, step_g, h11, h22, det): the damped Gauss-Newton (Levenberg-Marquardt) step on the
        2×2 normal equations of (I_b, I_w) in (α, g) for residuals (rb, rw), capped to a trust region
        (invert.c lm_step)."""
        # The damping keeps it finite where ∂I/∂g → 0 (α → 0).
        h11, h22, h12 = j11 * j11 + j21 * j21, j12 * j12 + j22 * j22, j11 * j12 + j21 * j22
        mu = 1e-9 + 1e-6 * (h11 + h22)
        h11, h22 = h11 + mu, h22 + mu
        b1, b2 = j11 * rb + j21 * rw, j12 * rb + j22 * rw
        det = h11 * h22 - h12 * h12
        # Trust region: a piecewise-trilinear map is only locally linear; cap the step at a few cells.
        step_a = np.minimum(np.maximum(-(h22 * b1 - h12 * b2) / det, -0.25), 0.25)
        step_g = np.minimum(np.maximum(-(h11 * b2 - h12 * b1) / det, -0.5), 0.5)
        return step_a, step_g, h11, h22, det

    def _newton_step(self, I_b, I_w, cell, rho_b, rho_w, alpha, g):
        """One damped Gauss-Newton step from (α, g): the new (α, g), the steps, (det, h11, h22) of the
        normal equations, and this evaluation's residuals (N, 2) and ∂(I_b, I_w)/∂(α, σt, g) (N, 2, 3)."""
        coef, d_a, d_g, d_ls = self.coefficients(alpha, cell, g, with_sigma_derivative=True)
        Ib, fb, hb = self.diffuse(coef, rho_b)
        Iw, fw, hw = self.diffuse(coef, rho_w)
        rb, rw = Ib - I_b, Iw - I_w
        j11, j12 = self.directional(fb, hb, d_a), self.directional(fb, hb, d_g)
        j21, j22 = self.directional(fw, hw, d_a), self.directional(fw, hw, d_g)
        step_a, step_g, h11, h22, det = self._lm_step(j11, j12, j21, j22, rb, rw)
        (a_lo, a_hi), (g_lo, g_hi) = self.alpha_range, self.g_range
        s = np.exp(cell.log_sigma_t)
        J_step = np.stack([np.stack([j11, self.directional(fb, hb, d_ls) / s, j12], axis=-1),
                           np.stack([j21, self.directional(fw, hw, d_ls) / s, j22], axis=-1)], axis=1)
        return (np.minimum(np.maximum(alpha + step_a, a_lo), a_hi), np.minimum(np.maximum(g + step_g, g_lo), g_hi),
                step_a, step_g, (det, h11, h22), (np.stack([rb, rw], axis=-1), J_step))

    # ------------------------------------------------------------------------------- uncertainty
    def jacobian(self, alpha, sigma_t, g, rho_b, rho_w):
        """∂(I_b, I_w, I_c)/∂(α, σt, g) per bin: (N, 3, 3). I_c depends on σt only."""
        cell = self.sigma_cell(sigma_t)
        coef, d_a, d_g, d_ls = self.coefficients(np.clip(alpha, *self.alpha_range), cell,
                                                 np.clip(g, *self.g_range), with_sigma_derivative=True)
        s = np.exp(cell.log_sigma_t)
        J = np.zeros((len(s), 3, 3))
        for row, rho in ((0, rho_b), (1, rho_w)):
            _, f, h = self.diffuse(coef, rho)
            J[:, row, 0] = self.directional(f, h, d_a)
            J[:, row, 1] = self.directional(f, h, d_ls) / s
            J[:, row, 2] = self.directional(f, h, d_g)
        J[:, 2, 1] = self.collimated_derivative(s)
        return J

    def first_order_holds(self, alpha, cell: SigmaCell, g, I_b, I_w, rho_b, rho_w, J, sigma_b, sigma_w, std_a, std_g,
                          sigmas, tol):
        """Whether the first-order stds std_a, std_g hold over ±`sigmas` σ (invert.c check_first_order,
        operation for operation). From the polish's solution (α, g) at σt's cell and its Jacobian J
        (N, 3, 3), the measured (I_b, I_w) are moved by ±sigmas·σ in I_b, then in I_w (σ: sigma_b,
        sigma_w, the stds propagated); each move's linear prediction (α, g) + J2⁻¹·δI, clamped to the
        map's box, is corrected by one Newton step there: where a re-fit from the moved intensities
        lands, up to the square of its distance from the prediction. A bin holds where correction and
        clamp stay within tol·sigmas of each std for all four moves: two evaluations per move, where
        solving the re-fits took up to six."""
        (a_lo, a_hi), (g_lo, g_hi) = self.alpha_range, self.g_range
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
                coef, e_a, e_g = self.coefficients(a1, cell, g1)
                Ib, gb, kb = self.diffuse(coef, rho_b)
                Iw, gw, kw = self.diffuse(coef, rho_w)
                rb = Ib - (I_b + dI) if on_b else Ib - I_b
                rw = Iw - I_w if on_b else Iw - (I_w + dI)
                step_a, step_g = self._lm_step(self.directional(gb, kb, e_a), self.directional(gb, kb, e_g),
                                               self.directional(gw, kw, e_a), self.directional(gw, kw, e_g), rb, rw)[:2]
                a2 = np.minimum(np.maximum(a1 + step_a, a_lo), a_hi)
                g2 = np.minimum(np.maximum(g1 + step_g, g_lo), g_hi)
                holds &= (np.abs(a2 - alpha - da) <= limit_a) & (np.abs(g2 - g - dg) <= limit_g)
        return holds

    @staticmethod
    def propagate(J, sigma_I, sigma_t_var=None):
        """Standard deviations of (α, σt, g) from independent intensity noise sigma_I (N, 3), to
        first order: cov = J⁻¹ Σ J⁻ᵀ, using the block structure (row I_c has only ∂/∂σt).
        sigma_t_var (N,): further variance of σt that (α, g) follow as they follow I_c's (the
        in-scattering correction's). Infinite where the (α, g) block is singular."""
        if native.available():
            return native.propagate(J, sigma_I, sigma_t_var)
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


def step_is_small(step, last, step_tol, step_var, h, det):
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


def polish_step_var(I_b, I_w, noise_rel, noise_abs, mc_stderr, kappa, sd=None):
    """solve_alpha_g's step_var: (κ σ)² per bin, σ² the mean of I_b's and I_w's variance under the
    noise model σ_I = noise_rel·I + noise_abs (or their given stds, sd (N, 3)), with the map's MC
    std-error in quadrature."""
    sb, sw = (noise_rel * I_b + noise_abs, noise_rel * I_w + noise_abs) if sd is None else (sd[:, 0], sd[:, 1])
    return kappa * kappa * (0.5 * (sb * sb + sw * sw + 2.0 * mc_stderr * mc_stderr))


def refine_axis(axis: np.ndarray, factor: int) -> np.ndarray:
    """`factor` − 1 evenly spaced points inserted into every interval of `axis`."""
    t = np.linspace(0, len(axis) - 1, (len(axis) - 1) * factor + 1)
    return np.interp(t, np.arange(len(axis)), np.asarray(axis, dtype=np.float64))


def cubic_resample(values: np.ndarray, old: np.ndarray, new: np.ndarray, axis: int, kind: str = "cubic") -> np.ndarray:
    """`values` along `axis` from nodes `old` onto `new`: a cubic spline ("cubic") or PCHIP ("pchip")
    through the nodes (both reproduce them exactly); linear with fewer than 4 nodes."""
    from scipy.interpolate import PchipInterpolator, make_interp_spline

    x = np.array(old, dtype=np.float64)  # a copy: container arrays can be unaligned (scipy refuses those)
    front = np.moveaxis(np.asarray(values, dtype=np.float64), axis, 0)
    flat = np.array(front.reshape(len(x), -1))
    if kind == "pchip" and len(x) >= 3:
        curve = PchipInterpolator(x, flat, axis=0)
    else:
        curve = make_interp_spline(x, flat, k=3 if len(x) >= 4 else 1)
    out = curve(np.asarray(new, dtype=np.float64)).reshape(len(new), *front.shape[1:])
    return np.moveaxis(out, 0, axis)


def linear_resample(values: np.ndarray, old: np.ndarray, new: np.ndarray, axis: int) -> np.ndarray:
    """`values` along `axis` from nodes `old` onto `new`, piecewise linear (clamped at the ends)."""
    i = np.clip(np.searchsorted(old, new, side="right") - 1, 0, len(old) - 2)
    w = np.clip((new - old[i]) / (old[i + 1] - old[i]), 0.0, 1.0)
    front = np.moveaxis(values, axis, 0)
    shape = (-1,) + (1,) * (front.ndim - 1)
    out = front[i] * (1.0 - w.reshape(shape)) + front[i + 1] * w.reshape(shape)
    return np.moveaxis(out, 0, axis)


# The map's interpolation error is estimated from the map alone by leaving each interior node out in
# turn, along each axis, and predicting it by the same spline through the others (kernel.refined's
# kinds); that prediction spans twice the node spacing (a cubic's error grows like h⁴ with it) and the
# three axes' estimates overlap, so it overstates the error between the nodes the fit interpolates
# over. The factor is chosen for coverage, not for an rms of 1: an rms is set by the few largest errors
# and left most bins' ±1σ far too wide. Fitted on device-n1.5-l0.4's held-out set alone (`trimeter
# bench uncertainty --map device-n1.5-l0.4`: α's ±1σ/±2σ nearest 68/95 % over the three noise levels);
# device-n1.5-l0.8's held-out set is the check.
LEAVE_ONE_OUT_SCALE = 0.1


def node_model_variance(values: np.ndarray, mc_std: np.ndarray, alpha, log_sigma_t, g) -> np.ndarray:
    """Variance of the map's own error at its nodes, (na, ns, ng, k) like `values` (here I_b, I_w
    at the reference backgrounds): its MC std-error squared plus the interpolation error, each axis's
    leave-one-out prediction error (× LEAVE_ONE_OUT_SCALE) squared and summed over the axes (end nodes
    take their neighbour's)."""
    values = np.asarray(values, dtype=np.float64)
    var = np.asarray(mc_std, dtype=np.float64) ** 2
    for axis, (x, kind) in enumerate(((alpha, "cubic"), (log_sigma_t, "cubic"), (g, "pchip"))):
        x = np.array(x, dtype=np.float64)
        if len(x) < 4:
            continue
        err = np.zeros_like(values)
        front, out = np.moveaxis(values, axis, 0), np.moveaxis(err, axis, 0)  # views
        for j in range(1, len(x) - 1):
            keep = np.r_[0:j, j + 1:len(x)]
            out[j] = cubic_resample(front[keep], x[keep], x[j:j + 1], 0, kind=kind)[0] - front[j]
        out[0], out[-1] = out[1], out[-2]
        var = var + (LEAVE_ONE_OUT_SCALE * err) ** 2
    return var
