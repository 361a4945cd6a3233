"""What every method does with its solution, and the thicknesses' combination: the inputs' flags, the
stds by first-order propagation and the flags at the solution (finish), and inverse-variance weighting of
several thicknesses (combine). trimeter.inversion.api runs them for the guess-and-polish methods, the paper
method for its own solve; the compiled kernel's tm_fit and tm_combine do the same in C.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from trimeter.domain.parameters import FitResult
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.newton import first_order_holds

if TYPE_CHECKING:
    from trimeter.inversion.kernel import Kernel
    from trimeter.model.grid import ForwardGrid

INPUT_TOLERANCE = 1e-3   # intensities this far below 0 / above 1 are still taken as noise around the limit
DISAGREE_SIGMAS = 3.0
UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD = 0.1, 0.2  # FitFlag.UNDERDETERMINED above these stds
# First order is checked (std_approximate) only where a bin's α or g std is above these, a fifth of
# the UNDERDETERMINED thresholds: below them the check changes no coverage figure noticeably, and it
# costs eight forward evaluations per bin checked.
STD_CHECK_ALPHA, STD_CHECK_G = 0.02, 0.04
# STD_APPROXIMATE where a re-fit from the intensities moved by ±STD_CHECK_SIGMAS σ lands off the
# Jacobian's prediction by more than STD_CHECK_TOL of that interval (STD_CHECK_SIGMAS · the std): the
# bins it flags are those whose ±2σ covers the truth markedly less often. One Newton step from each
# linear prediction flags the same bins as solving the re-fits to convergence.
STD_CHECK_SIGMAS, STD_CHECK_TOL = 2.0, 0.3


def input_flags(I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
                 rho_w: np.ndarray) -> np.ndarray:
    flags = np.zeros(I_b.shape, dtype=np.int64)
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(I_b) & np.isfinite(I_w) & np.isfinite(I_c) & np.isfinite(rho_b) & np.isfinite(rho_w)
        flags |= np.where(~finite, int(FitFlag.NONFINITE_INPUT), 0)
        negative = (I_b < -INPUT_TOLERANCE) | (I_w < -INPUT_TOLERANCE) | (I_c < -INPUT_TOLERANCE)
        flags |= np.where(negative, int(FitFlag.NEGATIVE_INPUT), 0)
        above = (I_b > 1 + INPUT_TOLERANCE) | (I_w > 1 + INPUT_TOLERANCE) | (I_c > 1 + INPUT_TOLERANCE)
        flags |= np.where(above, int(FitFlag.ABOVE_ONE), 0)
        bad_bg = ~((rho_b >= 0) & (rho_b < rho_w) & (rho_w <= 1))
        flags |= np.where(finite & bad_bg, int(FitFlag.BAD_BACKGROUND), 0)
        flags |= np.where(finite & (I_b >= I_w), int(FitFlag.BLACK_NOT_BELOW_WHITE), 0)
    return flags


def sanitize(x: np.ndarray, lo: float, hi: float, fill: float) -> np.ndarray:
    return np.clip(np.where(np.isfinite(x), x, fill), lo, hi)


def underdetermined(std_a: np.ndarray, std_g: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):  # NaN std_g (g undefined) does not count
        return (std_a > UNDERDETERMINED_ALPHA_STD) | (std_g > UNDERDETERMINED_G_STD)


def conditioning_stds(kernel: Kernel, J: np.ndarray, sd: np.ndarray, floor_sd: np.ndarray | None, model: np.ndarray,
                      inscatter_var: np.ndarray | None, std_a: np.ndarray, std_g: np.ndarray,
                      g_undef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """α's and g's stds with the intensities' stds sd (N, 3) raised to at least the noise model's floor_sd
    (None: sd stands): what UNDERDETERMINED is judged on. model: (2, N) the map's error variances of I_b,
    I_w; std_a, std_g: the stds at sd, returned as they are where no std is raised."""
    if floor_sd is None or not np.any(floor_sd > sd):
        return std_a, std_g
    cond_var = np.maximum(sd * sd, floor_sd * floor_sd)
    cond_I = np.column_stack([np.sqrt(cond_var[:, 0] + model[0]), np.sqrt(cond_var[:, 1] + model[1]),
                              np.maximum(sd[:, 2], floor_sd[:, 2])])
    cond_a, _, cond_g = kernel.propagate(J, cond_I, inscatter_var)
    return cond_a, np.where(g_undef, np.nan, cond_g)


# bins whose stds already come with a caveat are not checked for STD_APPROXIMATE
_STD_CHECK_SKIP = int(UNUSABLE | FitFlag.UNDERDETERMINED | FitFlag.G_UNDEFINED | FitFlag.OUTSIDE_MAP
                      | FitFlag.NOT_CONVERGED)


def std_approximate(grid: ForwardGrid, flags: np.ndarray, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray,
                     ib: np.ndarray, iw: np.ndarray, rb: np.ndarray, rw: np.ndarray, J: np.ndarray,
                     sigma_I: np.ndarray, std_a: np.ndarray, std_g: np.ndarray) -> np.ndarray:
    """Where FitFlag.STD_APPROXIMATE belongs (invert.c tm_fit_solve does the same): bins whose α or g
    std is above STD_CHECK_ALPHA / STD_CHECK_G, none already flagged as unusable, underdetermined, g
    undefined, outside the map or not converged, on which the map bends within ±STD_CHECK_SIGMAS σ
    of the solve's (α, g) at σt (ForwardGrid.first_order_holds; J: its Jacobian there)."""
    with np.errstate(invalid="ignore"):
        large = (std_a > STD_CHECK_ALPHA) | (std_g > STD_CHECK_G)
    idx = np.flatnonzero(((flags & _STD_CHECK_SKIP) == 0) & large & np.isfinite(std_a) & np.isfinite(std_g))
    out = np.zeros(len(flags), dtype=bool)
    if len(idx):
        out[idx] = ~first_order_holds(grid, alpha[idx], grid.sigma_cell(sigma_t[idx]), g[idx], ib[idx], iw[idx],
                                      rb[idx], rw[idx], J[idx], sigma_I[idx, 0], sigma_I[idx, 1], std_a[idx],
                                      std_g[idx], STD_CHECK_SIGMAS, STD_CHECK_TOL)
    return out


def finish(grid: ForwardGrid, flags: np.ndarray, usable: np.ndarray, ib: np.ndarray, iw: np.ndarray,
            ic: np.ndarray, rb: np.ndarray, rw: np.ndarray, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray,
            residual: np.ndarray, sigma_beer: np.ndarray, *, method: str, kernel: Kernel, sd: np.ndarray,
            sigma_t_solved: np.ndarray, inscatter_ds: np.ndarray | None, inscatter_rel_std: float,
            thickness_rel_std: float, alpha_min_g: float, J: np.ndarray | None = None,
            solved: tuple[np.ndarray, ...] | None = None, floor_sd: np.ndarray | None = None) -> FitResult:
    """Flags and stds at the solution. sd: (N, 3) the intensities' stds; sigma_t_solved: the σt
    (α, g) were solved at (before the in-scattering correction inscatter_ds, None without one);
    solved: those (α, g) and the (I_b, I_w) they were solved for, J the Jacobian there (default: the
    solution's and the measured intensities). floor_sd: (N, 3) the noise model's stds, below which
    UNDERDETERMINED does not take the intensities' stds (None: sd stands)."""
    alpha_solved, g_solved, ib_solved, iw_solved = (alpha, g, ib, iw) if solved is None else solved
    var_in = sd * sd
    mc2 = grid.mc_stderr * grid.mc_stderr
    tolerance = 3.0 * np.sqrt(var_in[:, 0] + mc2 + var_in[:, 1] + mc2) + 1e-4
    # the map's own error at the solution (invert.c model_variance), else its median MC std-error
    model = (grid.model_variance(alpha, grid.sigma_cell(sigma_t_solved), g) if grid.model_var is not None
             else np.full((2, len(alpha)), mc2))
    sigma_I = np.column_stack([np.sqrt(var_in[:, 0] + model[0]), np.sqrt(var_in[:, 1] + model[1]), sd[:, 2]])
    with np.errstate(invalid="ignore"):
        not_conv = ~(residual <= tolerance)
    flags |= np.where(usable & not_conv, int(FitFlag.NOT_CONVERGED), 0)
    g_lo, g_hi = grid.g_range
    at_edge = ((g <= g_lo + 1e-9) & (g_lo > -1 + 1e-6)) | ((g >= g_hi - 1e-9) & (g_hi < 1 - 1e-6))
    flags |= np.where(usable & not_conv & at_edge, int(FitFlag.OUTSIDE_MAP), 0)

    alpha = np.clip(np.where(np.isfinite(alpha), alpha, np.nan), 0.0, 1.0)
    g = np.clip(np.where(np.isfinite(g), g, np.nan), -1.0, 1.0)
    sigma_t = np.maximum(sigma_t, 0.0)
    if J is None:  # lut/mlp hand over the Jacobian of their last forward evaluation
        J = grid.jacobian(np.nan_to_num(alpha), sigma_t, np.nan_to_num(g), rb, rw)
    inscatter_var = None if inscatter_ds is None else (inscatter_rel_std * inscatter_ds) ** 2
    std_a, std_s, std_g = kernel.propagate(J, sigma_I, inscatter_var)
    std_s = np.sqrt(std_s * std_s + (thickness_rel_std * sigma_t) ** 2)
    below = (flags & int(FitFlag.IC_BELOW_FLOOR)) != 0
    std_s = np.where(below, np.inf, std_s)
    g_undef = usable & ~(alpha >= alpha_min_g)
    flags |= np.where(g_undef, int(FitFlag.G_UNDEFINED), 0)
    g = np.where(g_undef, np.nan, g)
    std_g = np.where(g_undef, np.nan, std_g)
    # UNDERDETERMINED is the map's conditioning at no less than the instrument's noise model: a
    # capture's frame scatter alone misses drift and calibration error, and one quiet capture must
    # not make α and g look told apart where a realistic noise leaves them not
    cond_a, cond_g = conditioning_stds(kernel, J, sd, floor_sd, model, inscatter_var, std_a, std_g, g_undef)
    flags |= np.where(usable & underdetermined(cond_a, cond_g), int(FitFlag.UNDERDETERMINED), 0)
    flags |= np.where(std_approximate(grid, flags, alpha_solved, sigma_t_solved, g_solved, ib_solved, iw_solved, rb,
                                       rw, J, sigma_I, std_a, std_g), int(FitFlag.STD_APPROXIMATE), 0)
    blank = ~usable
    nan = np.nan
    return FitResult(alpha=np.where(blank, nan, alpha), sigma_t=np.where(blank, nan, sigma_t),
                     g=np.where(blank, nan, g), alpha_std=np.where(blank, nan, std_a),
                     sigma_t_std=np.where(blank, nan, std_s), g_std=np.where(blank, nan, std_g),
                     flags=flags.astype(np.int64), sigma_t_beer=np.where(blank, nan, sigma_beer), method=method,
                     conditioning_alpha_std=None if cond_a is std_a else np.where(blank, nan, cond_a),
                     conditioning_g_std=None if cond_g is std_g else np.where(blank, nan, cond_g))


# --------------------------------------------------------------------------------- thicknesses
def combine(results: list[FitResult], method: str) -> FitResult:
    """Inverse-variance combination of per-thickness fits; THICKNESS_DISAGREE where two finite
    estimates differ by more than 3 combined standard deviations (α, σt, or g). The reference of the
    compiled kernel's tm_combine (Kernel.combine), which fit() runs where it can."""
    flags = np.bitwise_or.reduce([r.flags for r in results])
    # A thickness whose bins were unusable drops out; its UNUSABLE bits stay only if all dropped.
    all_unusable = np.logical_and.reduce([(r.flags & int(UNUSABLE)) != 0 for r in results])
    flags = np.where(all_unusable, flags, flags & ~int(UNUSABLE))
    flags &= ~int(FitFlag.UNDERDETERMINED)  # judged again on the combined stds below
    # every column at once, (column, thickness, bin): a handful of array operations whatever the
    # number of columns (per column they cost a third of a two-thickness fit)
    names = ("alpha", "sigma_t", "g", "sigma_t_beer")
    std_names = ("alpha_std", "sigma_t_std", "g_std", "sigma_t_std")  # the Beer-Lambert column: σt's std
    vals = np.array([[getattr(r, name) for r in results] for name in names])
    stds = np.array([[getattr(r, name) for r in results] for name in std_names])
    value, std = _weighted(vals, stds)
    # first order failing at one thickness matters where that thickness carries weight: a quarter or
    # more of α's or g's inverse-variance weight
    approx = np.zeros(len(flags), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for r in results:  # only the few bins flagged at that thickness are weighed
            idx = np.flatnonzero(r.flags & int(FitFlag.STD_APPROXIMATE))
            heavy = ((std[0, idx] / r.alpha_std[idx]) ** 2 >= 0.25) | ((std[2, idx] / r.g_std[idx]) ** 2 >= 0.25)
            approx[idx] |= heavy
    flags = (flags & ~int(FitFlag.STD_APPROXIMATE)) | np.where(approx, int(FitFlag.STD_APPROXIMATE), 0)
    disagree = _disagree(vals[:3], stds[:3])  # not the consistency column
    flags |= np.where(disagree, int(FitFlag.THICKNESS_DISAGREE), 0)
    usable = (flags & int(UNUSABLE)) == 0
    # judged on the conditioning stds (at least the noise model's), combined alike
    cond_a, cond_g = std[0], std[2]
    if any(r.conditioning_alpha_std is not None or r.conditioning_g_std is not None for r in results):
        cond = np.array([[r.alpha_std if r.conditioning_alpha_std is None else r.conditioning_alpha_std
                          for r in results],
                         [r.g_std if r.conditioning_g_std is None else r.conditioning_g_std for r in results]])
        cond_a, cond_g = _weighted(vals[[0, 2]], cond)[1]
    flags |= np.where(usable & underdetermined(cond_a, cond_g), int(FitFlag.UNDERDETERMINED), 0)
    same = cond_a is std[0]
    return FitResult(alpha=value[0], sigma_t=value[1], g=value[2], alpha_std=std[0], sigma_t_std=std[1],
                     g_std=std[2], flags=flags, sigma_t_beer=value[3], method=method, per_thickness=results,
                     conditioning_alpha_std=None if same else cond_a, conditioning_g_std=None if same else cond_g)


def _weighted(vals: np.ndarray, stds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance mean over the thicknesses (axis -2) and its std. Where no thickness has a
    usable std: the plain mean of the finite values and the smallest of their stds; NaN where no
    value is finite (a bin unusable at every thickness). Written out, not with nanmean/nanmin: those
    warn on all-NaN columns and cost more than the arithmetic here; the fallback is computed only for
    the bins that need it."""
    finite = np.isfinite(vals)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(finite & (stds > 0) & (stds < np.inf), 1.0 / (stds * stds), 0.0)  # NaN stds fail both
        wsum = w.sum(axis=-2)
        v0 = np.where(finite, vals, 0.0)
        value = (v0 * w).sum(axis=-2) / wsum
        std = 1.0 / np.sqrt(wsum)
        fallback = ~(wsum > 0)
        if fallback.any():
            count = finite.sum(axis=-2)[fallback]
            some = count > 0
            value[fallback] = np.where(some, v0.sum(axis=-2)[fallback] / count, np.nan)
            smallest = np.fmin.reduce(np.where(finite, stds, np.inf), axis=-2)[fallback]  # fmin: a NaN std does not win
            std[fallback] = np.where(some, smallest, np.nan)
    return value, std


def _disagree(vals: np.ndarray, stds: np.ndarray) -> np.ndarray:
    """Per bin, whether two thicknesses (axis -2) differ by more than DISAGREE_SIGMAS combined stds
    in any column (axis 0); each pair once."""
    k = vals.shape[-2]
    bad = np.zeros(vals.shape[-1], dtype=bool)
    with np.errstate(invalid="ignore"):
        for i in range(k):
            for j in range(i + 1, k):
                diff = np.abs(vals[:, i] - vals[:, j])
                scale = np.sqrt(stds[:, i] ** 2 + stds[:, j] ** 2)
                bad |= (diff > DISAGREE_SIGMAS * scale).any(axis=0)
    return bad
