"""`trimeter bench mapbuild`: naive map building vs the (k, m)-tally tracer, at matched MC error.

Both ways build the same small map in one run — the production α axis (40 values, finer near 1) at a
few (σt, g) columns, two backgrounds, `ideal` geometry:

- naive: one direct Mitsuba volpath render (trimeter.forward.render.render_diffuse) per
  (α, σt, g, ρ) point. Rendering all of them would take tens of minutes, so a random sample of points
  is rendered *in this run* at `--spp` samples each (time t_i, std-error s_i). The sample is
  stratified: every (σt, g, ρ) stratum (40 points each) gets a render in turn (a seeded random order,
  a random α), and a per-point quantity's mean over the map is the mean of its stratum means.
- new: the builder (trimeter.maps.builder) with target_stderr = the naive renders' median std-error
  (each column traced until its *largest* std-error over α and both backgrounds is at most that).
  The same map is also built with the tracer's plain estimator (no control variates, B not
  factorised, as many background as detector paths) and with the unfactorised default one (control
  variates, B from detector paths that carry on past the background, as device columns are traced),
  for their ratios in this run.

Matched error (the headline): a naive builder that matched the new map's MC error would render each
point to the map's own std-error σ_i there. Std-error ∝ 1/√spp and a render costs a fixed overhead
t_0 (measured here: a render of 4096 samples) plus time ∝ spp, so point i would take
t_0 + (t_i − t_0)·(s_i/σ_i)². The naive map's time is the number of points × the mean of that over
the rendered points (stratified, ± its standard error; with a single render in some stratum, the
unstratified formula, an overestimate); `ratio: N` = that / the new map's seconds.
The spread of (s_i/σ_i)² is printed too: a point where the map is far more precise than the render
weighs in fully, since the naive way would pay for it.

Also printed beside it, so that nothing is hidden: the same at the *requirement* the builder meets, std-error
≤ T (its target) at every point — a naive builder would render each point just to T, t_0 + (t_i − t_0)·(s_i/T)²,
and gets no credit for the map's extra precision elsewhere (the conservative figure); every ratio also in
CPU seconds of this process (Mitsuba's and Dr.Jit's threads), which the machine's load moves far less
than wall time; and the older statistic: the naive renders at their own `--spp` (number of points ×
mean t_i) over the new map's seconds. That one favours the naive side — the builder drives each column's
*worst* std-error to the naive *median*, so most of the map is more precise than the renders it is
compared with.

`--device-columns RECIPE` instead compares the tracer's estimators on columns of a device recipe: per
column, the plain one (as many background as detector paths, no control variates) and the default one
are traced alternately on the same seeds, and each one's time to the recipe's criterion is projected
from its seconds per path and the paths it needs (the builder's rule: std-error ∝ 1/√N, within the
recipe's min/max paths). Also the same projection in loop iterations (path events: the work, whatever
the machine's load). The last line is `ratio: N`, N = Σ plain time / Σ default time.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.errors import InputError
from trimeter.maps.recipe import Recipe, parse_recipe


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("mapbuild", help="map building: naive direct renders vs the (k, m)-tally tracer")
    p.add_argument("--spp", type=int, default=655360, help="samples per naive render (the paper's 640K)")
    p.add_argument("--naive-renders", type=int, default=24,
                   help="naive renders measured in this run (≥ 12: one per (σt, g, ρ) stratum; ≥ 24: two)")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--device-columns", metavar="RECIPE",
                   help="compare the tracer's plain and default estimators on columns of this device recipe")
    p.add_argument("--paths", type=int, default=1 << 21, help="detector paths per column (--device-columns)")
    p.set_defaults(func=run)


# Representative columns: clear, middle and dense σt at both ends of g.
COLUMNS = [(s, g) for s in (0.05, 0.2, 1.0, 5.0, 50.0) for g in (0.0, 0.9)]


def compare_estimators(recipe_path: str, n_paths: int, seed: int) -> int:
    """Print each column's projected time to the recipe's criterion with both estimators, and the ratio."""
    from trimeter.maps.builder import criterion_shortfall
    from trimeter.maps.recipe import load_recipe
    from trimeter.forward.transport import Stack, k_max_for, trace_column

    if n_paths < 65536:
        raise InputError(f"--paths must be ≥ 65536 (the projection scales the std-error it measures), got {n_paths}")
    recipe = load_recipe(recipe_path)
    s = recipe.sampling
    stack = Stack.from_recipe(recipe.geometry, recipe.geometry_params, recipe.n, recipe.thickness_mm)
    k_max = k_max_for(float(recipe.alpha[-1]), s.truncation)
    plain: dict[str, Any] = {"below_fraction": 1.0, "control_variates": False}
    trace_column(stack, 1.0, 0.5, 4096, seed, k_max, **plain)      # compile both kernels outside the timing
    trace_column(stack, 1.0, 0.5, 4096, seed, k_max)
    print(f"{recipe.name}: {n_paths} detector paths per column and estimator; criterion: α std-error ≤ "
          f"{s.target_alpha_stderr} where measurable, I std-error ≤ {s.target_stderr}, "
          f"{s.min_paths}…{s.max_paths} paths")
    totals = {"plain": 0.0, "default": 0.0}
    work = {"plain": 0.0, "default": 0.0}
    for i, (sigma_t, g) in enumerate(COLUMNS):
        row, times = [], []
        no_options: dict[str, Any] = {}
        for name, options in (("plain", plain), ("default", no_options)):
            t0 = time.perf_counter()
            tally = trace_column(stack, sigma_t, g, n_paths, seed + i, k_max, **options)
            seconds = time.perf_counter() - t0
            shortfall = criterion_shortfall(tally, recipe, sigma_t)
            needed = min(max(s.min_paths, n_paths * shortfall**2), s.max_paths)
            projected = seconds / n_paths * needed
            totals[name] += projected
            times.append(projected)
            events = tally.path_events / n_paths * needed
            work[name] += events
            row.append(f"{name} {seconds / n_paths * 1e6:5.2f} µs/path × {needed / 1e6:6.1f}M = {projected:6.1f} s "
                       f"({events / 1e9:5.2f}G iterations)")
        print(f"  σt {sigma_t:5g}, g {g:.1f}: " + "; ".join(row) + f"  → ×{times[0] / times[1]:.2f}", flush=True)
    print(f"sum over these columns: plain {totals['plain']:.0f} s, default {totals['default']:.0f} s; iterations "
          f"{work['plain'] / 1e9:.2f}G vs {work['default'] / 1e9:.2f}G (×{work['plain'] / work['default']:.2f})")
    print(f"ratio: {totals['plain'] / totals['default']:.2f}")
    return 0


def matched_naive_seconds(seconds: np.ndarray, overhead: float, naive_std: np.ndarray,
                          map_std: np.ndarray) -> np.ndarray:
    """Per rendered point, the seconds a direct render would take to reach the map's std-error there:
    t_0 + (t_i − t_0)·(s_i/σ_i)² (std-error ∝ 1/√spp, time = overhead + ∝ spp); inf where σ_i = 0."""
    seconds, naive_std, map_std = (np.asarray(a, dtype=np.float64) for a in (seconds, naive_std, map_std))
    if not (seconds.shape == naive_std.shape == map_std.shape) or seconds.size == 0:
        raise InputError("matched_naive_seconds needs one time, naive and map std-error per rendered point")
    if np.any(seconds <= 0) or np.any(naive_std < 0) or np.any(map_std < 0) or overhead < 0:
        raise InputError("render times must be positive and std-errors and the overhead non-negative")
    sampling = np.maximum(seconds - min(overhead, float(seconds.min())), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(map_std > 0, (naive_std / np.where(map_std > 0, map_std, 1.0)) ** 2, np.inf)
    return (seconds - sampling) + sampling * scale


def stratified_mean(values: np.ndarray, labels: np.ndarray) -> tuple[float, float]:
    """The mean over equal-sized strata of `values` sampled per stratum (`labels`): the mean of the
    stratum means, and its standard error — the stratified one if every stratum has ≥ 2 values, else
    the unstratified one (which also counts the spread between strata: an overestimate)."""
    values, labels = np.asarray(values, dtype=np.float64), np.asarray(labels)
    if values.shape != labels.shape or values.size < 2:
        raise InputError("stratified_mean needs at least two values, one stratum label each")
    groups = [values[labels == h] for h in np.unique(labels)]
    mean = float(np.mean([grp.mean() for grp in groups]))
    if all(len(grp) >= 2 for grp in groups):
        err = math.sqrt(sum(grp.var(ddof=1) / len(grp) for grp in groups)) / len(groups)
    else:
        err = float(values.std(ddof=1) / math.sqrt(values.size))
    return mean, err


BENCH_SIGMA_T = (0.2, 2.0, 20.0)
BENCH_G = (0.0, 0.8)


def bench_recipe(target_stderr: float) -> Recipe:
    return parse_recipe({
        "name": "bench-mapbuild", "geometry": "ideal", "n": 1.5, "thickness_mm": 0.5,
        "reference_rho_b": 0.02, "reference_rho_w": 0.9, "seed": 11,
        "grid": {"alpha": {"max": 0.999, "count": 40}, "sigma_t": list(BENCH_SIGMA_T), "g": list(BENCH_G)},
        "sampling": {"target_stderr": target_stderr, "min_paths": 65536, "max_paths": 4194304},
    })


def run(args: argparse.Namespace) -> int:
    if args.device_columns:
        return compare_estimators(args.device_columns, args.paths, args.seed)
    strata = [(j, k, r) for j in range(len(BENCH_SIGMA_T)) for k in range(len(BENCH_G)) for r in range(2)]
    if args.naive_renders < len(strata):
        raise InputError(f"--naive-renders must be ≥ {len(strata)} (one per (σt, g, ρ) stratum of the map), "
                         f"got {args.naive_renders}")
    if args.spp < 4096:
        raise InputError(f"--spp must be ≥ 4096 (a render of 4096 samples is the overhead measured), got {args.spp}")
    from trimeter.forward.render import render_diffuse
    from trimeter.maps.builder import build_map
    from trimeter.forward.transport import trace_column

    probe = bench_recipe(1e-3)
    rhos = (probe.reference_rho_b, probe.reference_rho_w)
    na, ns, ng = probe.shape
    n_points = na * ns * ng * len(rhos)
    rng = np.random.default_rng(args.seed)
    picks: list[tuple[int, int, int, int]] = []
    while len(picks) < args.naive_renders:
        for h in rng.permutation(len(strata))[: args.naive_renders - len(picks)]:
            picks.append((int(rng.integers(na)), *strata[h]))
    print(f"map: ideal, n = 1.5, ℓ = 0.5 mm; α {na} × σt {ns} × g {ng} × ρ {len(rhos)} = {n_points} "
          f"(α, σt, g, ρ) points")
    print(f"naive: volpath direct render per point at {args.spp} spp; measuring {len(picks)} random points "
          f"(stratified by σt, g, ρ)")
    render_diffuse("ideal", 0.5, 1.0, 0.5, 1.5, 0.5, 0.5, spp=4096, seed=0)   # load + JIT outside the timing
    with _Clocks() as small:  # a render's fixed cost: the time of one with few samples
        render_diffuse("ideal", 0.5, 1.0, 0.5, 1.5, 0.5, 0.5, spp=4096, seed=1)
    overhead = small.seconds
    naive: list[tuple[int, int, int, int, float, float]] = []
    clocks: list[np.ndarray] = []
    for i, j, k, r in picks:
        with _Clocks() as took:
            I, s = render_diffuse("ideal", float(probe.alpha[i]), float(probe.sigma_t[j]), float(probe.g[k]), 1.5,
                                  0.5, rhos[r], spp=args.spp, seed=args.seed + len(naive))
        naive.append((i, j, k, r, I, s))
        clocks.append(took.seconds)
        print(f"  α={probe.alpha[i]:.4f} σt={probe.sigma_t[j]:g} g={probe.g[k]:g} ρ={rhos[r]:g}: "
              f"I = {I:.5f} ± {s:.5f}  ({took.seconds[0]:.2f} s, {took.seconds[1]:.2f} CPU s)")
    seconds = np.array(clocks)                       # (render, [wall, CPU])
    naive_std = np.array([row[5] for row in naive])
    naive_err = float(np.median(naive_std))
    labels = np.array([strata.index(row[1:4]) for row in naive])
    naive_per, naive_per_err = stratified_mean(seconds[:, 0], labels)
    naive_total = naive_per * n_points
    naive_cpu_total = stratified_mean(seconds[:, 1], labels)[0] * n_points
    print(f"naive: {naive_per:.2f} ± {naive_per_err:.2f} s per render → "
          f"{naive_total:.0f} s for the map (extrapolated from {len(seconds)} renders); median std-error "
          f"{naive_err:.2e}; per-render overhead {overhead[0]:.2f} s (a 4096-sample render)")

    def matched(map_std: np.ndarray, clock: int) -> tuple[float, float]:
        """The naive map's seconds at these per-point std-errors (n_points × the stratified mean over
        the rendered points) and that estimate's standard error."""
        per_point = matched_naive_seconds(seconds[:, clock], float(overhead[clock]), naive_std, map_std)
        mean, err = stratified_mean(per_point, labels)
        return n_points * mean, n_points * err

    recipe = bench_recipe(naive_err)
    for name, estimator in (("plain", partial(trace_column, below_fraction=1.0, control_variates=False,
                                                factorise=False)),
                            ("unfactorised", partial(trace_column, factorise=False))):
        with tempfile.TemporaryDirectory() as tmp, _Clocks() as other_took:
            other = build_map(recipe, Path(tmp) / f"{name}.tmap", progress=False, tracer=estimator)
        other_total, other_cpu = (float(v) for v in other_took.seconds)
        other_std = np.concatenate([other.std_b.ravel(), other.std_w.ravel()])
        other_naive, other_naive_err = matched(_map_std(other, rhos, naive), 0)
        print(f"{name}: {other_total:.1f} s ({other_cpu:.1f} CPU s) for the whole map with the {name} estimator "
              f"({other.provenance['paths_per_column']['total']} paths, std-error median "
              f"{np.median(other_std):.2e}); matched-error ratio {other_naive / other_total:.1f} (naive "
              f"{other_naive:.0f} ± {other_naive_err:.0f} s; CPU seconds: "
              f"{matched(_map_std(other, rhos, naive), 1)[0] / other_cpu:.1f}), at the naive spp "
              f"{naive_total / other_total:.1f}")
    with tempfile.TemporaryDirectory() as tmp, _Clocks() as new_took:
        amap = build_map(recipe, Path(tmp) / "bench.tmap", progress=False)
    new_total, new_cpu = (float(v) for v in new_took.seconds)
    std = np.concatenate([amap.std_b.ravel(), amap.std_w.ravel()])
    print(f"new:   {new_total:.1f} s ({new_cpu:.1f} CPU s) for the whole map ({ns * ng} traces, "
          f"{amap.provenance['paths_per_column']['total']} paths); std-error median {np.median(std):.2e}, "
          f"max {std.max():.2e} (target {naive_err:.2e}); truncation ≤ "
          f"{amap.provenance['truncation']['max_error_bound']:.1e}")

    # Same points, both ways: grid points, so no interpolation is involved.
    z = np.array([(float(amap.diffuse(probe.alpha[i], probe.sigma_t[j], probe.g[k], rhos[r])) - I)
                  / math.hypot(s, (amap.std_b if r == 0 else amap.std_w)[i, j, k]) for i, j, k, r, I, s in naive])
    print(f"agreement at the rendered points: |z| median {np.median(np.abs(z)):.2f}, max {np.abs(z).max():.2f} "
          f"(z = (map − direct) / combined std-error)")
    map_std = _map_std(amap, rhos, naive)
    scale = (naive_std / map_std) ** 2
    print(f"(naive std-error / map std-error)² at the rendered points: median {np.median(scale):.1f}, "
          f"min {scale.min():.1f}, max {scale.max():.1f}")
    matched_total, matched_err = matched(map_std, 0)
    print(f"naive at the map's own std-error per point: {matched_total:.0f} ± {matched_err:.0f} s for the map "
          f"(ratio {(matched_total - matched_err) / new_total:.0f}…{(matched_total + matched_err) / new_total:.0f} "
          f"within one standard error); in CPU seconds: ratio {matched(map_std, 1)[0] / new_cpu:.1f}")
    spec, spec_err = matched(np.full(len(naive), naive_err), 0)
    print(f"conservative, naive rendering each point just to the builder's target {naive_err:.2e}: "
          f"{spec:.0f} ± {spec_err:.0f} s, ratio {spec / new_total:.1f} "
          f"(CPU seconds: {matched(np.full(len(naive), naive_err), 1)[0] / new_cpu:.1f})")
    print(f"older statistic, naive at its own {args.spp} spp (std-error median {naive_err:.2e} vs the map's "
          f"{np.median(std):.2e}): ratio {naive_total / new_total:.1f} (CPU seconds: {naive_cpu_total / new_cpu:.1f})")
    print(f"ratio: {matched_total / new_total:.1f}")
    return 0


class _Clocks:
    """Wall and CPU seconds (this process, all threads) of a `with` block: `seconds` = [wall, CPU]."""

    def __enter__(self) -> "_Clocks":
        self._start = np.array([time.perf_counter(), time.process_time()])
        self.seconds = np.zeros(2)
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds = np.array([time.perf_counter(), time.process_time()]) - self._start


def _map_std(amap: Any, rhos: tuple[float, float], naive: list[tuple[int, int, int, int, float, float]]) -> np.ndarray:
    """The map's std-error at each rendered (α, σt, g, ρ) point."""
    return np.array([float((amap.std_b if r == 0 else amap.std_w)[i, j, k]) for i, j, k, r, _, _ in naive])
