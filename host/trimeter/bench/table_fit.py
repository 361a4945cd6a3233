"""`trimeter bench table-fit`: the fit from a device table (.tlut v2) alone, in C (native.TableFitter:
the source the firmware links as tr_fit_bins, here in double precision), on its map's held-out set
(maps/heldout, as `bench fit` scores them): α p95, σt relative p95 and g p95 (α ≥ 0.5) against the
targets, and the time per 1024 bins beside the map's own lut fit (its refined grid, in C) in the same
run, timed round-robin, best of --repeats. Run it on one core for the per-core figure:
`taskset -c 1 trimeter bench table-fit --table FILE`. The first row is what `trimeter fit --table`
runs; a second row: the same table's forward model sampled onto the refined grid at load
(trimeter.inversion.table_model.DeviceTableModel, `fit --table --refine`).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError

# the targets for a fit from the table alone (noise-free rendered held-out references)
TARGETS = {"alpha_p95": 0.01, "sigma_rel_p95": 0.01, "g_p95": 0.015}


def register(bench_subparsers: argparse._SubParsersAction) -> None:
    p = bench_subparsers.add_parser("table-fit", help="the C fit from a device table alone: accuracy and speed",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--table", type=Path, required=True, help="a .tlut v2 file (tools/device_table_study.py build)")
    p.add_argument("--map", help="its map (default: the map the table names)")
    p.add_argument("--repeats", type=int, default=7, help="timed runs per variant (best kept; default 7)")
    p.add_argument("--library", type=Path, help="another build of the kernel to fit the table with (e.g. one compiled "
                                                "with -DTR_SINGLE: the MCU's single precision); default: the package's")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.repeats < 1:
        raise InputError(f"--repeats must be at least 1, not {args.repeats}")
    if args.library is not None and not args.library.is_file():
        raise InputError(f"--library: no such file: {args.library}")
    report = measure(args.table, args.map, args.repeats, args.library)
    print(f"{report['map']}: {report['materials']} held-out materials, noise-free rendered references; table "
          f"{report['table_bytes']} B; kernel: {report['kernel']}; cores {report['cores']}")
    header = "".join(f"{k:>15s}" for k in TARGETS) + f"{'targets':>9s}{'ms/1024':>10s}{'× base':>8s}"
    print(f"{'variant':40s}{header}")
    for row in report["rows"]:
        print(f"{row['variant']:40s}" + "".join(f"{row[k]:15.4g}" for k in TARGETS)
              + f"{'met' if row['targets_met'] else 'MISSED':>9s}{row['ms_per_1024']:10.3f}{row['x_baseline']:8.2f}")
    print("targets: " + ", ".join(f"{k} ≤ {v}" for k, v in TARGETS.items()))
    return 0


BASELINE = "map lut, refined grid, C (baseline)"


def measure(table_path: Path, map_name: str | None = None, repeats: int = 7,
            library: Path | None = None) -> dict[str, Any]:
    """The table's fits on its map's held-out set, scored (bench fit's figures: alpha_p95, sigma_rel_p95,
    g_p95, …) and timed per 1024 bins, best of `repeats` round-robin beside the map's own lut fit
    (`x_baseline`: time over the baseline's in this run). `library`: another build of the kernel for the
    table fit (e.g. single precision); the variant's name says which."""
    import trimeter
    from trimeter.bench.fit_scoring import error_budget, error_figures
    from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities
    from trimeter.inversion import api, native
    from trimeter.formats.appearance import AppearanceMap, find_map
    from trimeter.formats.container import read_bounded
    from trimeter.formats.device_table import MAX_BYTES, DeviceTable
    from trimeter.inversion.table_model import DeviceTableModel

    data = read_bounded(table_path, MAX_BYTES, "map table")
    table = DeviceTable.from_bytes(data, source=str(table_path))
    amap = AppearanceMap.load(find_map(map_name or table.name))
    if table.parent_sha256 != amap.checksum:
        raise InputError(f"{table_path} was built from another map than {amap.name} as it is now (parent SHA-256 "
                         f"{table.parent_sha256[:12]}…, the map's {str(amap.checksum)[:12]}…): rebuild it")
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    I_b, I_w = heldout_intensities(h, rb, rw)
    I_c = heldout_collimated(amap, h)
    truth = (h["alpha"], h["sigma_t"], h["g"])
    budget = error_budget(amap, h, rb, rw)
    fitter = native.TableFitter(data, library=library)

    def table_fit(ib: np.ndarray, iw: np.ndarray, ic: np.ndarray) -> SimpleNamespace:
        alpha, sigma_t, g, flags = fitter.fit(ib, iw, ic)
        return SimpleNamespace(alpha=alpha, sigma_t=sigma_t, g=g, flags=flags, alpha_std=np.full_like(alpha, np.nan))

    def map_fit(ib: np.ndarray, iw: np.ndarray, ic: np.ndarray) -> FitResult:
        return trimeter.fit(amap, ib, iw, ic, method="lut")

    refined_model = DeviceTableModel(table)

    def refined_fit(ib: np.ndarray, iw: np.ndarray, ic: np.ndarray) -> FitResult:
        return api.fit(refined_model, ib, iw, ic, method="lut")

    precision = "double" if library is None else library.name
    variants: dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], FitResult | SimpleNamespace]] = {
        f"table alone, C, {precision}": table_fit, "table alone, refined at load (--refine)": refined_fit,
        BASELINE: map_fit}
    tile = np.resize(np.arange(len(I_b)), 1024)
    tiled = (I_b[tile], I_w[tile], I_c[tile])
    best = dict.fromkeys(variants, np.inf)
    for fn in variants.values():
        fn(*tiled)  # warm: first calls load and prepare
    for _ in range(repeats):  # round-robin: a slow moment of the machine hits both alike
        for name, fn in variants.items():
            t0 = time.perf_counter()
            fn(*tiled)
            best[name] = min(best[name], time.perf_counter() - t0)
    rows = []
    for name, fn in variants.items():
        st = error_figures(fn(I_b, I_w, I_c), truth, budget)
        rows.append({"variant": name, **st, "targets_met": all(st[k] <= v for k, v in TARGETS.items()),
                     "ms_per_1024": best[name] * 1e3, "x_baseline": best[name] / best[BASELINE]})
    return {"map": amap.name, "table": str(table_path), "table_bytes": table.size_bytes, "materials": len(I_b),
            "kernel": native.status(), "cores": sorted(os.sched_getaffinity(0)), "repeats": repeats, "rows": rows}
