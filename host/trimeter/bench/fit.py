"""`trimeter bench fit`: inversion run time against error, every figure also as a ratio to `paper`
(plain interpolation) measured in the same run.

Held-out materials come from maps/heldout/<map-name>.held (made by tools/make_heldout.py: random
off-grid (α, σt, g) rendered directly, never map grid points). Per noise level (relative Gaussian
noise on I_b, I_w, I_c) and method variant it reports: time per 1024 bins of the whole `fit()` call
(best of several runs; validation, flags and per-bin uncertainty included), warm (right after an
untimed call) and cold (after evicting the caches: `ms_per_1024_cold`), and of the inversion
kernel alone ("core": the paper's scipy interpolator call against the lut/mlp guess + polish), α abs
error p50/p95, σt relative error p50/p95, g abs error p50/p95 over
α ≥ 0.5, NaN rate and flag rate, and what each variant costs in memory: the bytes of the files it
reads (`files_kB`: .tmap for paper; .tlut, .tins and the .onnx for lut/mlp), of the model it works on
in memory (`model_kB`: the refined forward grid and table cells, the network; the paper's map nodes)
and the peak of the Python heap (numpy included; tracemalloc) during one fit() of 1024 bins
(`peak_kB`). Errors are taken over the measurable gamut (I_c ≥ 1e-3, so σt is
not just a lower bound); NaN and flag rates over every held-out material. A Pareto plot (time
against α and g p95, noise-free) is written as a PNG whose path is printed.

All of that is at the map's reference backgrounds, the paper method's most favourable case: it
triangulates once per (ρ_b, ρ_w). `--per-wavelength-backgrounds` adds the case a calibration
actually produces, ρ_b(λ) and ρ_w(λ) varying over the bins, timing each method's first fit after it.

The rendered held-out set is the headline, but on this instrument its figures mix three errors. An
error budget per map (noise-free, measurable gamut) separates them, all to first order through the
map's Jacobian (trimeter.model.grid.ForwardGrid):
- reference noise floor: the α / g standard deviation implied by the held-out renders' own MC
  std-error (std_b, std_w per material) — how precisely the references can check any method;
- map error floor: the α / g error implied by model-forward − held-out intensities, where the model
  is the forward map lut and mlp polish on (the table's, refined in σt with cubic splines): the map's
  MC noise plus its interpolation — what even an exact inversion of that model gets wrong;
- map-exact rows: every variant on the same off-grid materials with I_b, I_w, I_c from that same
  forward model, which isolates the inversion method's error (what the lut/mlp targets measure about
  the method);
- well-conditioned columns: α / g p95 over the materials whose reference noise floor is below half
  the target (α std < 0.005, g std < 0.0075), where the rendered references can resolve the targets.
"""

from __future__ import annotations

import functools
import inspect
import json
import time
import tracemalloc
from collections.abc import Callable, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from trimeter.atomic import atomic_output, atomic_write
from trimeter.errors import InputError
from trimeter.model.collimated import MEASURABLE_IC
from trimeter.inversion.flags import FitFlag
from trimeter.paths import MAPS_DIR

if TYPE_CHECKING:
    import argparse

    from trimeter.domain.parameters import FitResult
    from trimeter.maps.appearance import AppearanceMap
    from trimeter.inversion.api import FitModel
    from trimeter.maps.artifacts import ArtifactCache

    # (label, method name, fit options, the map's loaded artifacts)
    Variant = tuple[str, str, dict[str, Any], FitModel]
    Heldout = dict[str, np.ndarray]  # a held-out set's arrays by name
    Row = dict[str, Any]  # one printed and reported row of figures


class PolishOptions(TypedDict):
    polish: int
    polish_tol: float


HELDOUT_DIR = MAPS_DIR / "heldout"
# used when no shipped map has a held-out set: the shipped ideal map, never a test fixture
IDEAL_FALLBACK = MAPS_DIR / "ideal-n1.5-l0.5.tmap"
# The inversion's noise-free p95 targets for lut/mlp; a reference resolves them where its own first-order
# std is below half of them (the well-conditioned subset).
ALPHA_TARGET, G_TARGET = 0.01, 0.015
# and its speed and σt targets: ≥ 50× paper's plain interpolation, ms per 1024 bins, σt relative p95
SPEEDUP_TARGET, MS_TARGET, SIGMA_REL_TARGET = 50.0, {"lut": 1.0, "mlp": 2.0}, 0.01
G_MIN_ALPHA = 0.5  # g is scored over α ≥ 0.5 only (below, g barely changes the intensities)
DEFAULT_POLISH = PolishOptions(polish=8, polish_tol=1e-6)  # trimeter.fit's defaults
SMALL_INVERSE = 8  # the lut-small variant's inverse grid side: a half-slot device table


def register(bench_subparsers: argparse._SubParsersAction) -> None:
    p = bench_subparsers.add_parser("fit", help="inversion: time per 1024 bins against error, ratios to paper",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--map", dest="maps", action="append",
                   help="map(s) to benchmark (default: every shipped map with a held-out set; else the ideal map)")
    p.add_argument("--noise", default="0,0.002,0.005,0.01", help="relative noise levels, comma-separated")
    p.add_argument("--median-bins", type=int, default=128,
                   help="bins timed for the paper ε-median (scaled to 1024; it costs ~250 interpolations per bin)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--per-wavelength-backgrounds", action="store_true",
                   help="also time the first fit after a calibration with ρ_b(λ), ρ_w(λ) varying over the bins "
                        "(the paper method then triangulates once per distinct pair: minutes per map)")
    p.add_argument("--out", type=Path, default=Path("out/bench-fit"))
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def _maps(specs: Sequence[str] | None) -> list[AppearanceMap]:
    from trimeter.maps.appearance import AppearanceMap, find_map, shipped_maps

    if specs:
        return [AppearanceMap.load(find_map(s)) for s in specs]
    found = [AppearanceMap.load(p) for p in shipped_maps() if (HELDOUT_DIR / f"{p.stem}.held").is_file()]
    return found or [AppearanceMap.load(IDEAL_FALLBACK)]


def heldout_for(amap: AppearanceMap) -> tuple[Path, dict[str, Any], Heldout]:
    from trimeter.errors import MapFileError
    from trimeter.maps.container import read_container

    # a set next to the map first: a map built elsewhere is scored on its own set, not on the shipped one
    candidates = [amap.path.with_suffix(".held")] if amap.path is not None else []
    candidates.append(HELDOUT_DIR / f"{amap.name}.held")
    for path in candidates:
        if path.is_file():
            meta, arrays, _ = read_container(path, "heldout-set")
            return path, meta, {k: np.asarray(v, dtype=float) for k, v in arrays.items()}
    raise MapFileError(f"no held-out set for map {amap.name} (looked for {', '.join(map(str, candidates))}); "
                       f"make one with tools/make_heldout.py")


def _variants(amap: AppearanceMap, cache: ArtifactCache, small_cache: ArtifactCache) -> list[Variant]:
    """(label, method, fit options, artifacts) per variant, from the method table: each method's
    bench variants, one set per artifact file a method needs (e.g. every <map>*.onnx for mlp), and the
    lut on the small table (the same fit with another table injected)."""
    from trimeter.errors import MapFileError
    from trimeter.inversion.methods import METHODS

    artifacts, small = cache.get(amap), small_cache.get(amap)
    variants: list[Variant] = []
    for method in sorted(METHODS.values(), key=lambda m: not m.joint):  # the paper baseline first
        sets: list[tuple[str, dict[str, Any]]] = [(method.name, {})]
        if method.needs:
            sets = []
            for suffix in method.needs:
                stem = amap.path.stem if amap.path is not None else ""
                files = sorted(amap.path.parent.glob(f"{stem}*{suffix}")) if amap.path is not None else []
                for model in files:
                    tag = model.stem[len(stem):].lstrip("-.")
                    try:
                        artifacts.mlp(model)
                    except MapFileError as exc:  # e.g. the map was rebuilt since: report it, bench the rest
                        print(f"   skipping {model.name}: {exc}")
                        continue
                    sets.append((f"{method.name}-{tag}" if tag else method.name, {"mlp_model": model}))
        for label, extra in sets:
            for suffix, options in method.bench_variants:
                name = f"{label}{suffix}" if suffix.startswith("-") or not suffix else f"{label} {suffix}"
                polish: dict[str, Any] = {} if method.joint else dict(DEFAULT_POLISH)
                variants.append((name, method.name, {**polish, **options, **extra}, artifacts))
        if method.name == "lut":
            variants += [("lut-small p0", "lut", dict(polish=0, polish_tol=0.0), small),
                         ("lut-small p≤8", "lut", dict(DEFAULT_POLISH), small)]
    return variants


def _array_bytes(*objects: object) -> int:
    """Bytes of the numpy arrays held by objects (their attributes one level down, tuples and lists too)."""
    seen: set[int] = set()
    total = 0
    for obj in objects:
        for value in vars(obj).values():
            for v in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(v, np.ndarray) and id(v) not in seen:
                    seen.add(id(v))
                    total += v.nbytes
    return total


def _variant_bytes(variant: Variant) -> tuple[int, int]:
    """(bytes of the files the variant reads, bytes of the model it solves on in memory)."""
    from trimeter.inversion.methods import get_method

    _, method, kw, artifacts = variant
    amap = artifacts.map
    path = amap.path
    if get_method(method).joint:  # the paper method interpolates the map's nodes
        paths = [path] if path is not None else []
        return sum(p.stat().st_size for p in paths), _array_bytes(amap)
    inverter = artifacts.inverter
    files = sum(path.with_suffix(suffix).stat().st_size for suffix in (".tins",)
                if path is not None and path.with_suffix(suffix).is_file())
    files += inverter.table.size_bytes
    model = _array_bytes(inverter, inverter.grid, inverter.table_grid)
    if "mlp_model" in kw:
        files += Path(kw["mlp_model"]).stat().st_size
        model += Path(kw["mlp_model"]).stat().st_size  # onnxruntime holds the weights, about the file's size
    return files, model


def _peak_bytes(fn: Callable[[], object]) -> int:
    """Peak of the Python heap (numpy arrays included) during fn(), above what was allocated before."""
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _fit_variant(variant: Variant, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray | None = None,
                 rho_w: np.ndarray | None = None) -> FitResult:
    from trimeter.inversion.api import fit

    _, method, kw, artifacts = variant
    return fit(artifacts, I_b, I_w, I_c, rho_b, rho_w, method=method, **kw)


def _core(variant: Variant, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rb: float,
          rw: float) -> Callable[[], object] | None:
    """The inversion kernel alone, without input validation, flags and uncertainty: paper = the
    scipy interpolator call; a guess-and-polish method = σt from I_c + its guess (the table's, or its
    guesser's: the network for mlp) + polish. None for another whole-fit method (not timed)."""
    import trimeter.inversion.api as api
    from trimeter.inversion.kernel import default_kernel
    from trimeter.inversion.methods import get_method
    from trimeter.inversion.newton import polish_step_var
    from trimeter.inversion.paper import coordinates, interpolator

    _, method, kw, artifacts = variant
    strategy = get_method(method)
    if method == "paper":
        interp = interpolator(artifacts.map, round(rb, 3), round(rw, 3), artifacts.paper_cache)
        return lambda: interp(coordinates(I_b, I_w, I_c))
    if strategy.joint:
        return None
    kernel = default_kernel()
    n = len(I_b)
    rho_b, rho_w = np.full(n, rb), np.full(n, rw)
    inv, grid = artifacts.inverter, artifacts.grid
    polish, tol = kw["polish"], kw["polish_tol"]
    sigma = lambda: artifacts.setup.beer_lambert_sigma_t(I_c)  # noqa: E731
    # the polish stops bins as fit() does: step_tol, or a step below POLISH_TOL_STD of the noise std
    # under fit()'s default noise model
    fit_defaults = {k: p.default for k, p in inspect.signature(api.fit).parameters.items()}
    step_var = lambda: polish_step_var(I_b, I_w, fit_defaults["noise_rel"], fit_defaults["noise_abs"],  # noqa: E731
                                       grid.mc_stderr, api._polish_tol_std(tol))
    if strategy.guesser is None:
        return lambda: kernel.invert(inv, I_b, I_w, sigma(), rho_b, rho_w, iterations=polish, step_tol=tol,
                                     step_var=step_var())
    net = strategy.guesser(artifacts, kw)

    def run() -> tuple[np.ndarray, ...]:
        s = sigma()
        a0, g0 = net.predict(I_b, I_w, s, rho_b, rho_w)
        return kernel.solve_alpha_g(grid, I_b, I_w, grid.sigma_cell(s), rho_b, rho_w, a0, g0, iterations=polish,
                                    step_tol=tol, step_var=step_var())
    return run


# The held-out materials are split once, here: every CALIBRATION_EVERY-th (σt, g) column (materials that
# share σt and g were traced together, so their errors are correlated: a column stays whole) in the order
# the set lists them is the calibration part, on which map-error constants are chosen
# (trimeter.model.grid.LEAVE_ONE_OUT_SCALE); the rest, the scored part, is what coverage is reported on.
CALIBRATION_EVERY = 4
HELDOUT_PARTS = ("scored", "calibration")


def heldout_part(h: Heldout, part: str) -> Heldout:
    """The `part` ("scored" or "calibration") of a held-out set: its arrays restricted to those materials."""
    if part not in HELDOUT_PARTS:
        raise InputError(f"held-out part must be one of {', '.join(HELDOUT_PARTS)}, got {part!r}")
    pairs = np.column_stack([h["sigma_t"], h["g"]])
    _, first, column = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))  # each column's rank by where it first appears
    calibration = order[column.ravel()] % CALIBRATION_EVERY == 0
    keep = calibration if part == "calibration" else ~calibration
    return {k: v[keep] for k, v in h.items()}


def heldout_intensities(h: Heldout, rho_b: float | np.ndarray,
                        rho_w: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I_b, I_w) of the held-out materials at the backgrounds, from their rendered A, B, C."""
    from trimeter.model.response import background_response

    return background_response(h["A"], h["B"], h["C"], rho_b), background_response(h["A"], h["B"], h["C"], rho_w)


def heldout_collimated(amap: AppearanceMap, h: Heldout, index: slice | np.ndarray = slice(None)) -> np.ndarray:
    """I_c of the held-out materials: the unscattered beam, and the light scattered into the detector's
    aperture where the set has it traced (tools/make_heldout.py --inscatter)."""
    unscattered = amap.collimated(h["sigma_t"][index])
    return unscattered * np.exp(h["inscatter_log1p"][index]) if "inscatter_log1p" in h else unscattered


def _solve_alpha_g(J: np.ndarray, d_b: np.ndarray, d_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First-order (δα, δg) from intensity offsets (δI_b, δI_w) at known σt: J2⁻¹ δI with J2 =
    ∂(I_b, I_w)/∂(α, g) (Cramer's rule, vectorized); ±inf where J2 is singular."""
    a, b, c, d = J[:, 0, 0], J[:, 0, 2], J[:, 1, 0], J[:, 1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        det = a * d - b * c
        da, dg = (d * d_b - b * d_w) / det, (a * d_w - c * d_b) / det
    return np.nan_to_num(da, nan=np.inf), np.nan_to_num(dg, nan=np.inf)


def error_budget(amap: AppearanceMap, h: Heldout, rho_b: float, rho_w: float,
                 artifacts: FitModel | None = None) -> dict[str, Any]:
    """Per held-out material, what limits the rendered-reference figures (see the module docstring):
    reference noise floor (first-order α / g std from the renders' MC std-error), map error floor
    (first-order signed α / g error of an exact map inversion: map forward − rendered intensities),
    the map-exact intensities (I_b, I_w, I_c from the map's own forward model) and the masks
    (measurable gamut, g scored, well-conditioned for α and for g). artifacts: the map's, loaded
    (default: through the process's cache)."""
    from trimeter.inversion.kernel import default_kernel
    from trimeter.maps.artifacts import load_artifacts
    from trimeter.model.grid import ForwardGrid

    a, s, g = h["alpha"], h["sigma_t"], h["g"]
    n = len(a)
    rb, rw = np.full(n, rho_b), np.full(n, rho_w)
    kernel = default_kernel()
    grid = (artifacts or load_artifacts(amap)).grid  # the forward model lut and mlp polish on
    I_b, I_w = heldout_intensities(h, rho_b, rho_w)
    map_b, map_w, map_c = grid.intensities(a, s, g, rb, rw)
    J = grid.jacobian(a, s, g, rb, rw)
    # I_c is analytic in both (no MC noise, no interpolation): its std is 0 here.
    alpha_std, _, g_std = kernel.propagate(J, np.column_stack([h["std_b"], h["std_w"], np.zeros(n)]))
    alpha_err, g_err = _solve_alpha_g(J, I_b - map_b, I_w - map_w)
    # The map's own MC part of that error: its nodes' std-errors interpolated like A, B, C (an upper
    # bound: exact when a cell's node errors are fully correlated, as along α within one traced column).
    node_std = ForwardGrid(amap.alpha, np.log(amap.sigma_t), amap.g,
                           np.stack([amap.std_b, amap.std_w, np.zeros_like(amap.std_b)], axis=-1),
                           setup=amap.setup)
    map_std = node_std.coefficients(a, node_std.sigma_cell(s), g)[0]
    alpha_map_std, _, g_map_std = kernel.propagate(J, np.column_stack([map_std[0], map_std[1], np.zeros(n)]))
    measurable = amap.collimated(s) >= MEASURABLE_IC
    g_scored = measurable & (a >= G_MIN_ALPHA)
    return {"alpha_floor_std": alpha_std, "g_floor_std": g_std, "alpha_map_err": alpha_err, "g_map_err": g_err,
            "alpha_map_std": alpha_map_std, "g_map_std": g_map_std,
            "map_exact": (map_b, map_w, map_c), "measurable": measurable, "g_scored": g_scored,
            "well_alpha": measurable & (alpha_std < ALPHA_TARGET / 2),
            "well_g": g_scored & (g_std < G_TARGET / 2)}


def _pct(x: np.ndarray, q: float) -> float:
    x = np.asarray(x, dtype=float)
    x = x[~np.isnan(x)]
    return float(np.percentile(x, q)) if len(x) else float("nan")


def _budget_summary(b: dict[str, Any]) -> dict[str, dict[str, float]]:
    def p50_p95(key: str, mask: np.ndarray) -> dict[str, float]:
        x = np.abs(b[key][mask])
        return {f"{key.split('_')[0]}_p50": _pct(x, 50), f"{key.split('_')[0]}_p95": _pct(x, 95)}

    return {
        "reference_noise_floor": {**p50_p95("alpha_floor_std", b["measurable"]),
                                  **p50_p95("g_floor_std", b["g_scored"])},
        "map_error_floor": {**p50_p95("alpha_map_err", b["measurable"]), **p50_p95("g_map_err", b["g_scored"])},
        "map_noise_floor": {**p50_p95("alpha_map_std", b["measurable"]), **p50_p95("g_map_std", b["g_scored"])},
        # what is left of the rendered well-conditioned figures once the references are precise
        "map_error_floor_well_conditioned": {**p50_p95("alpha_map_err", b["well_alpha"]),
                                             **p50_p95("g_map_err", b["well_g"])},
        "well_conditioned": {"alpha_count": int(b["well_alpha"].sum()), "alpha_of": int(b["measurable"].sum()),
                             "alpha_floor_std_below": ALPHA_TARGET / 2, "g_count": int(b["well_g"].sum()),
                             "g_of": int(b["g_scored"].sum()), "g_floor_std_below": G_TARGET / 2},
    }


def _stats(res: FitResult | SimpleNamespace, truth: tuple[np.ndarray, ...], budget: dict[str, Any]) -> Row:
    """Error figures of a fit's columns (a FitResult, or any result with its alpha, sigma_t, g, flags and
    alpha_std) against the true (α, σt, g)."""
    a, s, g = truth
    measurable = budget["measurable"]
    ea = np.abs(res.alpha - a)
    es = np.abs(res.sigma_t / s - 1)[measurable]
    eg = np.abs(res.g - g)
    nan_meas = float(np.mean(~np.isfinite(res.alpha[measurable]) | ~np.isfinite(res.sigma_t[measurable])))
    # the bins the fit itself calls determined (no FitFlag.UNDERDETERMINED)
    determined = (res.flags & int(FitFlag.UNDERDETERMINED)) == 0
    # the bins over the α target (NaN included): does the fit itself say it does not know α there?
    miss = measurable & ~(ea <= ALPHA_TARGET)
    miss_std = res.alpha_std[miss & np.isfinite(res.alpha_std)]
    return {"alpha_p50": _pct(ea[measurable], 50), "alpha_p95": _pct(ea[measurable], 95), "sigma_rel_p50": _pct(es, 50),
            "sigma_rel_p95": _pct(es, 95), "g_p50": _pct(eg[budget["g_scored"]], 50),
            "g_p95": _pct(eg[budget["g_scored"]], 95),
            "nan_rate": float(np.mean(~np.isfinite(res.alpha))), "nan_rate_measurable": nan_meas,
            "flag_rate": float(np.mean(res.flags != 0)),
            "alpha_p95_well": _pct(ea[budget["well_alpha"]], 95), "g_p95_well": _pct(eg[budget["well_g"]], 95),
            "alpha_p95_determined": _pct(ea[measurable & determined], 95),
            "g_p95_determined": _pct(eg[budget["g_scored"] & determined], 95),
            "determined_rate": float(np.mean(determined[measurable])),
            "alpha_misses": int(miss.sum()), "alpha_misses_flagged": int((miss & ~determined).sum()),
            "alpha_misses_min_std": float(miss_std.min()) if len(miss_std) else float("nan"),
            "measurable": int(measurable.sum())}


def _bench_case(variants: list[Variant], truth: tuple[np.ndarray, ...], budget: dict[str, Any],
                intensities: tuple[np.ndarray, ...], label: str, level: float, args: argparse.Namespace) -> list[Row]:
    """Score and time every variant on one set of intensities; returns one row per variant."""
    I_b, I_w, I_c = intensities
    rows: list[Row] = []
    timers: list[tuple[Row, str, Callable[[], object], float]] = []  # (row, key, fn, scale): timed round-robin
    tile = np.resize(np.arange(len(I_b)), 1024)
    rb, rw = budget["rho"]
    for variant in variants:
        name = variant[0]
        res = _fit_variant(variant, I_b, I_w, I_c)
        files, model = _variant_bytes(variant)
        st = {"noise": level, "reference": label, "variant": name, **_stats(res, truth, budget),
              "ms_per_1024": np.inf, "ms_per_1024_cold": np.inf, "core_ms_per_1024": np.inf,
              "files_kB": files / 1e3, "model_kB": model / 1e3}
        rows.append(st)
        nb = args.median_bins if name == "paper-median" else 1024
        idx = tile[:nb]
        sub = (I_b[idx], I_w[idx], I_c[idx])
        _fit_variant(variant, *sub)  # warm: the peak is the call's own, not the first load's
        whole_fit = functools.partial(_fit_variant, variant, *sub)
        st["peak_kB"] = _peak_bytes(whole_fit) * 1024 / nb / 1e3
        timers.append((st, "ms_per_1024", whole_fit, 1024 / nb))
        core = None if name == "paper-median" else _core(variant, *sub, rb, rw)
        if core is None:
            st["core_ms_per_1024"] = float("nan")
        else:
            timers.append((st, "core_ms_per_1024", core, 1.0))
    # Round-robin: every variant is timed once per round, so all see the same machine load
    # (the machine is shared); each keeps its best round. The ε-median is timed once, warm.
    # Two cache states, so that no variant's figure depends on which one ran just before it:
    # warm (the call right after an untimed one: a batch of spectra) and, for the whole fit, cold
    # (after evicting the caches: one press-button measurement).
    for fn in (t[2] for t in timers):
        fn()  # warm caches (interpolators, tables, ONNX sessions)
    for round_no in range(args.repeats):
        for st, key, fn, scale in timers:
            if st["variant"] == "paper-median":
                if round_no == 0:
                    st[key], st["ms_per_1024_cold"] = _timed(fn) * scale, float("nan")
                continue
            fn()
            st[key] = min(st[key], _timed(fn) * scale)
            if key == "ms_per_1024":
                _evict_caches()
                st["ms_per_1024_cold"] = min(st["ms_per_1024_cold"], _timed(fn) * scale)
    return rows


def hull_split(artifacts: FitModel, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rb: float, rw: float,
               repeats: int) -> dict[str, float]:
    """The paper method's time depends on where its inputs fall: scipy's Delaunay search rejects a
    point outside the hull's bounding box at once, but one inside the box and outside the hull costs
    a brute-force pass over every simplex (~0.3 ms). So: paper core and whole fit() against lut's
    default fit() on the inputs inside the hull alone (tiled to 1024), next to the whole set."""
    from trimeter.inversion.api import fit
    from trimeter.inversion.paper import coordinates, interpolator

    interp = interpolator(artifacts.map, round(rb, 3), round(rw, 3), artifacts.paper_cache)
    pts = coordinates(I_b, I_w, I_c)
    inside = interp.tri.find_simplex(pts) >= 0  # type: ignore[attr-defined]  # scipy sets .tri; its stubs omit it
    out: dict[str, float] = {"outside_hull": int((~inside).sum()), "of": len(inside)}
    if not inside.any():
        return out
    idx = np.resize(np.flatnonzero(inside), 1024)
    calls: dict[str, Callable[[], object]] = {"paper_core_ms": lambda: interp(pts[idx]),
             "paper_ms": lambda: fit(artifacts, I_b[idx], I_w[idx], I_c[idx], method="paper", samples=0),
             "lut_ms": lambda: fit(artifacts, I_b[idx], I_w[idx], I_c[idx], method="lut", **DEFAULT_POLISH)}
    for key, fn in calls.items():
        fn()
        out[key] = min(_timed(fn) for _ in range(repeats))
    return out


def two_thicknesses(amaps: list[AppearanceMap], repeats: int) -> dict[str, Any]:
    """The paper's own procedure (Sec. 4.3): the same materials at every thickness, fitted together.
    Only when the held-out sets hold the same materials (same seed and grid); scored over the
    materials measurable at any thickness (g over α ≥ 0.5). Rows: paper (plain, pooled), lut p≤8,
    mlp p≤8 — time per 1024 bins of the whole multi-map fit(), α / g p95, and each map alone over its
    own measurable gamut for comparison."""
    import trimeter
    from trimeter.inversion.methods import METHODS

    sets = [heldout_for(m)[2] for m in amaps]
    if not all(np.array_equal(sets[0][k], h[k]) for h in sets[1:] for k in ("alpha", "sigma_t", "g")):
        print("\n   two thicknesses: the held-out sets hold different materials, not scored together")
        return {}
    a, s, g = (sets[0][k] for k in ("alpha", "sigma_t", "g"))
    inten = [heldout_intensities(h, *m.reference_rhos) for h, m in zip(sets, amaps, strict=True)]
    I_b, I_w = np.stack([i[0] for i in inten]), np.stack([i[1] for i in inten])
    I_c = np.stack([heldout_collimated(m, h) for m, h in zip(amaps, sets, strict=True)])
    measurable = np.any(np.stack([m.collimated(s) for m in amaps]) >= MEASURABLE_IC, axis=0)  # as error_budget
    tile = np.resize(np.arange(len(a)), 1024)
    names = " + ".join(m.name for m in amaps)
    print(f"\n== two thicknesses: {names} — {len(a)} materials, {int(measurable.sum())} measurable at either thickness")
    print(f"   {'variant':22s} {'ms_per_1024':>12s} {'alpha_p95':>10s} {'g_p95':>8s}   alone: " +
          "  ".join(f"{m.name.rsplit('-', 1)[-1]} α / g" for m in amaps))
    def p95(r: FitResult, scored: np.ndarray) -> dict[str, float]:
        return {"alpha_p95": _pct(np.abs(r.alpha - a)[scored], 95),
                "g_p95": _pct(np.abs(r.g - g)[scored & (a >= G_MIN_ALPHA)], 95)}

    rows: list[Row] = []
    for strategy in sorted(METHODS.values(), key=lambda m: not m.joint):  # each method's plain default
        method = strategy.name
        name, kw = (method, strategy.bench_variants[0][1]) if strategy.joint else (f"{method} p≤8", DEFAULT_POLISH)
        if not all(m.path and m.path.with_suffix(suffix).is_file() for m in amaps for suffix in strategy.needs):
            continue
        res = trimeter.fit(list(amaps), I_b, I_w, I_c, method=method, **kw)
        alone = [trimeter.fit(m, I_b[i], I_w[i], I_c[i], method=method, **kw) for i, m in enumerate(amaps)]
        fn = functools.partial(trimeter.fit, list(amaps), I_b[:, tile], I_w[:, tile], I_c[:, tile], method=method, **kw)
        fn()
        ms = min(_timed(fn) for _ in range(repeats))
        row: Row = {"variant": name, "ms_per_1024": ms, **p95(res, measurable),
               "alone": {m.name: p95(r, I_c[i] >= MEASURABLE_IC)
                         for i, (m, r) in enumerate(zip(amaps, alone, strict=True))}}
        rows.append(row)
        print(f"   {name:22s} {ms:12.4g} {row['alpha_p95']:10.4f} {row['g_p95']:8.4f}   " +
              "  ".join(f"{v['alpha_p95']:.4f} / {v['g_p95']:.4f}" for v in row["alone"].values()))
    print("   (α, g p95 over the materials measurable at either thickness; 'alone': each map by itself over its own "
          "measurable gamut, as in its table above)")
    targets = _print_targets("two thicknesses fitted together", rows)
    return {"maps": [m.name for m in amaps], "measurable": int(measurable.sum()), "rows": rows, "targets": targets}


# The speed targets of a fit with per-bin stds and flags: one thickness against a bare scipy lookup of
# the same bins (a ratio, so that the machine's speed drops out), two thicknesses in absolute time.
SPEED_LOOKUP_RATIO_MAX, SPEED_TWO_MS_MAX = 0.8, 0.8


def speed(amaps: list[AppearanceMap], median_bins: int, repeats: int) -> dict[str, Any]:
    """The whole lut fit (validation, flags, stds) on 1024 bins against, in the same run and timed
    round-robin (the machine is shared): a bare scipy LinearNDInterpolator lookup of the same bins on
    the map's nodes (the paper's interpolant, built beforehand: the call alone) and the paper's fixed
    method (the ε-median of `samples` interpolations, timed on median_bins bins, scaled to 1024).
    Bins: the ideal (else the first) map's held-out materials inside the hull of its nodes, noise-free,
    tiled to 1024. Two thicknesses: where two
    maps share geometry and n at other thicknesses, the same materials' intensities from each map's
    forward model, fitted together; the one-thickness fit of the first of them is timed beside it."""
    import trimeter
    from trimeter.inversion.paper import coordinates, interpolator
    from trimeter.maps.artifacts import load_artifacts

    amap = next((m for m in amaps if m.recipe.get("geometry") == "ideal"), amaps[0])
    artifacts = load_artifacts(amap)
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    interp = interpolator(amap, round(rb, 3), round(rw, 3), artifacts.paper_cache)
    # inside the hull of the map's nodes only: the lookup's fastest case (see hull_split), so the ratio
    # is the lookup's best against the fit
    I_b, I_w = heldout_intensities(h, rb, rw)
    I_c = heldout_collimated(amap, h)
    inside = np.flatnonzero(interp.tri.find_simplex(coordinates(I_b, I_w, I_c)) >= 0)  # type: ignore[attr-defined]
    tile = np.resize(inside if len(inside) else np.arange(len(I_b)), 1024)
    I_b, I_w, I_c = I_b[tile], I_w[tile], I_c[tile]
    calls: dict[str, Callable[[], object]] = {
        "bare lookup": lambda: interp(coordinates(I_b, I_w, I_c)),
        "lut": lambda: trimeter.fit(amap, I_b, I_w, I_c, method="lut", **DEFAULT_POLISH)}
    pair = next(((a, b) for i, a in enumerate(amaps) for b in amaps[i + 1:]
                 if (a.recipe.get("geometry"), a.n) == (b.recipe.get("geometry"), b.n)
                 and a.thickness_mm != b.thickness_mm), None)
    if pair is not None:
        _, _, hp = heldout_for(pair[0])
        tp = np.resize(np.arange(len(hp["alpha"])), 1024)
        a, s, g = (hp[k][tp] for k in ("alpha", "sigma_t", "g"))
        forward = [load_artifacts(m).grid.intensities(a, s, g, *m.reference_rhos) for m in pair]
        stacked = [np.stack([f[i] for f in forward]) for i in range(3)]
        first = [x[0] for x in stacked]
        calls[f"lut, {pair[0].name} alone"] = lambda: trimeter.fit(pair[0], first[0], first[1], first[2],
                                                                    method="lut", **DEFAULT_POLISH)
        calls["lut, two thicknesses"] = lambda: trimeter.fit(list(pair), stacked[0], stacked[1], stacked[2],
                                                             method="lut", **DEFAULT_POLISH)
    best = {name: np.inf for name in calls}
    for fn in calls.values():
        fn()
    for _ in range(max(repeats, 1) * 20):
        for name, fn in calls.items():
            best[name] = min(best[name], _timed(fn))
    nb = max(1, min(median_bins, 1024))
    median = functools.partial(trimeter.fit, amap, I_b[:nb], I_w[:nb], I_c[:nb], method="paper")
    median()
    paper_ms = _timed(median) * 1024 / nb
    lookup = best["bare lookup"]
    print(f"\n== speed with uncertainty: {amap.name}, 1024 bins (its held-out materials inside the hull of its "
          f"nodes, noise-free), one core, "
          f"best of {max(repeats, 1) * 20} round-robin rounds")
    print(f"   {'':44s} {'ms_per_1024':>12s} {'× bare lookup':>14s} {'× paper faster':>15s}")
    print(f"   {'paper ε-median (fixed; ' + str(nb) + ' bins, scaled)':44s} {paper_ms:12.4g} "
          f"{paper_ms / lookup:14.3g} {1.0:15.3g}")
    for name, ms in best.items():
        print(f"   {name:44s} {ms:12.4g} {ms / lookup:14.3g} {paper_ms / ms:15.3g}")
    ratio = best["lut"] / lookup
    verdicts = {"lut_over_lookup": {"value": ratio, "max": SPEED_LOOKUP_RATIO_MAX,
                                    "met": ratio <= SPEED_LOOKUP_RATIO_MAX}}
    line = (f"   targets: whole lut fit ≤ {SPEED_LOOKUP_RATIO_MAX:g}× a bare lookup: ×{ratio:.3g} "
            f"{'met' if ratio <= SPEED_LOOKUP_RATIO_MAX else 'MISSED'}")
    if pair is not None:
        two = best["lut, two thicknesses"]
        verdicts["two_thicknesses_ms"] = {"value": two, "max": SPEED_TWO_MS_MAX, "met": two <= SPEED_TWO_MS_MAX}
        line += (f"; two thicknesses ({pair[0].name} + {pair[1].name}) ≤ {SPEED_TWO_MS_MAX:g} ms: {two:.3g} ms "
                 f"{'met' if two <= SPEED_TWO_MS_MAX else 'MISSED'}")
    print(line)
    return {"map": amap.name, "ms_per_1024": {**best, "paper ε-median": paper_ms}, "targets": verdicts}


_EVICT: list[np.ndarray] = []


def _evict_caches() -> None:
    """Write 64 MB (twice this machine's last-level cache): whatever a fit had cached is gone."""
    if not _EVICT:
        _EVICT.append(np.zeros(8 << 20))
    _EVICT[0] += 1.0


def _timed(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return (time.perf_counter() - t) * 1e3


def per_wavelength_backgrounds(n: int, rho_b: float, rho_w: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth ρ_b(λ), ρ_w(λ) over n bins around the reference values, as a calibration measures
    them: a black background's reflectance varies by tens of % over the visible, a white one's by
    a few % (downwards here: ρ_w stays ≤ 1)."""
    t = np.linspace(0.0, 1.0, n)
    return rho_b * (1.0 + 0.5 * np.sin(2 * np.pi * t)), rho_w * (1.0 - 0.05 * t)


BACKGROUND_VARIANTS = ("paper", "lut p≤8", "mlp p≤8")


def _bench_backgrounds(amap: AppearanceMap, h: Heldout, budget: dict[str, Any], variants: list[Variant]) -> list[Row]:
    """The held-out materials 4× over (960 bins) with per-wavelength backgrounds, noise-free, each
    variant timed once, cold: its first fit() after a calibration produced these ρ(λ) (the paper
    method triangulates once per distinct (ρ_b, ρ_w) pair; lut and mlp need nothing per ρ)."""
    idx = np.tile(np.arange(len(h["alpha"])), 4)
    rho_b, rho_w = per_wavelength_backgrounds(len(idx), *budget["rho"])
    I_b, I_w = heldout_intensities({k: h[k][idx] for k in ("A", "B", "C")}, rho_b, rho_w)
    I_c = heldout_collimated(amap, h, idx)
    truth = tuple(h[k][idx] for k in ("alpha", "sigma_t", "g"))
    tiled = {k: budget[k][idx] for k in ("measurable", "g_scored", "well_alpha", "well_g")}
    pairs = len(np.unique(np.round(np.column_stack([rho_b, rho_w]), 3), axis=0))
    rows = []
    for variant in variants:
        name = variant[0]
        if name not in BACKGROUND_VARIANTS:
            continue
        paper_cache = variant[3].paper_cache
        if paper_cache is not None:  # cold: no triangulation for these backgrounds yet
            paper_cache.clear()
        t = time.perf_counter()
        res = _fit_variant(variant, I_b, I_w, I_c, rho_b, rho_w)
        ms = (time.perf_counter() - t) * 1e3 * 1024 / len(idx)
        rows.append({"noise": 0.0, "reference": "rendered, per-wavelength backgrounds", "variant": name,
                     **_stats(res, truth, tiled), "ms_per_1024": ms, "ms_per_1024_cold": float("nan"),
                     "core_ms_per_1024": float("nan"), "background_pairs": pairs})
    return rows


def run(args: argparse.Namespace) -> int:
    report = measure(args)
    atomic_write(args.out / "results.json", json.dumps(report, indent=1, default=float))
    print(f"\nall figures: {args.out / 'results.json'}")
    return 0


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Run the bench as `run` does (printing its tables, writing the Pareto plots into args.out) and
    return every figure: per map its rows (per noise level and variant), map-exact rows, error budget
    and target verdicts; the two-thickness rows when two maps hold the same materials."""
    from trimeter.inversion import native
    from trimeter.maps.artifacts import ArtifactCache
    from trimeter.maps.device_table import build_from_map

    noise_levels = [float(x) for x in args.noise.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    # lut/mlp timings depend on it: the C kernel, or the numpy reference when the library is missing
    print(f"inversion kernel: {native.status()}")
    report: dict[str, Any] = {"maps": [], "kernel": native.status()}
    amaps = _maps(args.maps)  # loaded once: the two-thickness case below reuses them (and their refined grids)
    cache = ArtifactCache()
    for amap in amaps:
        artifacts = cache.get(amap)
        path, meta, h = heldout_for(amap)
        rb, rw = amap.reference_rhos
        a, s, g = h["alpha"], h["sigma_t"], h["g"]
        I_b0, I_w0 = heldout_intensities(h, rb, rw)
        I_c0 = heldout_collimated(amap, h)
        budget = error_budget(amap, h, rb, rw, artifacts)
        budget["rho"] = (rb, rw)
        measurable = budget["measurable"]
        mc = float(np.median(np.concatenate([h["std_b"], h["std_w"]])))
        print(f"\n== {amap.name}  (ℓ = {amap.thickness_mm:g} mm, grid {amap.A.shape}, ρ_b {rb:g}, ρ_w {rw:g})")
        print(f"   held-out: {path} — {len(a)} materials, {int(measurable.sum())} in the measurable gamut "
              f"(I_c ≥ {MEASURABLE_IC:g}); source: {meta.get('source')}; their own MC std-error median {mc:.1e}")
        t0 = time.perf_counter()
        small_table = build_from_map(amap, n_inverse=SMALL_INVERSE)
        small_cache = ArtifactCache(tables={amap.name: small_table})
        print(f"   small table ({SMALL_INVERSE}×{SMALL_INVERSE} inverse grid) built in "
              f"{time.perf_counter() - t0:.1f} s, "
              f"{small_table.size_bytes} bytes; full table: {artifacts.inverter.table.size_bytes} bytes")
        variants = _variants(amap, cache, small_cache)
        rng = np.random.default_rng(args.seed)
        rows = []
        for level in noise_levels:
            noisy = tuple(x * (1 + level * rng.standard_normal(x.shape)) if level else x for x in (I_b0, I_w0, I_c0))
            rows += _bench_case(variants, (a, s, g), budget, noisy, "rendered", level, args)
        exact_rows = _bench_case(variants, (a, s, g), budget, budget["map_exact"], "map-exact", 0.0, args)
        background_rows = (_bench_backgrounds(amap, h, budget, variants) if args.per_wavelength_backgrounds else [])
        hull = hull_split(artifacts, I_b0, I_w0, I_c0, rb, rw, args.repeats)
        for level in noise_levels:
            _print_table([r for r in rows if r["noise"] == level], f"noise {level * 100:g} %")
        _print_table(exact_rows, "map-exact")
        print(f"\n   paper's inputs: {hull['outside_hull']} of {hull['of']} noise-free held-out materials fall "
              f"outside the Delaunay hull of the map's nodes (NaN); scipy searches every simplex (~0.3 ms) for "
              f"each that is inside the hull's bounding box, so the paper rows' time depends on them.")
        if "lut_ms" in hull:
            print(f"   inside the hull only: paper {hull['paper_ms']:.3g} ms (core {hull['paper_core_ms']:.3g}), "
                  f"lut p≤8 {hull['lut_ms']:.3g} ms per 1024 bins → ×{hull['paper_ms'] / hull['lut_ms']:.1f} "
                  f"(core: ×{hull['paper_core_ms'] / hull['lut_ms']:.1f} against lut's whole fit)")
        if background_rows:
            _print_table(background_rows, "ρ(λ) per bin, cold")
            print(f"   (ρ(λ) per bin: ρ_b {rb:g}·(1 ± 0.5), ρ_w {rw:g}·(0.95…1) over the bins, "
                  f"{background_rows[0]['background_pairs']} distinct (ρ_b, ρ_w) pairs at 1e-3; each variant's first "
                  f"fit after the calibration, timed once)")
        summary = _budget_summary(budget)
        _print_budget(summary, rows, exact_rows)
        targets = _print_targets(amap.name, [r for r in rows if r["noise"] == 0])
        png = _pareto(rows, exact_rows, summary, amap, args.out)
        print(f"   Pareto plot: {png}")
        report["maps"].append({"map": amap.name, "geometry": amap.recipe.get("geometry"),
                               "thickness_mm": amap.thickness_mm, "heldout": str(path),
                               "heldout_source": meta.get("source"), "materials": len(a),
                               "measurable": int(measurable.sum()), "rows": rows, "map_exact_rows": exact_rows,
                               "background_rows": background_rows, "paper_hull_split": hull, "budget": summary,
                               "targets": targets})
    if len(report["maps"]) >= 2:
        report["two_thicknesses"] = two_thicknesses(amaps, args.repeats)
    report["speed"] = speed(amaps, args.median_bins, args.repeats)
    return report


def _print_table(sub: list[Row], title: str) -> None:
    cols = ("ms_per_1024", "ms_per_1024_cold", "core_ms_per_1024", "alpha_p50", "alpha_p95", "sigma_rel_p50",
            "sigma_rel_p95", "g_p50", "g_p95", "nan_rate", "flag_rate", "files_kB", "model_kB", "peak_kB")
    base = next(r for r in sub if r["variant"] == "paper")
    print(f"\n   {title:<19}" + " ".join(f"{c:>13}" for c in cols))
    for r in sub:
        print(f"   {r['variant']:<18}" + " ".join(f"{r[c]:>13.4g}" for c in cols))
        if r["variant"] != "paper":
            ratios = []
            for c in cols:
                if c.startswith(("ms_", "core_ms")):
                    ratios.append(f"{'×%.1f faster' % (base[c] / r[c]) if r[c] else '-':>13}")
                else:
                    ratios.append(f"{'%.3g' % (r[c] / base[c]) if base[c] else '-':>13}")
            print(f"   {'  ratio to paper':<18}" + " ".join(ratios))


def _print_budget(summary: dict[str, dict[str, float]], rows: list[Row], exact_rows: list[Row]) -> None:
    ref, err, wc = summary["reference_noise_floor"], summary["map_error_floor"], summary["well_conditioned"]
    print(f"\n   error budget, noise-free (first order through the map's Jacobian; α over the measurable gamut, "
          f"g over α ≥ {G_MIN_ALPHA:g}):")
    print(f"   {'':<52}{'α p50':>9}{'α p95':>9}{'g p50':>9}{'g p95':>9}")
    for label, d in (("reference noise floor (held-out MC std-error → std)", ref),
                     ("map error floor (map forward − held-out I → error)", err),
                     ("  its MC part (map nodes' std-error → std, ≤)", summary["map_noise_floor"]),
                     ("  map error floor over the well-conditioned subset",
                      summary["map_error_floor_well_conditioned"])):
        print(f"   {label:<52}" + "".join(f"{d[k]:>9.4f}" for k in ("alpha_p50", "alpha_p95", "g_p50", "g_p95")))
    print(f"   well-conditioned (reference floor below half the target): α std < {wc['alpha_floor_std_below']:g} for "
          f"{wc['alpha_count']}/{wc['alpha_of']} materials, g std < {wc['g_floor_std_below']:g} for "
          f"{wc['g_count']}/{wc['g_of']}")
    print(f"\n   noise-free p95 {'':<5}{'rendered α':>11}{'g':>9} | {'well-cond. α':>12}{'g':>9} | "
          f"{'map-exact α':>12}{'g':>9} | {'determined α':>12}{'g':>9}{'share':>7}   "
          f"(targets α {ALPHA_TARGET:g}, g {G_TARGET:g}; determined: no UNDERDETERMINED flag)")
    exact = {r["variant"]: r for r in exact_rows}
    for r in (r for r in rows if r["noise"] == 0):
        e = exact[r["variant"]]
        print(f"   {r['variant']:<20}{r['alpha_p95']:>11.4f}{r['g_p95']:>9.4f} | {r['alpha_p95_well']:>12.4f}"
              f"{r['g_p95_well']:>9.4f} | {e['alpha_p95']:>12.4f}{e['g_p95']:>9.4f} | "
              f"{r['alpha_p95_determined']:>12.4f}{r['g_p95_determined']:>9.4f}{r['determined_rate']:>7.0%}")
    print(f"\n   noise-free, rendered: bins over the α target ({ALPHA_TARGET:g}), and how many of them the fit "
          f"itself flags UNDERDETERMINED")
    for r in (r for r in rows if r["noise"] == 0 and r["variant"] != "paper-median"):
        line = f"   {r['variant']:<20}{r['alpha_misses']:>4} of {r['measurable']:<4}"
        if r["alpha_misses"]:
            line += (f" {r['alpha_misses_flagged']:>4} flagged; smallest fit α std among them "
                     f"{r['alpha_misses_min_std']:.3g}")
        print(line)


def target_checks(row: Row, paper: Row) -> dict[str, dict[str, Any]]:
    """The inversion targets for one lut/mlp row (noise-free, rendered references) against the paper row
    of the same run: {target: {"value", "limit", "met"}}. Figures a row lacks (the two-thickness rows
    have no cold time, σt or NaN figures) are not checked."""
    kind = row["variant"].split()[0]  # "lut" / "mlp"
    checks: dict[str, dict[str, Any]] = {}

    def check(name: str, value: float, limit: float, met: bool | np.bool_, issue_target: bool = True) -> None:
        checks[name] = {"value": value, "limit": limit, "met": bool(met), "issue_target": issue_target}

    # The speed-up target is a throughput figure (time per 1024 bins): warm, as in a batch of spectra.
    # Cold (one press-button fit after the caches were evicted) is this bench's own stricter view,
    # judged against the same limit but not a target: it is memory-bound (the
    # polish's refined forward model is ~22 MB) and moves ±15 % with the machine's state.
    for key, label, target in (("ms_per_1024", "× paper", True), ("ms_per_1024_cold", "× paper cold", False)):
        if key in row and key in paper:
            ratio = paper[key] / row[key]
            check(label, ratio, SPEEDUP_TARGET, ratio >= SPEEDUP_TARGET, target)
    check("ms per 1024 bins", row["ms_per_1024"], MS_TARGET[kind], row["ms_per_1024"] <= MS_TARGET[kind])
    check("α p95", row["alpha_p95"], ALPHA_TARGET, row["alpha_p95"] <= ALPHA_TARGET)
    if "sigma_rel_p95" in row:
        check("σt relative p95", row["sigma_rel_p95"], SIGMA_REL_TARGET, row["sigma_rel_p95"] <= SIGMA_REL_TARGET)
    check("g p95 (α ≥ 0.5)", row["g_p95"], G_TARGET, row["g_p95"] <= G_TARGET)
    if "nan_rate_measurable" in row:
        check("NaN in the gamut", row["nan_rate_measurable"], 0.0, row["nan_rate_measurable"] == 0)
    return checks


def _show_check(name: str, c: dict[str, Any]) -> str:
    verdict = "" if c["met"] else (" MISSED" if c["issue_target"] else f" (below {c['limit']:g})")
    return f"{name} {c['value']:.3g}{verdict}" + ("" if c["issue_target"] else " [not a target]")


def _print_targets(title: str, rows: list[Row]) -> dict[str, dict[str, dict[str, Any]]]:
    """One line per lut/mlp p≤8 variant: every inversion target, met or MISSED, from this run (the targets
    are noise-free: nothing to judge when --noise left out 0)."""
    paper = next((r for r in rows if r["variant"] == "paper"), None)
    if paper is None:
        print(f"\n   inversion targets, {title}: not judged (they are noise-free figures: include 0 in --noise)")
        return {}
    print(f"\n   inversion targets, {title} (noise-free, rendered references; ratios to paper in this run):")
    verdicts: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if r["variant"] not in ("lut p≤8", "mlp p≤8"):
            continue
        checks = target_checks(r, paper)
        verdicts[r["variant"]] = checks
        missed = [k for k, c in checks.items() if c["issue_target"] and not c["met"]]
        print(f"   {r['variant']:<10}" + "; ".join(_show_check(k, c) for k, c in checks.items())
              + (f"  — MISSED: {', '.join(missed)}" if missed else "  — all targets met"))
    return verdicts


def _pareto(rows: list[Row], exact_rows: list[Row], summary: dict[str, dict[str, float]], amap: AppearanceMap,
            out: Path) -> Path:
    """Time against α / g p95, noise-free: rendered references (filled), map-exact (hollow, the
    method's own error, joined to its rendered point) and the budget's floors (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clean = [r for r in rows if r["noise"] == 0] or rows
    exact = {r["variant"]: r for r in exact_rows}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "alpha_p95", "α abs error p95"), (axes[1], "g_p95", "g abs error p95 (α ≥ 0.5)")):
        for i, r in enumerate(clean):
            colour = f"C{i % 10}"
            ax.scatter(r["ms_per_1024"], r[key], s=30, color=colour)
            ax.annotate(r["variant"], (r["ms_per_1024"], r[key]), fontsize=7, xytext=(3, 3), textcoords="offset points")
            e = exact.get(r["variant"])
            if e is not None and e[key] > 0:
                ax.scatter(e["ms_per_1024"], e[key], s=30, facecolors="none", edgecolors=colour)
                ax.plot([r["ms_per_1024"], e["ms_per_1024"]], [r[key], e[key]], color=colour, lw=0.5, alpha=0.5)
        for floor, style in (("reference_noise_floor", "--"), ("map_error_floor", ":")):
            value = summary[floor][key]
            if np.isfinite(value) and value > 0:
                ax.axhline(value, color="grey", ls=style, lw=1, label=floor.replace("_", " ") + " (p95)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per 1024 bins [ms] (whole fit(), one core)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"trimeter bench fit — {amap.name}, noise-free: rendered held-out (filled), map-exact (hollow)")
    fig.tight_layout()
    png = out / f"pareto-{amap.name}.png"
    with atomic_output(png) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)
    return png
