#!/usr/bin/env python3
"""Render the held-out materials `trimeter bench fit` scores the inversion methods on, and cache them
as a committed data file (so the benchmark never re-renders): maps/heldout/<recipe-name>.held.

    nice taskset -c 1 .venv/bin/python tools/make_heldout.py maps/recipes/device-n1.5-l0.4.toml \
        [--pairs 64 --alphas 5 --paths 16777216 --seed 2027]   # ~12-14 min per device map on 2 cores
    .venv/bin/python tools/make_heldout.py --ideal tests/inversion/data/ideal-l0.5.tmap [--count 300]

Materials are random and OFF the map grid (α, σt, g all drawn continuously; any draw within 1e-3 of a
grid node on every axis is redrawn), rendered directly — never interpolated from a map:
- device/recipe maps: the builder's Dr.Jit tracer (trimeter.forward.transport.trace_column: detector and
  background paths, validated against Mitsuba volpath by the map helpers) at each random (σt, g),
  with `--paths` paths; one trace serves several random α. Records A, B, C per material and their MC
  std-error at the reference backgrounds.
- --ideal: Prahl's adding-doubling (iadpython), exact for the ideal geometry.
I_b, I_w at any ρ follow from A, B, C; I_c is analytic (trimeter.model.collimated), times
e^inscatter_log1p for device sets: the light scattered into the detector's aperture, traced per
material (`--inscatter SET`: trimeter.forward.transport.inscatter_tracer, one trace per (σt, g) column for all its α,
independent of the map's own in-scattering table).

Why 16M paths per (σt, g), and more for clear samples: the references must be precise enough to check the
inversion targets (α p95 0.01, g p95 0.015), and their own MC noise, propagated through the map's Jacobian
(the "reference noise floor" `trimeter bench fit` prints), falls only as 1/√paths. Clear samples (σt·ℓ < 0.1,
where I_b, I_w barely change with α) dominate it, so their columns are topped up (once, to at most --max-paths)
until α's std-error with g held is ≤ --alpha-stderr. The figures: `trimeter bench fit`'s error budget.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HELDOUT_KIND = "heldout-set"
HELDOUT_DIR = Path(__file__).resolve().parents[1] / "maps" / "heldout"


def _off_grid(values, axis, rng, lo, hi, log=False):
    """Redraw values that sit within 1e-3 (relative span) of a grid node."""
    span = (np.log(hi) - np.log(lo)) if log else (hi - lo)
    for _ in range(20):
        x = np.log(values) if log else values
        ax = np.log(axis) if log else axis
        near = np.min(np.abs(x[:, None] - ax[None, :]), axis=1) < 1e-3 * span
        if not near.any():
            break
        fresh = rng.uniform(np.log(lo), np.log(hi), near.sum()) if log else rng.uniform(lo, hi, near.sum())
        values[near] = np.exp(fresh) if log else fresh
    return values


def from_recipe(recipe_path, pairs, alphas, paths, seed, alpha_stderr=None, max_paths=None):
    import os

    os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so")
    from trimeter.maps.recipe import load_recipe
    from trimeter.maps.builder import paths_to_reach, worst_alpha_stderr
    from trimeter.forward.transport import Stack, k_max_for, trace_column
    from trimeter.forward.transport.sampling import mix64

    r = load_recipe(recipe_path)
    rng = np.random.default_rng(seed)
    stack = Stack.from_recipe(r.geometry, r.geometry_params, r.n, r.thickness_mm)
    k_max = k_max_for(float(r.alpha[-1]), r.sampling.truncation)
    s_lo, s_hi = float(r.sigma_t[0]), float(r.sigma_t[-1])
    sig = _off_grid(np.exp(rng.uniform(np.log(s_lo), np.log(s_hi), pairs)), r.sigma_t, rng, s_lo, s_hi, log=True)
    gs = _off_grid(rng.uniform(float(r.g[0]), float(r.g[-1]), pairs), r.g, rng, float(r.g[0]), float(r.g[-1]))
    rows = []
    t0 = time.perf_counter()
    for i, (s, g) in enumerate(zip(sig, gs, strict=True)):  # one trace per (σt, g): each is seconds of Dr.Jit work
        a_lo, a_hi = float(r.alpha[0]), float(r.alpha[-1])
        u = rng.uniform(0, 1, alphas)
        al = np.where(np.arange(alphas) % 2 == 0, a_lo + (a_hi - a_lo) * u, a_hi - (a_hi - a_lo) * u ** 2)
        al = _off_grid(al, r.alpha, rng, a_lo, a_hi)
        col_seed = int(rng.integers(1 << 31))
        tally = trace_column(stack, float(s), float(g), int(paths), col_seed, k_max,
                             polarisation=r.polarisation)  # the recipe's model, as its map traces it
        # top up (once) until α's std-error (g held) at these α meets --alpha-stderr: a reference
        # must be several times more precise than the target it checks, wherever it is thin
        if alpha_stderr is not None:
            short = worst_alpha_stderr(tally, al, r.reference_rho_b, r.reference_rho_w) / alpha_stderr
            more = paths_to_reach(tally.n_paths, short, int(max_paths or paths)) - tally.n_paths
            if short > 1 and more > 0:
                tally += trace_column(stack, float(s), float(g), int(more), mix64(col_seed), k_max,
                                      polarisation=r.polarisation)
        A, B, C = tally.abc(al)
        sb, sw = tally.stderr(al, r.reference_rho_b), tally.stderr(al, r.reference_rho_w)
        for j in range(alphas):
            rows.append((al[j], s, g, A[j], B[j], C[j], sb[j], sw[j]))
        print(f"\r{i + 1}/{pairs} (σt, g) traced, {time.perf_counter() - t0:.0f} s", end="", file=sys.stderr,
              flush=True)
    print(file=sys.stderr)
    budget = (f"{paths} paths per (sigma_t, g)" if alpha_stderr is None else
              f"{paths}-{max_paths} paths per (sigma_t, g) (α std-error ≤ {alpha_stderr:g} where reachable)")
    model = ", polarisation tracked" if r.polarisation else ""
    meta = {"recipe": r.to_dict(), "source": f"trimeter.forward.transport.trace_column, {budget}, off-grid{model}",
            "seed": seed, "seconds": round(time.perf_counter() - t0, 1)}
    return r.name, meta, np.array(rows)


def from_ideal(map_path, count, seed):
    from trimeter.forward.adding_doubling import IAD_QUAD_POINTS, ideal_abc
    from trimeter.formats.appearance import AppearanceMap

    m = AppearanceMap.load(map_path)
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 1, count)
    a_lo, a_hi = float(m.alpha[0]), float(m.alpha[-1])
    al = _off_grid(np.where(np.arange(count) % 2 == 0, a_lo + (a_hi - a_lo) * u, a_hi - (a_hi - a_lo) * u ** 2),
                   m.alpha, rng, a_lo, a_hi)
    sig = _off_grid(np.exp(rng.uniform(np.log(m.sigma_t[0]), np.log(m.sigma_t[-1]), count)), m.sigma_t, rng,
                    float(m.sigma_t[0]), float(m.sigma_t[-1]), log=True)
    gs = _off_grid(rng.uniform(m.g[0], m.g[-1], count), m.g, rng, float(m.g[0]), float(m.g[-1]))
    t0 = time.perf_counter()
    abc = ideal_abc(al, sig, gs, thickness_mm=m.thickness_mm, n=m.n)
    rows = np.column_stack([al, sig, gs, abc, np.zeros(count), np.zeros(count)])
    meta = {"recipe": m.recipe, "source": f"iadpython adding-doubling at {IAD_QUAD_POINTS} quadrature points (exact "
                                          "for the ideal geometry), off-grid",
            "seed": seed, "seconds": round(time.perf_counter() - t0, 1)}
    return m.name, meta, rows


def save(name, meta, rows, out=None) -> Path:
    from trimeter.formats.container import write_container

    out = Path(out) if out else HELDOUT_DIR / f"{name}.held"
    names = ("alpha", "sigma_t", "g", "A", "B", "C", "std_b", "std_w")
    write_container(out, HELDOUT_KIND, {**meta, "producer": "tools/make_heldout.py"},
                    {k: rows[:, i].astype(np.float64) for i, k in enumerate(names)})
    return out


def add_inscatter(path: Path, photons: int, seed: int) -> Path:
    """Trace the in-scattered light of every material of a device held-out set and store
    ln(1 + in-scattered / unscattered) as its array inscatter_log1p (the rest of the file unchanged)."""
    from trimeter.forward.transport.inscatter_tracer import traced_log1p_ratio
    from trimeter.formats.container import write_container

    meta, arrays = load_heldout(path)
    recipe = meta["recipe"]
    geometry, n, ell = recipe["geometry_params"], float(recipe["n"]), float(recipe["thickness_mm"])
    L = np.zeros(len(arrays["alpha"]))
    columns = np.unique(np.stack([arrays["sigma_t"], arrays["g"]], axis=1), axis=0)
    t0 = time.perf_counter()
    for j, (sigma_t, g) in enumerate(columns):
        rows = (arrays["sigma_t"] == sigma_t) & (arrays["g"] == g)
        L[rows] = traced_log1p_ratio(arrays["alpha"][rows], sigma_t, g, ell, n, geometry, photons, seed + j)
        print(f"\r{j + 1}/{len(columns)} (σt, g) columns traced", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    meta = {**meta, "inscatter": {"tracer": "trimeter.forward.transport.inscatter_tracer.traced_log1p_ratio",
                                  "photons": photons, "seed": seed, "seconds": round(time.perf_counter() - t0, 1)}}
    write_container(path, HELDOUT_KIND, meta, {**arrays, "inscatter_log1p": L})
    return path


def load_heldout(path) -> tuple[dict, dict]:
    """(meta, arrays) of a held-out set."""
    from trimeter.formats.container import read_container

    meta, arrays, _ = read_container(path, HELDOUT_KIND)
    return meta, {k: np.asarray(v) for k, v in arrays.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recipe", nargs="?", help="map recipe (.toml) for the tracer source")
    ap.add_argument("--ideal", type=Path, help="ideal map (.tmap): render with iadpython instead")
    # many columns, few α each: a column's materials share its MC error, so with few columns one or
    # two of them decide the p95
    ap.add_argument("--pairs", type=int, default=64, help="random (σt, g) columns traced (recipe source)")
    ap.add_argument("--alphas", type=int, default=5, help="random α per column (recipe source)")
    ap.add_argument("--paths", type=int, default=16777216, help="paths per column (recipe source)")
    # thin columns need far more paths than the rest for the same α precision (see the map recipes)
    ap.add_argument("--alpha-stderr", type=float, default=7e-4,
                    help="top a column up until α's MC std-error (g held) is this small (0: off)")
    ap.add_argument("--max-paths", type=int, default=1 << 27, help="cap per column for --alpha-stderr")
    ap.add_argument("--count", type=int, default=300)
    ap.add_argument("--seed", type=int, default=2027)
    ap.add_argument("-o", "--output", type=Path)
    ap.add_argument("--inscatter", type=Path, metavar="SET",
                    help="add the traced in-scattered light to an existing device set (.held), in place")
    ap.add_argument("--photons", type=int, default=200_000, help="photons per (σt, g) column for --inscatter")
    args = ap.parse_args(argv)
    if args.inscatter:
        out = add_inscatter(args.inscatter, args.photons, args.seed)
        print(f"{out}: in-scattered light added")
        return 0
    if args.ideal:
        name, meta, rows = from_ideal(args.ideal, args.count, args.seed)
    elif args.recipe:
        name, meta, rows = from_recipe(args.recipe, args.pairs, args.alphas, args.paths, args.seed,
                                       args.alpha_stderr or None, args.max_paths)
    else:
        ap.error("give a recipe or --ideal MAP")
    out = save(name, meta, rows, args.output)
    print(f"{out}: {len(rows)} held-out materials ({meta['source']}, {meta['seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
