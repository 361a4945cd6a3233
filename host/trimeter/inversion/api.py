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
session, its nodes for the paper method), loaded by trimeter.inversion.artifacts (`trimeter.fit` takes map
names and paths and loads them there), and the kernel (numpy or C, trimeter.inversion.kernel) it is
handed. Methods come from one table (trimeter.inversion.methods). For a guess-and-polish method, one
thickness's whole flow runs in one C call with the compiled kernel (`tm_fit`), and several thicknesses
from the map tables' guesses with their combination in one too (`tm_fit_thicknesses`); `_prepare` + the
solve + trimeter.inversion.finish.finish (and finish.combine) are their reference.
"""

from __future__ import annotations

import contextlib
import logging
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.inversion.finish import (DISAGREE_SIGMAS, INPUT_TOLERANCE, STD_CHECK_ALPHA, STD_CHECK_G,
                                       STD_CHECK_SIGMAS, STD_CHECK_TOL, UNDERDETERMINED_ALPHA_STD,
                                       UNDERDETERMINED_G_STD, combine, finish, input_flags, sanitize)
from trimeter.inversion.fit_model import FitModel
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.kernel import Kernel, default_kernel
from trimeter.inversion.newton import correct_inscatter, polish_step_var
from trimeter.inversion.strategy import Method
from trimeter.model.grid import ForwardGrid

log = logging.getLogger("trimeter.inversion")

# (I_b, I_w, I_c, ρ_b, ρ_w): one thickness's over its bins, or k thicknesses' as (k, bins) arrays
Inputs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]

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


def _polish_tol_std(polish_tol: float) -> float:
    return POLISH_TOL_STD if polish_tol > 0 else 0.0  # polish_tol = 0: a fixed step count


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

    models: a FitModel (trimeter.inversion.artifacts.load_artifacts), or a list of them (the same material at
    several thicknesses); with k maps, I_b, I_w, I_c (and ρ's, if per-thickness) have shape (k, N).
    method: a name in trimeter.inversion.methods; kernel: numpy or C (default: default_kernel()); the C
    kernel shares the bins out between threads from the table's guess (lut), as many as the process may use
    CPUs or TRIMETER_FIT_THREADS says (trimeter.inversion.kernel.NativeKernel(threads=1): all in the caller's;
    the same results).
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

    amaps = list(models) if isinstance(models, Sequence) else [models]
    kernel = default_kernel() if kernel is None else kernel
    s = _settings(amaps, get_method(method), polish, polish_tol, noise_rel, noise_abs, ic_floor, alpha_min_g, epsilon,
                  samples, inscatter_rel_std, thickness_std_mm, first_row)
    strategy, opts, k = s.strategy, s.options, len(amaps)
    if s.from_tables:  # the threads that may share the fit out wake while the inputs are checked
        kernel.expect_fit(k, _bins_at_a_glance(I_b))
    stacked = _shape_inputs(k, I_b, I_w, I_c, rho_b, rho_w, amaps)
    arrays: list[Inputs] = [(stacked[0][i], stacked[1][i], stacked[2][i], stacked[3][i], stacked[4][i])
                            for i in range(k)]
    stds = shape_stds(k, arrays, (I_b_std, I_w_std, I_c_std), opts["noise_rel"], opts["noise_abs"])
    if strategy.fit_all is not None:  # strategy.joint
        return strategy.fit_all(amaps, arrays, stds, s.thickness_rel, kernel=kernel, samples=s.samples,
                                epsilon=s.epsilon, seed=seed, first_row=s.first_row, **opts)
    if k > 1 and s.from_tables:  # every thickness and the combine in one call
        given = [sd for sd in stds if sd is not None]  # all or none
        together = kernel.fit_thicknesses([m.inverter for m in amaps], stacked,
                                          sd=np.stack(given) if given else None, options=s.native,
                                          method=strategy.name, disagree_sigmas=DISAGREE_SIGMAS,
                                          underdetermined_std=(UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD))
        if together is not None:
            return together
    # several thicknesses: each fitted into its place in the kernel's combine layout (no gathering after)
    blocks = kernel.output_blocks(k, arrays[0][0].shape[0]) if k > 1 else None
    singles = [_fit_one(amap, *arrays[i], sd=stds[i], thickness_rel_std=s.thickness_rel[i], method=strategy,
                        kernel=kernel, polish=s.polish, polish_tol=s.polish_tol, mlp_model=mlp_model,
                        options=s.native[i], block=None if blocks is None else blocks[i], **opts)
               for i, amap in enumerate(amaps)]
    if k == 1:
        return singles[0]
    # (a kernel whose fused path declined a thickness left that one's columns elsewhere: gathered then)
    fused = blocks is not None and all(r.alpha.base is blocks for r in singles)
    combined = kernel.combine(singles, method, underdetermined_std=(UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD),
                              disagree_sigmas=DISAGREE_SIGMAS, blocks=blocks if fused else None)
    combined = combine(singles, method) if combined is None else combined
    combined.guess_fallback_bins = sum(r.guess_fallback_bins for r in singles)
    return combined


@dataclass(frozen=True)
class _Settings:
    """fit()'s parameters checked, and what they make of its models: the same for every call with the same
    parameters and models, so kept (_settings). Read, never changed."""
    strategy: Method
    polish: int
    polish_tol: float
    samples: int
    epsilon: float
    first_row: int
    options: dict[str, Any]            # noise_rel, noise_abs, ic_floor, alpha_min_g, inscatter_rel_std
    thickness_rel: list[float]         # each model's thickness std over its thickness
    from_tables: bool                  # the method polishes the map tables' guesses (lut)
    native: list[dict[str, Any]]       # each model's native_options, for a method that polishes a guess


_SETTINGS: dict[tuple, tuple[list[weakref.ref], _Settings]] = {}


def _settings(amaps: list[FitModel], strategy: Method, *params: Any) -> _Settings:
    """The checked settings of a call with these models, this method and these parameters (the rest of
    fit()'s signature after method, in order): checked once and kept, since checking them and deriving the
    C kernel's options is a good part of a small fit's time. Kept by the method's identity (the settings
    hold it: a method registered later under the same name is another), the models' identities while they
    live (weak references: a model that is gone may have passed its id on) and the parameters' values; a
    call whose parameters are not all hashable (thickness stds in an array) is checked every time."""
    try:
        key = (id(strategy), tuple(map(id, amaps)), params)
        hit = _SETTINGS.get(key)
    except TypeError:
        return _check_settings(amaps, strategy, *params)
    if hit is not None and all(ref() is m for ref, m in zip(hit[0], amaps, strict=True)):
        return hit[1]
    settings = _check_settings(amaps, strategy, *params)
    if len(_SETTINGS) >= 64:  # a caller sweeping parameters: keep it bounded
        _SETTINGS.clear()
    with contextlib.suppress(TypeError):  # a model that takes no weak reference: checked every time
        _SETTINGS[key] = ([weakref.ref(m) for m in amaps], settings)
    return settings


def _check_settings(amaps: list[FitModel], strategy: Method, polish: int | None, polish_tol: float, noise_rel: float,
                    noise_abs: float, ic_floor: float, alpha_min_g: float, epsilon: float, samples: int,
                    inscatter_rel_std: float, thickness_std_mm: float | ArrayLike, first_row: int) -> _Settings:
    from trimeter.validation import require_number

    polish = strategy.default_polish if polish is None else polish
    options = dict(noise_rel=require_number("noise_rel", noise_rel, lo=0.0),
                   noise_abs=require_number("noise_abs", noise_abs, lo=0.0),
                   ic_floor=require_number("ic_floor", ic_floor, lo=0.0, lo_open=True, hi=1.0),
                   alpha_min_g=require_number("alpha_min_g", alpha_min_g, lo=0.0, hi=1.0),
                   inscatter_rel_std=require_number("inscatter_rel_std", inscatter_rel_std, lo=0.0))
    epsilon = require_number("epsilon", epsilon, lo=0.0)
    polish, samples = int(require_number("polish", polish, lo=0)), int(require_number("samples", samples, lo=0))
    polish_tol = require_number("polish_tol", polish_tol, lo=0.0)
    first_row = int(require_number("first_row", first_row, lo=0))
    if not amaps:
        raise InputError("maps must name at least one map")
    if not all(hasattr(m, "inverter") for m in amaps):  # a map, a path or a name: trimeter.fit loads those
        raise InputError("inversion.api.fit takes loaded maps (trimeter.inversion.artifacts.load_artifacts); "
                         "trimeter.fit takes maps, paths and names")
    k = len(amaps)
    thickness_rel = [t / m.setup.thickness_mm for t, m in zip(_thickness_stds(k, thickness_std_mm), amaps, strict=True)]
    native = [] if strategy.joint else [native_options(m, m.inverter.grid, polish=polish, polish_tol=polish_tol,
                                                        thickness_rel_std=thickness_rel[i], **options)
                                         for i, m in enumerate(amaps)]
    return _Settings(strategy, polish, polish_tol, samples, epsilon, first_row, options, thickness_rel,
                     strategy.guesser is None and not strategy.joint, native)


def _bins_at_a_glance(x: ArrayLike) -> int:
    """The bins of an array's last axis, without converting anything (0 for what is not yet an array)."""
    shape = getattr(x, "shape", None)
    return int(shape[-1]) if shape else 0


def _shape_inputs(k: int, I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike, rho_b: ArrayLike | None,
                  rho_w: ArrayLike | None, amaps: Sequence[FitModel]) -> Inputs:
    """I_b, I_w, I_c, ρ_b, ρ_w, each (k, bins): row i is thickness i's."""
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
    return I_b, I_w, I_c, rhos[0], rhos[1]


def shape_stds(k: int, arrays: list[Inputs], given: tuple[ArrayLike | None, ...], noise_rel: float,
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
            model = noise_rel * sanitize(x, 0.0, 1.0, fill) + noise_abs
            out[i, :, j] = np.where(np.isnan(out[i, :, j]), model, out[i, :, j])
    return list(out)


def _thickness_stds(k: int, thickness_std_mm: float | ArrayLike) -> list[float]:
    from trimeter.validation import require_number

    values = list(thickness_std_mm) if isinstance(thickness_std_mm, (list, tuple, np.ndarray)) else \
        [thickness_std_mm] * k
    if len(values) != k:
        raise InputError(f"thickness_std_mm: give one value or one per map ({k}), got {len(values)}")
    return [require_number("thickness_std_mm", 0.0 if v is None else v, lo=0.0) for v in values]


def _fit_one(model: FitModel, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
             rho_w: np.ndarray, *, sd: np.ndarray | None, thickness_rel_std: float, method: Method, kernel: Kernel,
             polish: int, polish_tol: float, mlp_model: str | Path | None, noise_rel: float, noise_abs: float,
             ic_floor: float, alpha_min_g: float, inscatter_rel_std: float, options: dict[str, Any],
             block: np.ndarray | None = None) -> FitResult:
    """One thickness's fit; options: native_options of these parameters, for the kernel's fused path."""
    inverter = model.inverter
    grid = inverter.grid
    guesser = None if method.guesser is None else method.guesser(model, {"mlp_model": mlp_model})
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
    result = finish(grid, p.flags, p.usable, p.ib, p.iw, p.ic, p.rb, p.rw, alpha, sigma_t, g, residual,
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
                alpha_min_g=alpha_min_g, input_tolerance=INPUT_TOLERANCE, ref_rho=amap.reference_rhos,
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
    flags = input_flags(I_b, I_w, I_c, rho_b, rho_w)
    usable = (flags & int(UNUSABLE)) == 0
    # Unusable bins are computed on harmless stand-ins and blanked at the end: no branch per bin.
    ib = sanitize(I_b, 0.0, 1.0, 0.0)
    iw = sanitize(I_w, 0.0, 1.0, 1.0)
    ic = sanitize(I_c, 0.0, 1.0, 1.0)
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
