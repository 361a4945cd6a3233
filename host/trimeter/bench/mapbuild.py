"""`trimeter bench mapbuild`: naive map building vs the (k, m)-tally tracer, at matched MC error.

Both ways build the same small map in one run — the production α axis (40 values, finer near 1) at a
few (σt, g) columns, two backgrounds, `ideal` geometry:

- naive: one direct Mitsuba volpath render (trimeter.forward.render.render_diffuse) per
  (α, σt, g, ρ) point. Rendering all of them would take tens of minutes, so a random sample of points
  is rendered *in this run*; the naive time is (points × mean measured seconds per render) and the
  naive std-error is the median of the measured ones.
- new: the builder (trimeter.maps.builder) with target_stderr = that naive std-error, so the new map
  has equal or lower MC error (both printed).

The last line is `ratio: N` with N = naive seconds / new seconds.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np

from trimeter.maps.recipe import parse_recipe


def register(subparsers) -> None:
    p = subparsers.add_parser("mapbuild", help="map building: naive direct renders vs the (k, m)-tally tracer")
    p.add_argument("--spp", type=int, default=655360, help="samples per naive render (the paper's 640K)")
    p.add_argument("--naive-renders", type=int, default=12, help="naive renders measured in this run")
    p.add_argument("--seed", type=int, default=7)
    p.set_defaults(func=run)


def bench_recipe(target_stderr: float):
    return parse_recipe({
        "name": "bench-mapbuild", "geometry": "ideal", "n": 1.5, "thickness_mm": 0.5,
        "reference_rho_b": 0.02, "reference_rho_w": 0.9, "seed": 11,
        "grid": {"alpha": {"max": 0.999, "count": 40}, "sigma_t": [0.2, 2.0, 20.0], "g": [0.0, 0.8]},
        "sampling": {"target_stderr": target_stderr, "min_paths": 65536, "max_paths": 4194304},
    })


def run(args) -> int:
    from trimeter.forward.render import render_diffuse
    from trimeter.maps.builder import build_map

    probe = bench_recipe(1e-3)
    rhos = (probe.reference_rho_b, probe.reference_rho_w)
    na, ns, ng = probe.shape
    n_points = na * ns * ng * len(rhos)
    rng = np.random.default_rng(args.seed)
    picks = [(int(rng.integers(na)), int(rng.integers(ns)), int(rng.integers(ng)), int(rng.integers(len(rhos))))
             for _ in range(args.naive_renders)]
    print(f"map: ideal, n = 1.5, ℓ = 0.5 mm; α {na} × σt {ns} × g {ng} × ρ {len(rhos)} = {n_points} "
          f"(α, σt, g, ρ) points")
    print(f"naive: volpath direct render per point at {args.spp} spp; measuring {len(picks)} random points")
    render_diffuse("ideal", 0.5, 1.0, 0.5, 1.5, 0.5, 0.5, spp=4096, seed=0)   # load + JIT outside the timing
    naive = []
    for i, j, k, r in picks:
        t0 = time.perf_counter()
        I, s = render_diffuse("ideal", float(probe.alpha[i]), float(probe.sigma_t[j]), float(probe.g[k]), 1.5, 0.5,
                              rhos[r], spp=args.spp, seed=args.seed + len(naive))
        naive.append((i, j, k, r, I, s, time.perf_counter() - t0))
        print(f"  α={probe.alpha[i]:.4f} σt={probe.sigma_t[j]:g} g={probe.g[k]:g} ρ={rhos[r]:g}: "
              f"I = {I:.5f} ± {s:.5f}  ({naive[-1][-1]:.2f} s)")
    seconds = np.array([row[-1] for row in naive])
    naive_err = float(np.median([row[5] for row in naive]))
    naive_per = float(seconds.mean())
    naive_total = naive_per * n_points
    print(f"naive: {naive_per:.2f} ± {seconds.std(ddof=1) / math.sqrt(len(seconds)):.2f} s per render → "
          f"{naive_total:.0f} s for the map (extrapolated from {len(seconds)} renders); median std-error "
          f"{naive_err:.2e}")

    recipe = bench_recipe(naive_err)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        amap = build_map(recipe, Path(tmp) / "bench.tmap", progress=False)
        new_total = time.perf_counter() - t0
    std = np.concatenate([amap.std_b.ravel(), amap.std_w.ravel()])
    print(f"new:   {new_total:.1f} s for the whole map ({ns * ng} traces, "
          f"{amap.provenance['paths_per_column']['total']} paths); std-error median {np.median(std):.2e}, "
          f"max {std.max():.2e} (target {naive_err:.2e}); truncation ≤ "
          f"{amap.provenance['truncation']['max_error_bound']:.1e}")

    # Same points, both ways: grid points, so no interpolation is involved.
    z = []
    for i, j, k, r, I, s, _ in naive:
        m_std = (amap.std_b if r == 0 else amap.std_w)[i, j, k]
        I_map = float(amap.diffuse(probe.alpha[i], probe.sigma_t[j], probe.g[k], rhos[r]))
        z.append((I_map - I) / math.hypot(s, m_std))
    z = np.array(z)
    print(f"agreement at the rendered points: |z| median {np.median(np.abs(z)):.2f}, max {np.abs(z).max():.2f} "
          f"(z = (map − direct) / combined std-error)")
    matched = np.median(std) <= naive_err * 1.05
    print(f"matched error: new median std-error {'≤' if matched else '>'} naive ({np.median(std):.2e} vs "
          f"{naive_err:.2e})")
    print(f"ratio: {naive_total / new_total:.1f}")
    return 0
