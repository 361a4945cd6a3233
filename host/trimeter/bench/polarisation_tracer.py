"""`trimeter bench polarisation-tracer`: the map tracer's `polarisation` option (s and p tracked at the
interfaces, trimeter.forward.transport.walk.Walk) against what it should give, and what it costs.

- The clear lossless slab of `trimeter bench polarisation` (ideal geometry, over ρ 0.5, α = 0): R_d from the
  traced I, with the option off and on, against the closed forms per treatment of Fresnel; factorised (the
  walk alone) and unfactorised (the next-event estimate and the control variates' expectations too).
- The bench's clear and thin materials: the shift of I polarised − unpolarised, traced with the same paths
  on and off (in batches, for its own std-error), against the renders' shift d − u (Mitsuba's polarised
  variant with the depolarising phase function, the tracer's model, − its unpolarised one) and p − u from
  maps/polarisation.json.
- The cost: one device column traced off and on, alternately, after both kernels are compiled; the ratio
  of the medians (and of the fastest), measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.bench import write_figures
from trimeter.errors import InputError

TRACED = ("clear", "thin")          # the bench's materials whose shifts are beyond the maps' error
COST_COLUMNS = ((0.2, 0.0), (20.0, 0.9))   # (σt, g): a clear and a dense device column
DEFAULT_PATHS, DEFAULT_BATCHES, DEFAULT_COST_PATHS, DEFAULT_SEED = 1 << 20, 4, 1 << 21, 13


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("polarisation-tracer", help="the tracer's polarisation option against closed "
                                                                "forms and the polarised renders, and its cost",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--geometry", choices=("ideal", "device", "both"), default="both")
    p.add_argument("--paths", type=int, default=DEFAULT_PATHS,
                   help=f"paths per trace (default {DEFAULT_PATHS}; the slab check: 4× as many)")
    p.add_argument("--batches", type=int, default=DEFAULT_BATCHES,
                   help=f"paired traces per material (default {DEFAULT_BATCHES})")
    p.add_argument("--series-orders", type=int, default=0,
                   help="device: trace a bounce series to this many background orders (C matched at the white) "
                        "instead of the maps' single C (default 0: the maps')")
    p.add_argument("--cost-paths", type=int, default=DEFAULT_COST_PATHS,
                   help=f"paths per timed device column (default {DEFAULT_COST_PATHS}; 0: not timed)")
    p.add_argument("--cost-repeats", type=int, default=5)
    p.add_argument("--renders", type=Path, default=None,
                   help="the polarisation bench's JSON to compare with (default maps/polarisation.json)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED)
    p.add_argument("--out", type=Path, default=Path("out/bench-polarisation-tracer/results.json"))
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report = measure(args)
    _print(report)
    write_figures(report, args.out)
    return 0


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """{"slab": the clear-slab check, "geometries": per geometry the materials' shifts, "cost": the timings}."""
    from trimeter.paths import MAPS_DIR, REPO_ROOT

    if args.paths < 4096:
        raise InputError("--paths must be ≥ 4096")
    if args.batches < 2:
        raise InputError("--batches must be ≥ 2 (their spread is the shift's std-error)")
    if args.series_orders and args.series_orders < 3:
        raise InputError("--series-orders must be 0 (the maps' single C) or ≥ 3")
    if args.cost_paths and (args.cost_paths < 4096 or args.cost_repeats < 1):
        raise InputError("--cost-paths must be 0 (not timed) or ≥ 4096, with --cost-repeats ≥ 1")
    renders_path = args.renders or MAPS_DIR / "polarisation.json"
    try:
        renders = json.loads(Path(renders_path).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"--renders {renders_path}: cannot read the polarisation bench's JSON ({exc})") from None
    geometries = ("ideal", "device") if args.geometry == "both" else (args.geometry,)
    shown = Path(renders_path).resolve()
    shown = shown.relative_to(REPO_ROOT) if shown.is_relative_to(REPO_ROOT) else shown
    report: dict[str, Any] = {"paths": args.paths, "batches": args.batches, "seed": args.seed,
                              "series_orders": args.series_orders, "renders": str(shown),
                              "render_spp": renders.get("spp"), "slab": slab_check(4 * args.paths, args.seed),
                              "geometries": [shifts(geometry, renders, args.paths, args.batches, args.seed,
                                                    args.series_orders) for geometry in geometries],
                              "cost": cost(args.cost_paths, args.cost_repeats, args.seed) if args.cost_paths else None}
    return report


def _map_stack(geometry: str):
    from trimeter.bench.polarisation import MAPS
    from trimeter.formats.appearance import AppearanceMap, find_map
    from trimeter.forward.transport import Stack

    amap = AppearanceMap.load(find_map(MAPS[geometry]))
    return amap, Stack.from_recipe(geometry, amap.recipe["geometry_params"], amap.n, amap.thickness_mm)


def slab_check(n_paths: int, seed: int) -> dict[str, Any]:
    """R_d of the clear lossless slab from the traced I (α = 0, σt 1e-6/mm) per option and estimator."""
    from trimeter.bench.polarisation import (SLAB_N, SLAB_RHO, SLAB_THICKNESS_MM, slab_diffuse_from,
                                             slab_diffuse_reflectance)
    from trimeter.forward.transport import Stack, trace_column
    from trimeter.geometry import load_geometry

    stack = Stack.from_recipe("ideal", load_geometry("ideal"), SLAB_N, SLAB_THICKNESS_MM)
    closed = dict(zip(("unpolarised", "polarised"), slab_diffuse_reflectance(SLAB_N), strict=True))
    alpha = np.array([0.0])
    out: dict[str, Any] = {"paths": n_paths, "closed_form": closed, "traced": []}
    for factorise in (True, False):
        for key in closed:
            tally = trace_column(stack, 1e-6, 0.0, n_paths, seed, 4, factorise=factorise,
                                 polarisation=key == "polarised", below_fraction=1.0)
            A, B, C = tally.abc(alpha)
            I = A + B * SLAB_RHO / (1 - C * SLAB_RHO)
            se = tally.stderr(alpha, SLAB_RHO)
            R_d = float(slab_diffuse_from(I, SLAB_RHO, SLAB_N)[0])
            R_d_se = abs(float(slab_diffuse_from(I + se, SLAB_RHO, SLAB_N)[0]) - R_d)
            out["traced"].append({"factorised": factorise, "treatment": key, "R_d": R_d, "stderr": R_d_se,
                                  "z": (R_d - closed[key]) / R_d_se})
    return out


def shifts(geometry: str, renders: dict, n_paths: int, batches: int, seed: int, series_orders: int) -> dict[str, Any]:
    """Per TRACED material and reference background: the traced I (off), the traced shift on − off with its
    std-error over `batches` paired traces, and the renders' shifts."""
    from trimeter.bench.polarisation import MATERIALS
    from trimeter.forward.transport import N_BACKGROUND_ORDERS, k_max_for, trace_column

    amap, stack = _map_stack(geometry)
    rendered = {(r["material"], r["background"]): r for g in renders.get("geometries", ())
                if g["geometry"] == geometry for r in g["rows"]}
    series = bool(series_orders) and geometry == "device"
    orders = series_orders if series else N_BACKGROUND_ORDERS
    rows = []
    for label, a, s, g in MATERIALS:
        if label not in TRACED:
            continue
        alpha = np.array([a])
        I: dict[bool, list[list[float]]] = {False: [], True: []}
        for batch in range(batches):
            for polarisation in (False, True):
                tally = trace_column(stack, s, g, n_paths, seed + batch, k_max_for(a, 1e-9), polarisation=polarisation,
                                     background_orders=orders)
                if series:
                    I[polarisation].append([float(tally.bounce_series(alpha, rho)[0][0])
                                            for rho in amap.reference_rhos])
                else:
                    A, B, C = tally.abc(alpha)
                    I[polarisation].append([float((A + B * rho / (1 - C * rho))[0]) for rho in amap.reference_rhos])
        off, on = np.array(I[False]), np.array(I[True])
        for j, background in enumerate(("black", "white")):
            d = on[:, j] - off[:, j]
            row: dict[str, Any] = {"material": label, "background": background, "rho": amap.reference_rhos[j],
                                   "I": float(off[:, j].mean()), "shift": float(d.mean()),
                                   "stderr_shift": float(d.std(ddof=1) / math.sqrt(batches))}
            r = rendered.get((label, background))
            if r is not None:
                row.update(render_I=r["I_unpolarised"], render_d=r["delta_depolarising"],
                           render_d_stderr=r["stderr_delta_depolarising"], render_p=r["delta"],
                           render_p_stderr=r["stderr_delta"])
                row["z"] = (row["shift"] - row["render_d"]) / math.hypot(row["stderr_shift"], row["render_d_stderr"])
            rows.append(row)
    return {"geometry": geometry, "map": amap.name, "orders": orders, "rows": rows}


def cost(n_paths: int, repeats: int, seed: int) -> dict[str, Any]:
    """Seconds per device column (COST_COLUMNS) traced off and on, alternately, both kernels compiled first."""
    from trimeter.forward.transport import k_max_for, trace_column

    _, stack = _map_stack("device")
    k_max = k_max_for(0.999, 1e-5)
    columns = []
    for sigma_t, g in COST_COLUMNS:
        for polarisation in (False, True):
            trace_column(stack, sigma_t, g, 4096, seed, k_max, polarisation=polarisation)
        seconds: dict[bool, list[float]] = {False: [], True: []}
        for r in range(repeats):
            for polarisation in ((False, True) if r % 2 == 0 else (True, False)):
                t0 = time.perf_counter()
                trace_column(stack, sigma_t, g, n_paths, seed, k_max, polarisation=polarisation)
                seconds[polarisation].append(time.perf_counter() - t0)
        off, on = seconds[False], seconds[True]
        columns.append({"sigma_t": sigma_t, "g": g, "off": off, "on": on,
                        "median_ratio": float(np.median(on) / np.median(off)), "fastest_ratio": min(on) / min(off)})
    return {"paths": n_paths, "repeats": repeats, "columns": columns}


def _print(report: dict[str, Any]) -> None:
    slab = report["slab"]
    closed = slab["closed_form"]
    print(f"clear lossless slab (ideal, over ρ 0.5, α 0, {slab['paths']} paths): R_d from the traced I; closed forms "
          f"{closed['unpolarised']:.4f} unpolarised, {closed['polarised']:.4f} polarised")
    for t in slab["traced"]:
        kind = "factorised  " if t["factorised"] else "unfactorised"
        print(f"   {kind} option {'on ' if t['treatment'] == 'polarised' else 'off'}  R_d {t['R_d']:.4f} ± "
              f"{t['stderr']:.4f}  ({t['z']:+.1f}σ from the {t['treatment']} closed form)")
    print(f"\nshift of I, option on − off (same paths, {report['batches']} batches of {report['paths']}), against the "
          f"renders' d − u and p − u ({report['renders']}, {report['render_spp']} samples per render)")
    for geo in report["geometries"]:
        series = f", bounce series to {geo['orders']} orders" if geo["orders"] > 2 else ""
        print(f"{geo['geometry']} ({geo['map']}{series})")
        for r in geo["rows"]:
            line = (f"   {r['material']:<6}{r['background']:<6} I {r['I']:.5f}  traced {r['shift']:+.5f} ± "
                    f"{r['stderr_shift']:.5f}")
            if "render_d" in r:
                line += (f"   render d − u {r['render_d']:+.5f} ± {r['render_d_stderr']:.5f}, p − u "
                         f"{r['render_p']:+.5f}  (z {r['z']:+.1f})")
            print(line)
    if report["cost"]:
        c = report["cost"]
        print(f"\ncost: device columns of {c['paths']} paths, off and on alternately, {c['repeats']} each")
        for col in c["columns"]:
            print(f"   σt {col['sigma_t']}/mm g {col['g']}: off {np.median(col['off']):.2f} s, on "
                  f"{np.median(col['on']):.2f} s (medians): on/off {col['median_ratio']:.3f} (fastest "
                  f"{col['fastest_ratio']:.3f})")
