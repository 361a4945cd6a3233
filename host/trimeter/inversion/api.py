"""`trimeter.fit`: one entry point for every inversion method and for one or two thicknesses.

Flow per map (thickness): validate the inputs into flags (never an exception for bad values) →
σt from I_c (exact Beer-Lambert incl. Fresnel; a lower bound under the noise floor) → (α, g) by the
method → flags for g undefined / outside the map / not converged → per-bin standard deviations by
first-order propagation through the forward map's Jacobian of every known error: the intensities'
noise (given per bin, else the noise model), the map's own error at the solution (its MC std-error
and interpolation error, kernel.node_model_variance), the in-scattering correction's and the
thickness's uncertainty. Several
thicknesses are then combined by inverse-variance weighting (the paper's method pools its samples
and takes the median, as written) and checked against each other.

For lut and mlp, one thickness's whole flow runs in one C call when the native kernel is built
(trimeter.inversion.native, `tm_fit`); `_prepare` + the solve + `_finish` below are its reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trimeter.errors import InputError
from trimeter.forward.collimated import beer_lambert_sigma_t
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.kernel import ForwardGrid, polish_step_var

METHODS = ("lut", "mlp", "paper")
_INPUT_TOLERANCE = 1e-3   # intensities this far below 0 / above 1 are still taken as noise around the limit
_DISAGREE_SIGMAS = 3.0
UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD = 0.1, 0.2  # FitFlag.UNDERDETERMINED above these stds
# The polish also stops a bin once a step moved α and g by less than this fraction of their noise
# std (the noise model's): further steps only wander along what the data cannot tell apart. Thick
# and dark bins used to take all 8 steps that way. Measured (device maps, rendered held-out, lut,
# steps per bin on l0.4 / l0.8, from 4.5 / 4.9 with none): 1e-3 → 3.6 / 3.6, 3e-3 → 3.2 / 3.3, both
# with α and g p95 unchanged to 1e-4 (noise-free and map-exact alike); 5e-3 → 3.0 / 3.1 and 1e-2 →
# 2.8 / 2.9 moved l0.8's α p95 by 0.0015-0.0026 (its underdetermined bins stop further from the
# exact solution of the map). A bin also stops when its step shrank at least 4× and the next one would be
# below that fraction (kernel.step_is_small): ~0.3 steps per bin fewer.
POLISH_TOL_STD = 3e-3
# The in-scattering correction's relative std: the map's table (30k photons per node) against the
# held-out sets' own traces (200k photons) differs by 1-2 % of the correction at p50 and up to 4.4 %
# at p95 over the measurable gamut; the tracer's approximations (trimeter.forward.inscatter) add to it.
INSCATTER_REL_STD = 0.05
# First order is checked (_std_approximate) only where a bin's α or g std is above these: a fifth of
# the UNDERDETERMINED thresholds. On the device maps' held-out sets at 0.2-1 % noise, the bins below
# them held 0-26 % of those the check flags, and flagging those too changed no coverage figure by
# more than 0.3 points; the check costs eight forward evaluations per bin checked.
STD_CHECK_ALPHA, STD_CHECK_G = 0.02, 0.04
# STD_APPROXIMATE where a re-fit from the intensities moved by ±STD_CHECK_SIGMAS σ lands off the
# Jacobian's prediction by more than STD_CHECK_TOL of that interval (STD_CHECK_SIGMAS · the std).
# Held-out device maps, 1 % noise: the bins it flags had g within ±2σ 78-82 % of the time, those it
# kept 92.6 / 91.6 % (all: 91.1 / 89.0 %). One Newton step from each linear prediction flags the same
# bins as solving the re-fits to convergence did (within 1-4 of 60-150 per set, same coverage).
STD_CHECK_SIGMAS, STD_CHECK_TOL = 2.0, 0.3


def _polish_tol_std(polish_tol: float) -> float:
    return POLISH_TOL_STD if polish_tol > 0 else 0.0  # polish_tol = 0: a fixed step count


@dataclass
class FitResult:
    """α, σt [1/mm], g with per-bin standard deviations and FitFlag words, over the input bins."""
    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray
    alpha_std: np.ndarray
    sigma_t_std: np.ndarray
    g_std: np.ndarray
    flags: np.ndarray
    sigma_t_beer: np.ndarray        # the consistency column: σt from I_c alone (paper Eq. 2)
    method: str
    per_thickness: list = field(default_factory=list)  # FitResult per map when several were given
    # α's and g's std with the intensities' stds at least the noise model's: what UNDERDETERMINED is
    # judged on (None: the stds above)
    conditioning_alpha_std: np.ndarray | None = None
    conditioning_g_std: np.ndarray | None = None

    COLUMNS = ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "flags", "sigma_t_beer")

    def __len__(self) -> int:
        return len(self.alpha)

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.COLUMNS}


# ------------------------------------------------------------------------------------ map handling
_TABLES: dict = {}


def _load_map(spec):
    from trimeter.maps.appearance import AppearanceMap, find_map

    if isinstance(spec, AppearanceMap):
        return spec
    return AppearanceMap.load(find_map(spec))


def _key(amap):
    inscatter = amap.inscatter
    return (amap.checksum or id(amap)), (inscatter.checksum if inscatter is not None else None)


def _forward_grid(amap) -> ForwardGrid:
    """One forward model per map for every method's polish and Jacobian: the map table's forward
    map between its nodes (ForwardGrid.between_nodes)."""
    return table_inverter(amap).grid


def table_inverter(amap):
    """The map's table inverter: maps/<name>.tlut if it exists and was built from this very map;
    else the table is built in memory from the map (≈0.2-2 s, cached). A stale .tlut (built from an
    earlier version of the map) is never used: it is rebuilt in memory with a warning, since the map
    is the source of truth and the file only a cache of it on the host."""
    import warnings

    from trimeter.inversion.lut import TableInverter
    from trimeter.inversion.table import MapTable, build_from_map, table_path_for

    key = _key(amap)
    if key not in _TABLES:
        path = table_path_for(amap.path) if amap.path else None
        table = None
        if path is not None and path.is_file():
            table = MapTable.load(path)  # a damaged file is a MapFileError, never ignored
            if amap.checksum and table.source_checksum != amap.checksum:
                warnings.warn(f"{path} was built from map {table.source_checksum[:12]}…, not from {amap.path.name} "
                              f"({amap.checksum[:12]}…): using a table rebuilt in memory; refresh the file with "
                              f"tools/build_table.py", stacklevel=3)
                table = None
        if table is None:
            table = build_from_map(amap)
        _TABLES[key] = TableInverter(table, inscatter=amap.inscatter, model_variance=map_model_variance(amap))
    return _TABLES[key]


def map_model_variance(amap):
    """The map's own error variance of (I_b, I_w) at its nodes, at its reference backgrounds:
    (variances (na, ns, ng, 2), α, ln σt, g axes) for ForwardGrid.attach_model_variance."""
    from trimeter.inversion.kernel import node_model_variance
    from trimeter.maps.appearance import background_response

    rb, rw = amap.reference_rhos
    values = np.stack([background_response(amap.A, amap.B, amap.C, rho) for rho in (rb, rw)], axis=-1)
    axes = (np.asarray(amap.alpha, float), np.log(np.asarray(amap.sigma_t, float)), np.asarray(amap.g, float))
    var = node_model_variance(values, np.stack([amap.std_b, amap.std_w], axis=-1), *axes)
    return var, axes


# ---------------------------------------------------------------------------------------- the fit
def fit(maps, I_b, I_w, I_c, rho_b=None, rho_w=None, method: str = "lut", *,
        noise_rel: float = 0.005, noise_abs: float = 2e-4, ic_floor: float = 1e-4,
        alpha_min_g: float = 0.02, polish: int = 8, polish_tol: float = 1e-6, samples: int = 250,
        epsilon: float = 0.01,
        seed: int = 0, mlp_model: str | Path | None = None, I_b_std=None, I_w_std=None, I_c_std=None,
        thickness_std_mm=0.0, inscatter_rel_std: float = INSCATTER_REL_STD) -> FitResult:
    """Invert measured intensities (arrays over wavelength bins) to α, σt [1/mm], g.

    maps: an AppearanceMap, a map path or shipped-map name, or a list of them (the same material at
    several thicknesses); with k maps, I_b, I_w, I_c (and ρ's, if per-thickness) have shape (k, N).
    rho_b, rho_w: per-bin background reflectances (default: each map's reference backgrounds).
    noise_rel, noise_abs: the intensity noise model σ_I = noise_rel·I + noise_abs (for the stds and
    the convergence tolerance) where the intensities' own stds are not given; ic_floor: I_c below it
    bounds σt from below only.
    I_b_std, I_w_std, I_c_std: the intensities' standard deviations (shaped like them, or scalars),
    e.g. from the capture's frame-to-frame scatter; where one is missing or NaN, the noise model's.
    thickness_std_mm: the sample thickness's std (one number, or one per map): it widens σt's std
    by σt·std/ℓ (α and g do not depend on it: the slab's intensities depend on σt·ℓ).
    inscatter_rel_std: the in-scattering correction's relative std.
    polish, polish_tol: at most `polish` Newton iterations after the lut/mlp guess (0 = the raw
    table/network); a bin stops once a step moved α and g by at most polish_tol, or by less than
    POLISH_TOL_STD of their noise std, or by a quarter of the step before with the next one,
    extrapolated, below that (polish_tol = 0: every bin takes `polish` steps).
    samples, epsilon, seed: the paper method's ε-median (samples=0: plain interpolation).
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    from trimeter.validation import require_number

    noise_rel = require_number("noise_rel", noise_rel, lo=0.0)
    noise_abs = require_number("noise_abs", noise_abs, lo=0.0)
    ic_floor = require_number("ic_floor", ic_floor, lo=0.0, lo_open=True, hi=1.0)
    alpha_min_g = require_number("alpha_min_g", alpha_min_g, lo=0.0, hi=1.0)
    epsilon = require_number("epsilon", epsilon, lo=0.0)
    polish, samples = int(require_number("polish", polish, lo=0)), int(require_number("samples", samples, lo=0))
    polish_tol = require_number("polish_tol", polish_tol, lo=0.0)
    inscatter_rel_std = require_number("inscatter_rel_std", inscatter_rel_std, lo=0.0)
    map_list = list(maps) if isinstance(maps, (list, tuple)) else [maps]
    if not map_list:
        raise InputError("maps must name at least one map")
    amaps = [_load_map(m) for m in map_list]
    k = len(amaps)
    arrays = _shape_inputs(k, I_b, I_w, I_c, rho_b, rho_w, amaps)
    stds = _shape_stds(k, arrays, (I_b_std, I_w_std, I_c_std), noise_rel, noise_abs)
    thickness_rel = [t / m.thickness_mm for t, m in zip(_thickness_stds(k, thickness_std_mm), amaps, strict=True)]
    opts = dict(noise_rel=noise_rel, noise_abs=noise_abs, ic_floor=ic_floor, alpha_min_g=alpha_min_g,
                inscatter_rel_std=inscatter_rel_std)
    if method == "paper":
        return _fit_paper(amaps, arrays, stds, thickness_rel, samples=samples, epsilon=epsilon, seed=seed, **opts)
    singles = [_fit_one(amap, *arrays[i], sd=stds[i], thickness_rel_std=thickness_rel[i], method=method, polish=polish,
                        polish_tol=polish_tol, mlp_model=mlp_model, **opts)
               for i, amap in enumerate(amaps)]
    return singles[0] if k == 1 else combine(singles, method)


def _shape_inputs(k, I_b, I_w, I_c, rho_b, rho_w, amaps):
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


def _shape_stds(k, arrays, given, noise_rel, noise_abs) -> list:
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


def _thickness_stds(k, thickness_std_mm) -> list[float]:
    from trimeter.validation import require_number

    values = list(thickness_std_mm) if isinstance(thickness_std_mm, (list, tuple, np.ndarray)) else \
        [thickness_std_mm] * k
    if len(values) != k:
        raise InputError(f"thickness_std_mm: give one value or one per map ({k}), got {len(values)}")
    return [require_number("thickness_std_mm", 0.0 if v is None else v, lo=0.0) for v in values]


def _input_flags(I_b, I_w, I_c, rho_b, rho_w):
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


def _sanitize(x, lo, hi, fill):
    return np.clip(np.where(np.isfinite(x), x, fill), lo, hi)


def _fit_one(amap, I_b, I_w, I_c, rho_b, rho_w, *, sd, thickness_rel_std, method, polish, polish_tol, mlp_model,
             noise_rel, noise_abs, ic_floor, alpha_min_g, inscatter_rel_std) -> FitResult:
    inverter = table_inverter(amap)
    grid = inverter.grid
    mlp = None
    if method == "mlp":
        from trimeter.inversion.mlp import mlp_inverter

        mlp = mlp_inverter(amap, mlp_model)
    solver = inverter.native_solver  # the whole fit in C (invert.c tm_fit); the numpy code below is its reference
    if solver is not None:
        options = native_options(amap, grid, polish=polish, polish_tol=polish_tol, noise_rel=noise_rel,
                                 noise_abs=noise_abs, ic_floor=ic_floor, alpha_min_g=alpha_min_g,
                                 thickness_rel_std=thickness_rel_std, inscatter_rel_std=inscatter_rel_std)
        if mlp is None:
            out = solver.fit(I_b, I_w, I_c, rho_b, rho_w, sd=sd, **options)
        else:  # the network guesses from the features C prepares; tm_fit_solve clamps its guess to the map's box
            out = solver.fit_guessed(I_b, I_w, I_c, rho_b, rho_w, mlp.run, mlp.log_sigma_range, sd=sd, **options)
            out.pop("features")
        out.pop("steps")
        if sd is None:  # the noise model's stds: the conditioning stds are the stds themselves
            out["conditioning_alpha_std"] = out["conditioning_g_std"] = None
        return FitResult(**out, method=method)
    p = _prepare(amap, grid, I_b, I_w, I_c, rho_b, rho_w, ic_floor)
    floor_sd = _noise_model(p, noise_rel, noise_abs)
    sd = floor_sd if sd is None else sd
    step_var = polish_step_var(p.ib, p.iw, noise_rel, noise_abs, grid.mc_stderr, _polish_tol_std(polish_tol), sd=sd)
    if mlp is None:
        alpha, g, residual, J = inverter.invert(p.ib, p.iw, p.sigma_t, p.rb, p.rw, polish_iterations=polish,
                                                step_tol=polish_tol, step_var=step_var)
    else:
        alpha0, g0 = mlp.predict(p.ib, p.iw, p.sigma_t, p.rb, p.rw)
        broken = ~(np.isfinite(alpha0) & np.isfinite(g0))  # a network gone bad: the table guesses there
        if broken.any():
            table_a, table_g = inverter.initial_guess(p.ib, p.iw, inverter.table_grid.sigma_cell(p.sigma_t))
            alpha0, g0 = np.where(broken, table_a, alpha0), np.where(broken, table_g, g0)
        alpha, g, residual, J = grid.solve_alpha_g(p.ib, p.iw, grid.sigma_cell(p.sigma_t), p.rb, p.rw, alpha0, g0,
                                                   iterations=max(polish, 0), step_tol=polish_tol, step_var=step_var)
    sigma_t, inscatter_ds, solved = p.sigma_t, None, (alpha, g, p.ib, p.iw)
    if grid.inscatter_grid is not None:  # the in-scattered light out of I_c (invert.c correct_inscatter)
        eligible = (p.flags & int(UNUSABLE | FitFlag.IC_BELOW_FLOOR | FitFlag.OUTSIDE_MAP)) == 0
        a, s, gg, ds = grid.correct_inscatter(alpha, sigma_t, g, J)
        alpha, sigma_t, g = np.where(eligible, a, alpha), np.where(eligible, s, sigma_t), np.where(eligible, gg, g)
        inscatter_ds = np.where(eligible, ds, 0.0)
    return _finish(amap, grid, p.flags, p.usable, p.ib, p.iw, p.ic, p.rb, p.rw, alpha, sigma_t, g, residual,
                   p.sigma_beer, method=method, sd=sd, sigma_t_solved=p.sigma_t, inscatter_ds=inscatter_ds,
                   inscatter_rel_std=inscatter_rel_std, thickness_rel_std=thickness_rel_std,
                   alpha_min_g=alpha_min_g, J=J, solved=solved, floor_sd=floor_sd)


def _noise_model(p, noise_rel, noise_abs):
    """(N, 3) stds of the sanitized I_b, I_w, I_c under σ_I = noise_rel·I + noise_abs."""
    return np.column_stack([noise_rel * p.ib + noise_abs, noise_rel * p.iw + noise_abs, noise_rel * p.ic + noise_abs])


def native_options(amap, grid, *, polish, polish_tol, noise_rel, noise_abs, ic_floor, alpha_min_g,
                   thickness_rel_std=0.0, inscatter_rel_std=INSCATTER_REL_STD) -> dict:
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


def _prepare(amap, grid, I_b, I_w, I_c, rho_b, rho_w, ic_floor) -> _Prepared:
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
    # σt from I_c; under the floor, the floor's σt (a lower bound); above T(σt = 0), σt = 0
    # The grid's sample set-up (the table's, stored as float32), not the map's: with the map's, T(σt = 0)
    # of the two differed in the last digits and I_c at T(σt = 0) came out as σt = NaN.
    sample = (grid.thickness_mm, grid.n, grid.cover_slide_n)
    sigma_t = beer_lambert_sigma_t(np.minimum(np.maximum(ic, ic_floor), t_max), *sample)
    in_range = np.isfinite(I_c) & (I_c >= ic_floor) & (I_c <= t_max)
    sigma_beer = sigma_t if in_range.all() else np.where(in_range, sigma_t, beer_lambert_sigma_t(I_c, *sample))
    s_lo, s_hi = grid.sigma_t_range
    flags |= np.where(usable & ((sigma_t < s_lo * (1 - 1e-6)) | (sigma_t > s_hi * (1 + 1e-6))),
                      int(FitFlag.OUTSIDE_MAP), 0)
    return _Prepared(flags, usable, ib, iw, ic, rb, rw, sigma_t, sigma_beer)


def _underdetermined(std_a, std_g):
    with np.errstate(invalid="ignore"):  # NaN std_g (g undefined) does not count
        return (std_a > UNDERDETERMINED_ALPHA_STD) | (std_g > UNDERDETERMINED_G_STD)


# bins whose stds already come with a caveat are not checked for STD_APPROXIMATE
_STD_CHECK_SKIP = int(UNUSABLE | FitFlag.UNDERDETERMINED | FitFlag.G_UNDEFINED | FitFlag.OUTSIDE_MAP
                      | FitFlag.NOT_CONVERGED)


def _std_approximate(grid, flags, alpha, sigma_t, g, ib, iw, rb, rw, J, sigma_I, std_a, std_g):
    """Where FitFlag.STD_APPROXIMATE belongs (invert.c tm_fit_solve does the same): bins whose α or g
    std is above STD_CHECK_ALPHA / STD_CHECK_G, none already flagged as unusable, underdetermined, g
    undefined, outside the map or not converged, on which the map bends within ±STD_CHECK_SIGMAS σ
    of the solve's (α, g) at σt (ForwardGrid.first_order_holds; J: its Jacobian there)."""
    with np.errstate(invalid="ignore"):
        large = (std_a > STD_CHECK_ALPHA) | (std_g > STD_CHECK_G)
    idx = np.flatnonzero(((flags & _STD_CHECK_SKIP) == 0) & large & np.isfinite(std_a) & np.isfinite(std_g))
    out = np.zeros(len(flags), dtype=bool)
    if len(idx):
        out[idx] = ~grid.first_order_holds(alpha[idx], grid.sigma_cell(sigma_t[idx]), g[idx], ib[idx], iw[idx],
                                           rb[idx], rw[idx], J[idx], sigma_I[idx, 0], sigma_I[idx, 1], std_a[idx],
                                           std_g[idx], STD_CHECK_SIGMAS, STD_CHECK_TOL)
    return out


def _finish(amap, grid, flags, usable, ib, iw, ic, rb, rw, alpha, sigma_t, g, residual, sigma_beer, *,
            method, sd, sigma_t_solved, inscatter_ds, inscatter_rel_std, thickness_rel_std, alpha_min_g,
            J=None, solved=None, floor_sd=None) -> FitResult:
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
    std_a, std_s, std_g = grid.propagate(J, sigma_I, inscatter_var)
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
        cond_a, _, cond_g = grid.propagate(J, cond_I, inscatter_var)
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
    estimates differ by more than 3 combined standard deviations (α, σt, or g)."""
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
        for r in results:
            heavy = ((std[0] / r.alpha_std) ** 2 >= 0.25) | ((std[2] / r.g_std) ** 2 >= 0.25)
            approx |= ((r.flags & int(FitFlag.STD_APPROXIMATE)) != 0) & heavy
    flags = (flags & ~int(FitFlag.STD_APPROXIMATE)) | np.where(approx, int(FitFlag.STD_APPROXIMATE), 0)
    disagree = _disagree(vals[:3], stds[:3]).any(axis=0)  # not the consistency column
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


def _weighted(vals, stds):
    """Inverse-variance mean over the thicknesses (axis -2) and its std. Where no thickness has a
    usable std: the plain mean of the finite values and the smallest of their stds; NaN where no
    value is finite (a bin unusable at every thickness). Written out, not with nanmean/nanmin: those
    warn on all-NaN columns and cost more than the arithmetic here."""
    finite = np.isfinite(vals)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(finite & np.isfinite(stds) & (stds > 0), 1.0 / (stds * stds), 0.0)
        wsum = w.sum(axis=-2)
        v0 = np.where(finite, vals, 0.0)
        weighted = (v0 * w).sum(axis=-2) / wsum
        count = finite.sum(axis=-2)
        plain = np.where(count > 0, v0.sum(axis=-2) / count, np.nan)
        smallest = np.fmin.reduce(np.where(finite, stds, np.inf), axis=-2)  # fmin: a NaN std does not win
        value = np.where(wsum > 0, weighted, plain)
        std = np.where(wsum > 0, 1.0 / np.sqrt(wsum), np.where(count > 0, smallest, np.nan))
    return value, std


def _disagree(vals, stds):
    """Where two thicknesses (axis -2) differ by more than _DISAGREE_SIGMAS combined stds."""
    with np.errstate(invalid="ignore"):
        diff = np.abs(vals[..., :, None, :] - vals[..., None, :, :])
        scale = np.sqrt(stds[..., :, None, :] ** 2 + stds[..., None, :, :] ** 2)
        bad = diff > _DISAGREE_SIGMAS * scale
    return bad.any(axis=(-3, -2))


# ---------------------------------------------------------------------------------- paper method
def _fit_paper(amaps, arrays, stds, thickness_rel, *, samples, epsilon, seed, noise_rel, noise_abs, ic_floor,
               alpha_min_g, inscatter_rel_std):
    from trimeter.inversion.paper import paper_medians

    inputs, singles = [], []
    for amap, (I_b, I_w, I_c, rho_b, rho_w) in zip(amaps, arrays, strict=True):
        flags = _input_flags(I_b, I_w, I_c, rho_b, rho_w)
        usable = (flags & int(UNUSABLE)) == 0
        inputs.append((np.where(usable, I_b, np.nan), I_w, I_c, rho_b, rho_w))
        singles.append((amap, flags, usable, I_b, I_w, I_c, rho_b, rho_w))
    pooled_median, own_medians = paper_medians(amaps, inputs, samples=samples, epsilon=epsilon, seed=seed)
    results = []
    # Each thickness on its own median (the consistency check), the estimate on the pooled one.
    for i, (med, (amap, flags, usable, I_b, I_w, I_c, rho_b, rho_w)) in enumerate(
            zip(own_medians, singles, strict=True)):
        grid = _forward_grid(amap)
        ib, iw, ic = _sanitize(I_b, 0, 1, 0), _sanitize(I_w, 0, 1, 1), _sanitize(I_c, 0, 1, 1)
        ref = amap.reference_rhos
        rb, rw = np.where(usable, rho_b, ref[0]), np.where(usable, rho_w, ref[1])
        flags = flags | np.where(usable & (ic < ic_floor), int(FitFlag.IC_BELOW_FLOOR), 0)
        outside = usable & ~np.all(np.isfinite(med), axis=1)
        flags |= np.where(outside, int(FitFlag.OUTSIDE_MAP) | int(FitFlag.NOT_CONVERGED), 0)
        alpha, sigma_t, g = med[:, 0], med[:, 1], med[:, 2]
        coef_in = np.isfinite(alpha)
        I_model = grid.intensities(np.nan_to_num(alpha), np.nan_to_num(sigma_t, nan=1.0), np.nan_to_num(g), rb, rw)
        residual = np.where(coef_in, np.hypot(I_model[0] - ib, I_model[1] - iw), np.inf)
        sigma_beer = beer_lambert_sigma_t(I_c, amap.thickness_mm, amap.n, amap.cover_slide_n)
        floor_sd = np.column_stack([noise_rel * ib + noise_abs, noise_rel * iw + noise_abs, noise_rel * ic + noise_abs])
        sd = stds[i] if stds[i] is not None else floor_sd
        # the ε-median has no separate in-scattering correction to propagate: its map's I_c holds it.
        # The interpolated median does not solve the map exactly: STD_APPROXIMATE's re-fits start from
        # the map's own intensities there, so that its residual does not count as the map's bend.
        r = _finish(amap, grid, flags, usable, ib, iw, ic, rb, rw, alpha, sigma_t, g, residual, sigma_beer,
                    method="paper", sd=sd, sigma_t_solved=sigma_t, inscatter_ds=None,
                    inscatter_rel_std=inscatter_rel_std, thickness_rel_std=thickness_rel[i], alpha_min_g=alpha_min_g,
                    solved=(alpha, g, I_model[0], I_model[1]), floor_sd=floor_sd)
        for name in ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std"):
            getattr(r, name)[outside] = np.nan
        results.append(r)
    if len(results) == 1:
        return results[0]
    combined = combine(results, "paper")
    # As written: the pooled median is the estimate; the stds come from the inverse-variance combination.
    med = pooled_median
    combined.alpha, combined.sigma_t, combined.g = med[:, 0], med[:, 1], med[:, 2]
    combined.g = np.where((combined.flags & int(FitFlag.G_UNDEFINED)) != 0, np.nan, combined.g)
    return combined
