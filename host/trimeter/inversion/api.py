"""`trimeter.fit`: one entry point for every inversion method and for one or two thicknesses.

Flow per map (thickness): validate the inputs into flags (never an exception for bad values) →
σt from I_c (exact Beer-Lambert incl. Fresnel; a lower bound under the noise floor) → (α, g) by the
method → flags for g undefined / outside the map / not converged → per-bin standard deviations by
first-order propagation through the forward map's Jacobian of every known error: the intensities'
noise (given per bin, else the noise model), the map's own error at the solution (its MC std-error
and interpolation error, trimeter.model.grid.node_model_variance), the in-scattering correction's and
the thickness's uncertainty. Several thicknesses are then combined by inverse-variance weighting (the
paper's method pools its samples and takes the median, as written) and checked against each other.

The fit takes what it solves as model objects (FitModel: a map's forward grid, table inverter, MLP
session, its nodes for the paper method), loaded by trimeter.maps.artifacts (`trimeter.fit` takes map
names and paths and loads them there), and the kernel (numpy or C, trimeter.inversion.kernel) it is
handed. Methods come from one table (trimeter.inversion.methods). For a guess-and-polish method, one
thickness's whole flow runs in one C call with the compiled kernel (`tm_fit`); `_prepare` + the solve
+ `_finish` below are its reference.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.kernel import Kernel, default_kernel
from trimeter.inversion.lut import TableInverter
from trimeter.inversion.newton import correct_inscatter, first_order_holds, polish_step_var
from trimeter.inversion.strategy import Method
from trimeter.model.grid import ForwardGrid
from trimeter.model.setup import SampleSetup

log = logging.getLogger("trimeter.inversion")

if TYPE_CHECKING:
    from scipy.interpolate import LinearNDInterpolator

    from trimeter.inversion.mlp import MlpInverter

# one thickness's (I_b, I_w, I_c, ρ_b, ρ_w) over its bins
Inputs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]

_INPUT_TOLERANCE = 1e-3   # intensities this far below 0 / above 1 are still taken as noise around the limit
_DISAGREE_SIGMAS = 3.0
UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD = 0.1, 0.2  # FitFlag.UNDERDETERMINED above these stds
# The polish also stops a bin once a step moved α and g by less than this fraction of their noise
# std (the noise model's): further steps only wander along what the data cannot tell apart (thick,
# dark bins would take every step). Larger fractions stop underdetermined bins too far from the map's
# exact solution. A bin also stops when its step shrank at least 4× and the next one would be below
# that fraction (newton.step_is_small). The figures behind the value: the git history of maps/README.md.
POLISH_TOL_STD = 3e-3
# The in-scattering correction's relative std: how far the map's table and independent, longer traces
# differ over the measurable gamut, with room for the tracer's approximations
# (trimeter.forward.transport.inscatter_tracer).
INSCATTER_REL_STD = 0.05
# First order is checked (_std_approximate) only where a bin's α or g std is above these, a fifth of
# the UNDERDETERMINED thresholds: below them the check changes no coverage figure noticeably, and it
# costs eight forward evaluations per bin checked.
STD_CHECK_ALPHA, STD_CHECK_G = 0.02, 0.04
# STD_APPROXIMATE where a re-fit from the intensities moved by ±STD_CHECK_SIGMAS σ lands off the
# Jacobian's prediction by more than STD_CHECK_TOL of that interval (STD_CHECK_SIGMAS · the std): the
# bins it flags are those whose ±2σ covers the truth markedly less often. One Newton step from each
# linear prediction flags the same bins as solving the re-fits to convergence.
STD_CHECK_SIGMAS, STD_CHECK_TOL = 2.0, 0.3


def _polish_tol_std(polish_tol: float) -> float:
    return POLISH_TOL_STD if polish_tol > 0 else 0.0  # polish_tol = 0: a fixed step count


class FitModel(Protocol):
    """What a fit needs of one map (thickness): trimeter.maps.artifacts.MapArtifacts is one."""
    # read-only: a fit never sets them (properties, so that a model may compute them)
    @property
    def name(self) -> str: ...

    @property
    def reference_rhos(self) -> tuple[float, float]: ...

    # the sample set-up every step of the fit uses (the polish grid's: grid.setup)
    @property
    def setup(self) -> SampleSetup: ...

    # the map table's guess and the polish's forward grid (inverter.grid)
    @property
    def inverter(self) -> TableInverter: ...

    # the appearance map's nodes, A, B, C and collimated_measured (paper); maps sits above the inversion
    @property
    def map(self) -> Any: ...

    # the paper method's triangulations of this map (None: none kept)
    @property
    def paper_cache(self) -> OrderedDict[tuple[float, float], LinearNDInterpolator] | None: ...

    @property
    def grid(self) -> ForwardGrid: ...

    def mlp(self, model: str | Path | None = None) -> MlpInverter: ...


# ---------------------------------------------------------------------------------------- the fit
def fit(models: FitModel | Sequence[FitModel], I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike,
        rho_b: ArrayLike | None = None, rho_w: ArrayLike | None = None, method: str = "lut", *,
        kernel: Kernel | None = None,
        noise_rel: float = 0.005, noise_abs: float = 2e-4, ic_floor: float = 1e-4,
        alpha_min_g: float = 0.02, polish: int | None = None, polish_tol: float = 1e-6, samples: int = 250,
        epsilon: float = 0.01,
        seed: int = 0, mlp_model: str | Path | None = None, I_b_std: ArrayLike | None = None,
        I_w_std: ArrayLike | None = None, I_c_std: ArrayLike | None = None,
        thickness_std_mm: float | ArrayLike = 0.0, inscatter_rel_std: float = INSCATTER_REL_STD,
        first_row: int = 0) -> FitResult:
    """Invert measured intensities (arrays over wavelength bins) to α, σt [1/mm], g.

    models: a FitModel (trimeter.maps.artifacts.load_artifacts), or a list of them (the same material at
    several thicknesses); with k maps, I_b, I_w, I_c (and ρ's, if per-thickness) have shape (k, N).
    method: a name in trimeter.inversion.methods; kernel: numpy or C (default: default_kernel()).
    rho_b, rho_w: per-bin background reflectances (default: each map's reference backgrounds).
    noise_rel, noise_abs: the intensity noise model σ_I = noise_rel·I + noise_abs (for the stds and
    the convergence tolerance) where the intensities' own stds are not given; ic_floor: I_c below it
    bounds σt from below only.
    I_b_std, I_w_std, I_c_std: the intensities' standard deviations (shaped like them, or scalars),
    e.g. from the capture's frame-to-frame scatter; where one is missing or NaN, the noise model's.
    thickness_std_mm: the sample thickness's std (one number, or one per map): it widens σt's std
    by σt·std/ℓ (α and g do not depend on it: the slab's intensities depend on σt·ℓ).
    inscatter_rel_std: the in-scattering correction's relative std.
    polish, polish_tol: at most `polish` Newton iterations after the method's guess (0 = the raw
    guess; None: the method's default_polish); a bin stops once a step moved α and g by at most
    polish_tol, or by less than POLISH_TOL_STD of their noise std, or by a quarter of the step before
    with the next one, extrapolated, below that (polish_tol = 0: every bin takes `polish` steps).
    samples, epsilon, seed: the paper method's ε-median (samples=0: plain interpolation); first_row: the
    bins' position in a larger input fitted in parts, so that their ε-samples are those of one fit of it all
    (every other method fits each bin on its own).
    """
    from trimeter.inversion.methods import get_method  # the table imports the methods, which use this module
    from trimeter.validation import require_number

    strategy = get_method(method)
    kernel = default_kernel() if kernel is None else kernel
    polish = strategy.default_polish if polish is None else polish

    noise_rel = require_number("noise_rel", noise_rel, lo=0.0)
    noise_abs = require_number("noise_abs", noise_abs, lo=0.0)
    ic_floor = require_number("ic_floor", ic_floor, lo=0.0, lo_open=True, hi=1.0)
    alpha_min_g = require_number("alpha_min_g", alpha_min_g, lo=0.0, hi=1.0)
    epsilon = require_number("epsilon", epsilon, lo=0.0)
    polish, samples = int(require_number("polish", polish, lo=0)), int(require_number("samples", samples, lo=0))
    polish_tol = require_number("polish_tol", polish_tol, lo=0.0)
    inscatter_rel_std = require_number("inscatter_rel_std", inscatter_rel_std, lo=0.0)
    amaps = list(models) if isinstance(models, Sequence) else [models]
    if not amaps:
        raise InputError("maps must name at least one map")
    if not all(hasattr(m, "inverter") for m in amaps):  # a map, a path or a name: trimeter.fit loads those
        raise InputError("inversion.api.fit takes loaded maps (trimeter.maps.artifacts.load_artifacts); "
                         "trimeter.fit takes maps, paths and names")
    k = len(amaps)
    arrays = _shape_inputs(k, I_b, I_w, I_c, rho_b, rho_w, amaps)
    stds = _shape_stds(k, arrays, (I_b_std, I_w_std, I_c_std), noise_rel, noise_abs)
    thickness_rel = [t / m.setup.thickness_mm for t, m in zip(_thickness_stds(k, thickness_std_mm), amaps, strict=True)]
    opts: dict[str, Any] = dict(noise_rel=noise_rel, noise_abs=noise_abs, ic_floor=ic_floor, alpha_min_g=alpha_min_g,
                                inscatter_rel_std=inscatter_rel_std)
    if strategy.fit_all is not None:  # strategy.joint
        return strategy.fit_all(amaps, arrays, stds, thickness_rel, kernel=kernel, samples=samples, epsilon=epsilon,
                                seed=seed, first_row=int(require_number("first_row", first_row, lo=0)), **opts)
    # several thicknesses: each fitted into its place in the kernel's combine layout (no gathering after)
    blocks = kernel.output_blocks(k, arrays[0][0].shape[0]) if k > 1 else None
    singles = [_fit_one(amap, *arrays[i], sd=stds[i], thickness_rel_std=thickness_rel[i], method=strategy,
                        kernel=kernel, polish=polish, polish_tol=polish_tol, mlp_model=mlp_model,
                        block=None if blocks is None else blocks[i], **opts)
               for i, amap in enumerate(amaps)]
    if k == 1:
        return singles[0]
    # (a kernel whose fused path declined a thickness left that one's columns elsewhere: gathered then)
    fused = blocks is not None and all(r.alpha.base is blocks for r in singles)
    combined = kernel.combine(singles, method, underdetermined_std=(UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD),
                              disagree_sigmas=_DISAGREE_SIGMAS, blocks=blocks if fused else None)
    combined = combine(singles, method) if combined is None else combined
    combined.guess_fallback_bins = sum(r.guess_fallback_bins for r in singles)
    return combined


def _shape_inputs(k: int, I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike, rho_b: ArrayLike | None,
                  rho_w: ArrayLike | None, amaps: Sequence[FitModel]) -> list[Inputs]:
    try:
        I_b, I_w, I_c = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (I_b, I_w, I_c))
    except (TypeError, ValueError) as exc:
        raise InputError(f"I_b, I_w, I_c must be numeric arrays ({exc})") from None
    if not (I_b.shape == I_w.shape == I_c.shape):
        raise InputError(f"I_b, I_w, I_c must have one shape, got {I_b.shape}, {I_w.shape}, {I_c.shape}")
    if k == 1 and I_b.ndim == 1:
        I_b, I_w, I_c = I_b[None], I_w[None], I_c[None]
    if I_b.ndim != 2 or I_b.shape[0] != k:
        raise InputError(f"with {k} map(s) the intensities must have shape ({k}, bins), got {I_b.shape}")
    n = I_b.shape[1]
    rhos = []
    for i, (name, rho) in enumerate((("rho_b", rho_b), ("rho_w", rho_w))):
        if rho is None:
            rho = np.array([m.reference_rhos[i] for m in amaps])[:, None]
        full = np.empty((k, n))  # contiguous rows, as the C kernel reads them (broadcast_to: a copy later)
        try:
            full[...] = rho
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name} must be a number or an array over the bins ({exc})") from None
        rhos.append(full)
    return [(I_b[i], I_w[i], I_c[i], rhos[0][i], rhos[1][i]) for i in range(k)]


def _shape_stds(k: int, arrays: list[Inputs], given: tuple[ArrayLike | None, ...], noise_rel: float,
                noise_abs: float) -> list[np.ndarray | None]:
    """Per thickness, the intensities' stds as an (N, 3) array, or None when none was given (the
    noise model then stands everywhere, computed where it is used). A missing column, or a NaN in
    one, takes the noise model's value at that (sanitized) intensity."""
    if all(v is None for v in given):
        return [None] * k
    n = len(arrays[0][0])
    out = np.empty((k, n, 3))
    for j, (name, value) in enumerate(zip(("I_b_std", "I_w_std", "I_c_std"), given, strict=True)):
        if value is None:
            out[:, :, j] = np.nan
            continue
        try:
            v = np.asarray(value, dtype=float)
            out[:, :, j] = v  # a scalar, one row of N for every thickness, or (k, N)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name} must be a number or an array shaped like the intensities ({exc})") from None
        with np.errstate(invalid="ignore"):
            if np.any(out[:, :, j] < 0):
                raise InputError(f"{name} must not be negative")
    if np.any(np.isinf(out)):
        raise InputError("I_b_std, I_w_std, I_c_std must be finite (or NaN: the noise model's there)")
    for i, (I_b, I_w, I_c, _, _) in enumerate(arrays):
        for j, (x, fill) in enumerate(((I_b, 0.0), (I_w, 1.0), (I_c, 1.0))):
            model = noise_rel * _sanitize(x, 0.0, 1.0, fill) + noise_abs
            out[i, :, j] = np.where(np.isnan(out[i, :, j]), model, out[i, :, j])
    return list(out)


def _thickness_stds(k: int, thickness_std_mm: float | ArrayLike) -> list[float]:
    from trimeter.validation import require_number

    values = list(thickness_std_mm) if isinstance(thickness_std_mm, (list, tuple, np.ndarray)) else \
        [thickness_std_mm] * k
    if len(values) != k:
        raise InputError(f"thickness_std_mm: give one value or one per map ({k}), got {len(values)}")
    return [require_number("thickness_std_mm", 0.0 if v is None else v, lo=0.0) for v in values]


def _input_flags(I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
                 rho_w: np.ndarray) -> np.ndarray:
    flags = np.zeros(I_b.shape, dtype=np.int64)
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(I_b) & np.isfinite(I_w) & np.isfinite(I_c) & np.isfinite(rho_b) & np.isfinite(rho_w)
        flags |= np.where(~finite, int(FitFlag.NONFINITE_INPUT), 0)
        negative = (I_b < -_INPUT_TOLERANCE) | (I_w < -_INPUT_TOLERANCE) | (I_c < -_INPUT_TOLERANCE)
        flags |= np.where(negative, int(FitFlag.NEGATIVE_INPUT), 0)
        above = (I_b > 1 + _INPUT_TOLERANCE) | (I_w > 1 + _INPUT_TOLERANCE) | (I_c > 1 + _INPUT_TOLERANCE)
        flags |= np.where(above, int(FitFlag.ABOVE_ONE), 0)
        bad_bg = ~((rho_b >= 0) & (rho_b < rho_w) & (rho_w <= 1))
        flags |= np.where(finite & bad_bg, int(FitFlag.BAD_BACKGROUND), 0)
        flags |= np.where(finite & (I_b >= I_w), int(FitFlag.BLACK_NOT_BELOW_WHITE), 0)
    return flags


def _sanitize(x: np.ndarray, lo: float, hi: float, fill: float) -> np.ndarray:
    return np.clip(np.where(np.isfinite(x), x, fill), lo, hi)


def _fit_one(model: FitModel, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
             rho_w: np.ndarray, *, sd: np.ndarray | None, thickness_rel_std: float, method: Method, kernel: Kernel,
             polish: int, polish_tol: float, mlp_model: str | Path | None, noise_rel: float, noise_abs: float,
             ic_floor: float, alpha_min_g: float, inscatter_rel_std: float,
             block: np.ndarray | None = None) -> FitResult:
    inverter = model.inverter
    grid = inverter.grid
    guesser = None if method.guesser is None else method.guesser(model, {"mlp_model": mlp_model})
    options = native_options(model, grid, polish=polish, polish_tol=polish_tol, noise_rel=noise_rel,
                             noise_abs=noise_abs, ic_floor=ic_floor, alpha_min_g=alpha_min_g,
                             thickness_rel_std=thickness_rel_std, inscatter_rel_std=inscatter_rel_std)
    out = kernel.fused_fit(inverter, I_b, I_w, I_c, rho_b, rho_w, sd=sd, guesser=guesser, options=options,
                           block=block)
    if out is not None:
        if sd is None:  # the noise model's stds: the conditioning stds are the stds themselves
            out["conditioning_alpha_std"] = out["conditioning_g_std"] = None
        return _said(FitResult(**out, method=method.name))
    p = _prepare(model, grid, I_b, I_w, I_c, rho_b, rho_w, ic_floor)
    floor_sd = _noise_model(p, noise_rel, noise_abs)
    sd = floor_sd if sd is None else sd
    step_var = polish_step_var(p.ib, p.iw, noise_rel, noise_abs, grid.mc_stderr, _polish_tol_std(polish_tol), sd=sd)
    if guesser is None:
        alpha, g, residual, J = kernel.invert(inverter, p.ib, p.iw, p.sigma_t, p.rb, p.rw, iterations=polish,
                                              step_tol=polish_tol, step_var=step_var)
    else:
        alpha0, g0 = guesser.predict(p.ib, p.iw, p.sigma_t, p.rb, p.rw)
        broken = ~(np.isfinite(alpha0) & np.isfinite(g0))  # a guesser gone bad: the table guesses there
        fallback = int(np.count_nonzero(broken))
        if broken.any():
            table_a, table_g = inverter.initial_guess(p.ib, p.iw, inverter.table_grid.sigma_cell(p.sigma_t))
            alpha0, g0 = np.where(broken, table_a, alpha0), np.where(broken, table_g, g0)
        alpha, g, residual, J = kernel.solve_alpha_g(grid, p.ib, p.iw, grid.sigma_cell(p.sigma_t), p.rb, p.rw, alpha0,
                                                     g0, iterations=polish, step_tol=polish_tol, step_var=step_var)
    sigma_t, inscatter_ds, solved = p.sigma_t, None, (alpha, g, p.ib, p.iw)
    if grid.inscatter_grid is not None:  # the in-scattered light out of I_c (invert.c correct_inscatter)
        eligible = (p.flags & int(UNUSABLE | FitFlag.IC_BELOW_FLOOR | FitFlag.OUTSIDE_MAP)) == 0
        a, s, gg, ds = correct_inscatter(grid, alpha, sigma_t, g, J)
        alpha, sigma_t, g = np.where(eligible, a, alpha), np.where(eligible, s, sigma_t), np.where(eligible, gg, g)
        inscatter_ds = np.where(eligible, ds, 0.0)
    result = _finish(grid, p.flags, p.usable, p.ib, p.iw, p.ic, p.rb, p.rw, alpha, sigma_t, g, residual,
                     p.sigma_beer, method=method.name, kernel=kernel, sd=sd, sigma_t_solved=p.sigma_t,
                     inscatter_ds=inscatter_ds, inscatter_rel_std=inscatter_rel_std,
                     thickness_rel_std=thickness_rel_std, alpha_min_g=alpha_min_g, J=J, solved=solved,
                     floor_sd=floor_sd)
    result.guess_fallback_bins = 0 if guesser is None else fallback
    return _said(result)


def _said(result: FitResult) -> FitResult:
    """The fit, with a warning when its method's guess failed on some bins (they hold the lut fit's answer)."""
    if result.guess_fallback_bins:
        log.warning("%s: the method's first guess was not finite on %d of %d bins (a damaged model?); those bins "
                    "were solved from the table's guess, as the lut method would", result.method,
                    result.guess_fallback_bins, len(result))
    return result


def _noise_model(p: _Prepared, noise_rel: float, noise_abs: float) -> np.ndarray:
    """(N, 3) stds of the sanitized I_b, I_w, I_c under σ_I = noise_rel·I + noise_abs."""
    return np.column_stack([noise_rel * p.ib + noise_abs, noise_rel * p.iw + noise_abs, noise_rel * p.ic + noise_abs])


def native_options(amap: FitModel, grid: ForwardGrid, *, polish: int, polish_tol: float, noise_rel: float,
                   noise_abs: float, ic_floor: float, alpha_min_g: float, thickness_rel_std: float = 0.0,
                   inscatter_rel_std: float = INSCATTER_REL_STD) -> dict[str, Any]:
    """The C kernel's options for one thickness (NativeSolver.fit / prepare): fit()'s parameters plus
    what the numpy path below takes from the map and its grid."""
    return dict(noise_rel=noise_rel, noise_abs=noise_abs, mc_stderr=grid.mc_stderr, ic_floor=ic_floor,
                alpha_min_g=alpha_min_g, input_tolerance=_INPUT_TOLERANCE, ref_rho=amap.reference_rhos,
                t_max=grid.transmittance_limits[0], t_valid=grid.transmittance_limits[1], iterations=polish,
                step_tol=polish_tol, step_tol_std=_polish_tol_std(polish_tol),
                underdetermined_std=(UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD),
                std_check=(STD_CHECK_ALPHA, STD_CHECK_G, STD_CHECK_SIGMAS, STD_CHECK_TOL),
                thickness_rel_std=thickness_rel_std, inscatter_rel_std=inscatter_rel_std)


@dataclass
class _Prepared:
    """One thickness's bins before the (α, g) solve: flags, the sanitized stand-ins, σt from I_c."""
    flags: np.ndarray
    usable: np.ndarray
    ib: np.ndarray
    iw: np.ndarray
    ic: np.ndarray
    rb: np.ndarray
    rw: np.ndarray
    sigma_t: np.ndarray
    sigma_beer: np.ndarray


def _prepare(amap: FitModel, grid: ForwardGrid, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
             rho_w: np.ndarray, ic_floor: float) -> _Prepared:
    flags = _input_flags(I_b, I_w, I_c, rho_b, rho_w)
    usable = (flags & int(UNUSABLE)) == 0
    # Unusable bins are computed on harmless stand-ins and blanked at the end: no branch per bin.
    ib = _sanitize(I_b, 0.0, 1.0, 0.0)
    iw = _sanitize(I_w, 0.0, 1.0, 1.0)
    ic = _sanitize(I_c, 0.0, 1.0, 1.0)
    rb = np.where(usable, rho_b, amap.reference_rhos[0])
    rw = np.where(usable, rho_w, amap.reference_rhos[1])

    below = ic < ic_floor
    flags |= np.where(below & usable, int(FitFlag.IC_BELOW_FLOOR), 0)
    t_max = grid.transmittance_limits[0]
    # σt from I_c; under the floor, the floor's σt (a lower bound); above T(σt = 0), σt = 0. One set-up
    # throughout (the grid's, FitModel.setup): T(σt = 0) and its inverse must agree to the last digit.
    sigma_t = grid.setup.beer_lambert_sigma_t(np.minimum(np.maximum(ic, ic_floor), t_max))
    in_range = np.isfinite(I_c) & (I_c >= ic_floor) & (I_c <= t_max)
    sigma_beer = sigma_t if in_range.all() else np.where(in_range, sigma_t, grid.setup.beer_lambert_sigma_t(I_c))
    s_lo, s_hi = grid.sigma_t_range
    flags |= np.where(usable & ((sigma_t < s_lo * (1 - 1e-6)) | (sigma_t > s_hi * (1 + 1e-6))),
                      int(FitFlag.OUTSIDE_MAP), 0)
    return _Prepared(flags, usable, ib, iw, ic, rb, rw, sigma_t, sigma_beer)


def _underdetermined(std_a: np.ndarray, std_g: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):  # NaN std_g (g undefined) does not count
        return (std_a > UNDERDETERMINED_ALPHA_STD) | (std_g > UNDERDETERMINED_G_STD)


# bins whose stds already come with a caveat are not checked for STD_APPROXIMATE
_STD_CHECK_SKIP = int(UNUSABLE | FitFlag.UNDERDETERMINED | FitFlag.G_UNDEFINED | FitFlag.OUTSIDE_MAP
                      | FitFlag.NOT_CONVERGED)


def _std_approximate(grid: ForwardGrid, flags: np.ndarray, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray,
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


def _finish(grid: ForwardGrid, flags: np.ndarray, usable: np.ndarray, ib: np.ndarray, iw: np.ndarray,
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
    cond_a, cond_g = std_a, std_g
    if floor_sd is not None and np.any(floor_sd > sd):
        cond_var = np.maximum(var_in, floor_sd * floor_sd)
        cond_I = np.column_stack([np.sqrt(cond_var[:, 0] + model[0]), np.sqrt(cond_var[:, 1] + model[1]),
                                  np.maximum(sd[:, 2], floor_sd[:, 2])])
        cond_a, _, cond_g = kernel.propagate(J, cond_I, inscatter_var)
        cond_g = np.where(g_undef, np.nan, cond_g)
    flags |= np.where(usable & _underdetermined(cond_a, cond_g), int(FitFlag.UNDERDETERMINED), 0)
    flags |= np.where(_std_approximate(grid, flags, alpha_solved, sigma_t_solved, g_solved, ib_solved, iw_solved, rb,
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
    flags |= np.where(usable & _underdetermined(cond_a, cond_g), int(FitFlag.UNDERDETERMINED), 0)
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
    """Per bin, whether two thicknesses (axis -2) differ by more than _DISAGREE_SIGMAS combined stds
    in any column (axis 0); each pair once."""
    k = vals.shape[-2]
    bad = np.zeros(vals.shape[-1], dtype=bool)
    with np.errstate(invalid="ignore"):
        for i in range(k):
            for j in range(i + 1, k):
                diff = np.abs(vals[:, i] - vals[:, j])
                scale = np.sqrt(stds[:, i] ** 2 + stds[:, j] ** 2)
                bad |= (diff > _DISAGREE_SIGMAS * scale).any(axis=0)
    return bad
