"""The map's interpolant: A, B, C on an (α, ln σt, g) grid, trilinear between the nodes with analytic
derivatives, evaluated per bin as gathers and array arithmetic (no Python loop per bin). Every method
polishes on it, the twin renders its virtual samples from it and `trimeter map query` answers with it;
trimeter.inversion solves it (the Newton polish, the uncertainty propagation).
"""

from __future__ import annotations

from dataclasses import dataclass

from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import ArrayLike

from trimeter.model.cells import cubic_resample, linear_resample, refine_axis, regular_cell, trilinear
from trimeter.model.sample_setup import SampleSetup

if TYPE_CHECKING:
    from trimeter.model.inscatter_table import InscatterTable

class MapNodes(Protocol):
    """What a grid is built from on an appearance map's own nodes (trimeter.formats.appearance.AppearanceMap
    is one; the formats sit above the model)."""

    @property
    def alpha(self) -> np.ndarray: ...
    @property
    def sigma_t(self) -> np.ndarray: ...
    @property
    def g(self) -> np.ndarray: ...
    @property
    def A(self) -> np.ndarray: ...
    @property
    def B(self) -> np.ndarray: ...
    @property
    def C(self) -> np.ndarray: ...
    @property
    def std_b(self) -> np.ndarray: ...
    @property
    def std_w(self) -> np.ndarray: ...
    @property
    def setup(self) -> SampleSetup: ...


class TableNodes(Protocol):
    """What a grid is built from on a device table's forward section (trimeter.formats.device_table.DeviceTable
    is one)."""

    @property
    def alpha(self) -> np.ndarray: ...
    @property
    def log_sigma_t(self) -> np.ndarray: ...
    @property
    def g(self) -> np.ndarray: ...
    @property
    def coefficients_grid(self) -> np.ndarray: ...
    @property
    def setup(self) -> SampleSetup: ...
    @property
    def mc_stderr(self) -> float: ...


@dataclass(frozen=True)
class SigmaCell:
    """Where each bin's σt sits on the grid (fixed during a Newton solve)."""
    index: np.ndarray        # int (N,) lower node
    weight: np.ndarray       # (N,) in [0, 1]
    log_sigma_t: np.ndarray  # (N,) clamped to the grid


# How a map is evaluated between its nodes — everywhere (ForwardGrid.between_nodes): refined by these
# factors with cubic splines in α and ln σt and PCHIP in g, then trilinear. Trilinear interpolation
# between the raw nodes (ln σt ×1.6 apart, 7 g) was the maps' main error, not their MC noise; PCHIP
# in g, because a cubic spline overshoots between its few noisy nodes. ln σt is refined to ~121
# nodes because between the nodes of a refined axis the kernel is linear in B, while B (the light
# through the slab and back) falls like exp(−c·σt·ℓ): coarser cells missed B for dark samples.
# The figures behind these choices: `trimeter bench fit`; as first measured, the git history of maps/README.md.
BETWEEN_NODES_ALPHA = 2
BETWEEN_NODES_SIGMA_NODES = 121  # ln σt refined to about this many nodes
BETWEEN_NODES_G = 2


def sigma_refine_factor(n_sigma: int) -> int:
    """The refinement that brings n_sigma nodes to about BETWEEN_NODES_SIGMA_NODES (1: none)."""
    return max(1, round((BETWEEN_NODES_SIGMA_NODES - 1) / max(n_sigma - 1, 1)))


class ForwardGrid:
    """A, B, C (coefficients: (na, ns, ng, 3)) on the axes α, ln σt, g for one sample set-up, with
    the map's median MC std-error of I."""

    def __init__(self, alpha: ArrayLike, log_sigma_t: ArrayLike, g: ArrayLike, coefficients: ArrayLike, *,
                 setup: SampleSetup, mc_stderr: float = 0.0) -> None:
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
        self.setup = setup
        self.mc_stderr = float(mc_stderr)
        self.alpha_range = (float(self.alpha[0]), float(self.alpha[-1]))
        self.g_range = (float(self.g[0]), float(self.g[-1]))
        self.sigma_t_range = (float(np.exp(self.log_sigma_t[0])), float(np.exp(self.log_sigma_t[-1])))
        # in-scattering into I_c (attach_inscatter): None means I_c is the unscattered beam alone
        self.inscatter_grid: tuple[np.ndarray, float, float] | None = None  # (L, 1/Δτ, τ max)
        # the map's own error as variances of (I_b, I_w) on this grid's nodes (attach_model_variance), or None
        self.model_var: np.ndarray | None = None

    @classmethod
    def from_map(cls, amap: MapNodes) -> ForwardGrid:
        """The grid on an appearance map's own nodes (anything with its arrays and `setup`)."""
        mc = float(np.median(np.concatenate([amap.std_b.ravel(), amap.std_w.ravel()])))
        return cls(amap.alpha, np.log(amap.sigma_t), amap.g, np.stack([amap.A, amap.B, amap.C], axis=-1),
                   setup=amap.setup, mc_stderr=mc)

    @classmethod
    def from_table(cls, table: TableNodes) -> ForwardGrid:
        """The grid on a map table's forward section (its f32 set-up: what the device fits with)."""
        return cls(table.alpha, table.log_sigma_t, table.g, table.coefficients_grid, setup=table.setup,
                   mc_stderr=table.mc_stderr)

    # the set-up's numbers, read per bin by the kernels
    @property
    def n(self) -> float:
        return self.setup.n

    @property
    def thickness_mm(self) -> float:
        return self.setup.thickness_mm

    @property
    def cover_slide_n(self) -> float | None:
        return self.setup.cover_slide_n

    def refined(self, alpha: int = 1, sigma: int = 1, g: int = 1) -> ForwardGrid:
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
        return ForwardGrid(axes[0], axes[1], axes[2], coef, setup=self.setup, mc_stderr=self.mc_stderr)

    def between_nodes(self) -> ForwardGrid:
        """This map as evaluated between its nodes everywhere (see BETWEEN_NODES_ALPHA)."""
        return self.refined(BETWEEN_NODES_ALPHA, sigma_refine_factor(len(self.log_sigma_t)), BETWEEN_NODES_G)

    @property
    def coefficients_grid(self) -> np.ndarray:
        """(na, ns, ng, 3): A, B, C at the nodes."""
        return self._nodes

    # ---------------------------------------------------------------------------------- helpers
    @staticmethod
    def _cell(axis: np.ndarray, inv_d: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # np.minimum/maximum: np.clip's Python wrapper costs more than the work at N ≈ 1000
        i = np.minimum(np.maximum(np.searchsorted(axis, x, side="right") - 1, 0), len(axis) - 2)
        w = np.minimum(np.maximum((x - axis[i]) * inv_d[i], 0.0), 1.0)
        return i, w

    def alpha_g_cells(self, alpha: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The (α, g) cells of bins: the cells whose derivatives a step uses."""
        return self._cell(self.alpha, self._inv_da, alpha)[0], self._cell(self.g, self._inv_dg, g)[0]

    def sigma_cell(self, sigma_t: ArrayLike) -> SigmaCell:
        with np.errstate(divide="ignore", invalid="ignore"):
            ls = np.log(np.asarray(sigma_t, dtype=np.float64))
        ls = np.clip(np.nan_to_num(ls, nan=self.log_sigma_t[0], posinf=self.log_sigma_t[-1],
                                   neginf=self.log_sigma_t[0]), self.log_sigma_t[0], self.log_sigma_t[-1])
        i, w = self._cell(self.log_sigma_t, self._inv_ds, ls)
        return SigmaCell(i, w, ls)

    def clamp_sigma_t(self, sigma_t: np.ndarray) -> np.ndarray:
        """σt clamped to the grid as sigma_cell does it (NaN → lowest node), without the cell."""
        lo, hi = self.sigma_t_range
        return np.minimum(np.where(sigma_t >= lo, sigma_t, lo), hi)

    def collimated(self, sigma_t: np.ndarray) -> np.ndarray:
        return self.setup.collimated(sigma_t)

    def attach_inscatter(self, table: InscatterTable | None) -> None:
        """Take in-scattered light into I_c into account (a trimeter.model.inscatter_table.InscatterTable,
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

    def attach_model_variance(self, node_var: ArrayLike | None, alpha: ArrayLike, log_sigma_t: ArrayLike,
                              g: ArrayLike) -> None:
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

    def model_variance(self, alpha: np.ndarray, cell: SigmaCell, g: np.ndarray) -> np.ndarray:
        """(2, N): the map's error variance of I_b, I_w at (α, σt's cell, g), trilinear on the nodes
        (invert.c model_variance, operation for operation); zeros without attach_model_variance."""
        if self.model_var is None:
            return np.zeros((2, len(cell.index)))
        ia, wa = self._cell(self.alpha, self._inv_da, alpha)
        ig, wg = self._cell(self.g, self._inv_dg, g)
        # the nodes hold (I_b, I_w) pairs: the weights broadcast over that last axis
        return trilinear(self.model_var, ia, wa[:, None], cell.index, cell.weight[:, None], ig, wg[:, None]).T

    def inscatter_log1p(self, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray) -> np.ndarray:
        """L = ln(1 + r) at (α, σt, g) from inscatter_grid (invert.c inscatter_log1p, operation for
        operation): trilinear on the α and g nodes and the optical depths σt·ℓ (clamped to the table)."""
        if self.inscatter_grid is None:
            raise ValueError("no in-scattering table attached (attach_inscatter)")
        L, inv_dt, tau_max = self.inscatter_grid
        ia, wa = self._cell(self.alpha, self._inv_da, alpha)
        ig, wg = self._cell(self.g, self._inv_dg, g)
        tau = np.asarray(sigma_t * self.thickness_mm, dtype=np.float64)
        tau = np.where(np.isfinite(tau), tau, 0.0)  # an unusable bin's NaN: any index will do, not a wild one
        it, wt = regular_cell(np.minimum(np.maximum(tau, 0.0), tau_max) * inv_dt, L.shape[1])
        return trilinear(L, ia, wa, it, wt, ig, wg)


    def collimated_measured(self, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray) -> np.ndarray:
        """I_c as the instrument reads it: the unscattered beam and, with an in-scattering table, the
        light scattered into the detector's aperture."""
        unscattered = self.collimated(sigma_t)
        if self.inscatter_grid is None:
            return unscattered
        return unscattered * np.exp(self.inscatter_log1p(alpha, sigma_t, g))

    @property
    def transmittance_limits(self) -> tuple[float, float]:
        """(T(σt = 0), the largest I_c the Beer-Lambert inverse takes) of this grid's sample set-up."""
        return self.setup.transmittance_limits

    @property
    def stack_constants(self) -> tuple[float, float, float]:
        """(a, b, T(σt = 0)) of I_c = a·x / (1 − b·x²), x = exp(−σt ℓ)."""
        return self.setup.stack_constants

    def coefficients(self, alpha: np.ndarray, cell: SigmaCell, g: np.ndarray,
                     with_sigma_derivative: bool = False) -> tuple[np.ndarray, ...]:
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
    def diffuse(coef: np.ndarray, rho: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """I(ρ) = A + Bρ/(1 − Cρ) and its gradient in (A, B, C) as (dI/dB, dI/dC), coef (3, N)."""
        A, B, C = coef
        f = rho / (1.0 - C * rho)
        return A + B * f, f, B * f * f

    @staticmethod
    def directional(grad_B: np.ndarray, grad_C: np.ndarray, d: np.ndarray) -> np.ndarray:
        """dI along one parameter from the (A, B, C) derivatives d (3, N)."""
        return d[0] + grad_B * d[1] + grad_C * d[2]

    def intensities(self, alpha: ArrayLike, sigma_t: np.ndarray, g: ArrayLike, rho_b: ArrayLike,
                    rho_w: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(I_b, I_w, I_c) by the kernel (for training data and checks; σt clamped to the grid)."""
        cell = self.sigma_cell(sigma_t)
        alpha, g = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(g, float))
        coef, _, _ = self.coefficients(alpha.ravel(), cell, g.ravel())
        I_b = self.diffuse(coef, np.asarray(rho_b, float))[0]
        I_w = self.diffuse(coef, np.asarray(rho_w, float))[0]
        return I_b, I_w, self.collimated_measured(alpha, sigma_t, g)

    # ----------------------------------------------------------------------------------- solving

    def residual_and_jacobian(self, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell, rho_b: np.ndarray,
                              rho_w: np.ndarray, alpha: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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

    def collimated_derivative(self, s: np.ndarray) -> np.ndarray:
        return self.setup.collimated_derivative(s)


    def jacobian(self, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray, rho_b: np.ndarray,
                 rho_w: np.ndarray) -> np.ndarray:
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


# The map's interpolation error is estimated from the map alone by leaving each interior node out in
# turn, along each axis, and predicting it by the same spline through the others (ForwardGrid.refined's
# kinds); that prediction spans twice the node spacing (a cubic's error grows like h⁴ with it) and the
# three axes' estimates overlap, so it overstates the error between the nodes the fit interpolates
# over. The factor is chosen for coverage, not for an rms of 1: an rms is set by the few largest errors
# and left most bins' ±1σ far too wide. It is chosen on the calibration part of the device maps' held-out
# sets (trimeter.bench.heldout.heldout_part; `trimeter bench uncertainty --part calibration
# --leave-one-out-scale …` prints the sweep), never on the scored part the bench reports coverage on.
LEAVE_ONE_OUT_SCALE = 0.1


def node_model_variance(values: np.ndarray, mc_std: np.ndarray, alpha: ArrayLike, log_sigma_t: ArrayLike,
                        g: ArrayLike) -> np.ndarray:
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
