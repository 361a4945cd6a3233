#!/usr/bin/env python3
"""Map builds on Dask, measured: a reduced device recipe built on local clusters of 1 and 2 workers, the
scheduler's overhead per task, and from those a projection for a larger cluster.

    .venv/bin/python tools/bench_distributed.py [--recipe maps/recipes/device-n1.5-l0.4.toml]
        [--sigma-t-every 5] [--g-every 3] [--workers 1,2] [--project 64] [--noop-tasks 400]

The reduced recipe keeps every n-th σt and g node of the recipe (thin and dense columns alike; the
other fields as they are), so its columns cost what the full map's cost. Printed per worker count: the
cluster's start-up, the build's wall time, the columns' own trace seconds (sum, max) and the overhead
(wall − Σ trace / workers). The projection for P workers and the full map (and a library of maps):
start-up + max(Σ trace / P, longest column) + tasks × scheduler overhead per task, with Σ trace scaled
from the measured mean per column to the full map's column count.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def reduced(recipe, sigma_every: int, g_every: int, flat_paths: int | None = None):
    from trimeter.maps.recipe import parse_recipe

    data = recipe.to_dict()
    data.pop("geometry_params")
    if flat_paths:   # every column the same paths: times per path, not per a column's adaptive top-ups
        data["sampling"] = {**data["sampling"], "min_paths": flat_paths, "max_paths": flat_paths}
        data["sampling"].pop("target_alpha_stderr", None)
    grid = data["grid"]
    grid["sigma_t"] = _every(grid["sigma_t"], sigma_every)
    grid["g"] = _every(grid["g"], g_every)
    data["name"] = f"{recipe.name}-reduced"
    return parse_recipe(data)


def _every(axis: list, n: int) -> list:
    picked = axis[::n]
    return picked if picked[-1] == axis[-1] else [*picked, axis[-1]]


def _noop(i: int) -> int:
    return i


def main(argv=None) -> int:
    from distributed import wait

    from trimeter.maps.builder import MapJob, build_maps
    from trimeter.maps.distributed import local_client
    from trimeter.maps.recipe import load_recipe

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recipe", default="maps/recipes/device-n1.5-l0.4.toml")
    ap.add_argument("--sigma-t-every", type=int, default=5)
    ap.add_argument("--g-every", type=int, default=3)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--project", type=int, default=64, help="workers of the projected cluster")
    ap.add_argument("--library", type=int, default=8, help="maps in the projected library build")
    ap.add_argument("--noop-tasks", type=int, default=400)
    ap.add_argument("--flat-paths", type=int, help="paths per column (default: the recipe's adaptive sampling); "
                                                   "the projection then scales by the shipped map's total paths")
    args = ap.parse_args(argv)
    full = load_recipe(args.recipe)
    recipe = reduced(full, args.sigma_t_every, args.g_every, args.flat_paths)
    full_columns = full.shape[1] * full.shape[2]
    columns = recipe.shape[1] * recipe.shape[2]
    print(f"reduced recipe: {recipe.name}, σt {list(np.round(recipe.sigma_t, 3))} × g {list(np.round(recipe.g, 3))}"
          f" = {columns} of the full map's {full_columns} columns")
    runs = {}
    for workers in (int(w) for w in args.workers.split(",")):
        t0 = time.perf_counter()
        with local_client(workers) as client, tempfile.TemporaryDirectory() as tmp:
            start_up = time.perf_counter() - t0
            client.run(lambda: __import__("trimeter.forward.transport"))   # imports outside the timing
            t1 = time.perf_counter()
            amap = build_maps([MapJob(recipe, Path(tmp) / "m.tmap")], client=client, progress=False,
                              keep_checkpoint=True)[0]
            wall = time.perf_counter() - t1
            seconds = _column_seconds(Path(tmp) / ".m.tmap.checkpoint")
            overhead = None
            if workers == max(int(w) for w in args.workers.split(",")):
                t2 = time.perf_counter()
                wait(client.map(_noop, range(args.noop_tasks), pure=False))
                overhead = (time.perf_counter() - t2) / args.noop_tasks
        runs[workers] = (start_up, wall, seconds, overhead)
        print(f"{workers} worker(s): start-up {start_up:.1f} s, build {wall:.1f} s wall; columns' trace time "
              f"Σ {seconds.sum():.1f} s, mean {seconds.mean():.1f} s, max {seconds.max():.1f} s; overhead "
              f"{wall - seconds.sum() / workers:.1f} s (wall − Σ/workers); paths "
              f"{amap.provenance['paths_per_column']['total'] / 1e6:.0f}M")
        if overhead is not None:
            print(f"  scheduler: {args.noop_tasks} no-op tasks, {1e3 * overhead:.2f} ms per task")
    one = min(runs)
    scale = full_columns / columns            # per-map time: the reduced recipe's, scaled by columns or paths
    shipped = Path(args.recipe).parent.parent / f"{full.name}.tmap"
    if args.flat_paths and shipped.is_file():
        from trimeter.maps.appearance import AppearanceMap

        total = AppearanceMap.load(shipped).provenance["paths_per_column"]["total"]
        scale = total / (columns * args.flat_paths)
        print(f"scaled by paths: the shipped {shipped.name} traced {total / 1e6:.0f}M paths, this run "
              f"{columns * args.flat_paths / 1e6:.0f}M (×{scale:.1f})")
    if len(runs) > 1:
        most = max(runs)
        print(f"speed-up {one} → {most} workers: {runs[one][1] / runs[most][1]:.2f}× "
              f"(per-map time, scaled: {runs[one][1] * scale:.0f} s → {runs[most][1] * scale:.0f} s)")
    start_up, _, seconds, _ = runs[max(runs)]
    overhead = next(r[3] for r in runs.values() if r[3] is not None)
    mean = float(np.sum(runs[one][2])) * scale / full_columns      # per column of the full map
    # the longest column: the measured one, or with flat paths one at the recipe's cap
    longest = float(np.max(runs[one][2])) * (full.sampling.max_paths / args.flat_paths if args.flat_paths else 1)
    P = args.project
    for maps in (1, args.library):
        tasks = maps * full_columns
        busy = max(tasks * mean / P, longest)
        total = start_up + busy + tasks * overhead
        print(f"projection, {P} workers, {maps} map(s) = {tasks} columns: {total:.0f} s ≈ start-up {start_up:.0f} s "
              f"+ max(Σ {tasks * mean:.0f} s / {P}, longest column {longest:.0f} s) + {tasks} × "
              f"{1e3 * overhead:.1f} ms (per-column time from the {one}-worker run)")
    return 0


def _column_seconds(checkpoint: Path) -> np.ndarray:
    out = []
    for path in sorted(checkpoint.glob("col_*.npz")):
        with np.load(path) as z:
            out.append(float(z["seconds"]))
    return np.array(out)


if __name__ == "__main__":
    sys.exit(main())
