"""`trimeter bench tracer-check`: the map tracer against Mitsuba's volpath over many random materials.

Per geometry (ideal ℓ = 0.5 mm; device, half the materials at ℓ = 0.4 mm and half at 0.8 mm), seeded
random materials over the maps' range (trimeter.forward.validate.random_materials: half of them with
α near 1), both reference backgrounds (ρ = 0.02, 0.9). Each material: one tracer column at `--paths`
detector paths and volpath per ρ at `--spp` samples (std-errors of the same order), extrapolated to no
ray offset with a second render at a quarter of them (trimeter.forward.render.render_diffuse_offset_free:
Mitsuba's ray offsets make dense samples dark), then z = (tracer − volpath) / combined
std-error. Judged by the distribution (trimeter.forward.validate: p95 |z| ≤ 2.5 and |mean z| ≤ 0.5 per
geometry); the ideal geometry also against adding-doubling.
Exit status 1 when a geometry misses. Rows and summaries also go to `--out` (JSON).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from trimeter.errors import InputError

DEVICE_THICKNESSES = (0.4, 0.8)
IDEAL_THICKNESS = 0.5


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("tracer-check", help="the map tracer against Mitsuba volpath: z-scores over random "
                                                   "materials, both geometries and backgrounds")
    p.add_argument("--materials", type=int, default=40, help="random materials per geometry (default 40)")
    p.add_argument("--paths", type=int, default=1 << 21, help="tracer detector paths per material")
    p.add_argument("--spp", type=int, default=1 << 19, help="volpath samples per render")
    p.add_argument("--geometry", choices=("ideal", "device", "both"), default="both")
    p.add_argument("--seed", type=int, default=2027)
    p.add_argument("--backend", default="auto", help="tracer backend: llvm, cuda or auto (default)")
    p.add_argument("--series-orders", type=int, default=None, metavar="N",
                   help="device: judge the tracer's own bounce series to N (3…16) background orders instead of "
                        "the map model A + Bρ/(1 − Cρ) (a comparison; the shipped maps use the model)")
    p.add_argument("--out", default="out/bench-tracer-check/results.json", help="JSON report")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report = check(args)
    _print_summary(report)
    out = Path(args.out)
    from trimeter.atomic import atomic_write

    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, json.dumps(report, indent=1).encode())
    print(f"report: {out}")
    print(f"tracer check: {'ok' if report['ok'] else 'MISSED'}")
    return 0 if report["ok"] else 1


def check(args: argparse.Namespace) -> dict[str, Any]:
    """Trace and render every material (printing each row as it comes) and judge the z-scores: {"settings",
    "seconds", "rows", "summary" (per geometry, per geometry and ρ, ideal against adding-doubling), "ok"}."""
    from trimeter.forward.validate import random_materials
    from trimeter.forward.transport.agreement import require_series_orders, tracer_agreement
    from trimeter.forward.transport import resolve_backend

    if not 1 <= args.materials <= 10_000:
        raise InputError(f"--materials must be 1…10000, got {args.materials}")
    if args.paths < 4096 or args.spp < 1024:
        raise InputError("--paths must be ≥ 4096 and --spp ≥ 1024")
    backend = resolve_backend(args.backend)
    geometries = ("ideal", "device") if args.geometry == "both" else (args.geometry,)
    for geometry in geometries:                 # before any work is printed
        require_series_orders(geometry, args.series_orders)
    print(f"tracer ({backend}, {args.paths} paths per material) vs volpath ({args.spp} spp per render), "
          f"{args.materials} materials per geometry, ρ = 0.02 and 0.9, seed {args.seed}"
          + (f"; tracer values from its bounce series to {args.series_orders} background orders"
             if args.series_orders else ""))
    rows: list[dict] = []
    start = time.perf_counter()
    for gi, geometry in enumerate(geometries):
        materials = random_materials(args.materials, args.seed + gi)
        if geometry == "ideal":
            parts = [(IDEAL_THICKNESS, materials, args.seed)]
        else:
            half = (len(materials) + 1) // 2
            parts = [(DEVICE_THICKNESSES[0], materials[:half], args.seed),
                     (DEVICE_THICKNESSES[1], materials[half:], args.seed + half)]
        for ell, subset, seed in parts:
            for i, material in enumerate(subset):   # one at a time, so the rows print as they come
                part = tracer_agreement(geometry, [material], 1.5, ell, paths=args.paths, spp=args.spp,
                                        seed=seed + i, backend=backend, series_orders=args.series_orders)
                rows += part
                _print_rows(part, geometry, ell)
    summary, ok = summarise(rows, geometries)
    return {"settings": {k: getattr(args, k) for k in ("materials", "paths", "spp", "seed", "series_orders")}
            | {"backend": backend}, "seconds": round(time.perf_counter() - start, 1), "summary": summary,
            "rows": rows, "ok": ok}


def _print_rows(part: list[dict], geometry: str, ell: float) -> None:
    for r in part:
        extra = f"  iad {r['iad']:.5f} z_iad {r['z_iad']:+.2f}" if "iad" in r else ""
        print(f"  {geometry} ℓ={ell:g} α={r['alpha']:.4f} σt={r['sigma_t']:7.3f} g={r['g']:.2f} "
              f"ρ={r['rho']:.2f}: tracer {r['tracer']:.5f}±{r['tracer_stderr']:.5f} volpath "
              f"{r['volpath']:.5f}±{r['volpath_stderr']:.5f} z {r['z']:+.2f}{extra}", flush=True)


def summarise(rows: list[dict], geometries: tuple[str, ...]) -> tuple[dict[str, dict], bool]:
    """z summaries per geometry, per geometry and background, and of the ideal geometry against
    adding-doubling; ok when every geometry (and adding-doubling, where there is one) meets the goal."""
    from trimeter.forward.transport.agreement import z_summary

    summary: dict[str, dict] = {}
    ok = True
    groups = [(g, None) for g in geometries] + [(g, rho) for g in geometries for rho in (0.02, 0.9)]
    for geometry, rho in groups:
        z = [r["z"] for r in rows if r["geometry"] == geometry and (rho is None or r["rho"] == rho)]
        key = geometry if rho is None else f"{geometry} ρ={rho:g}"
        summary[key] = z_summary(z)
        if rho is None:
            ok &= summary[key]["ok"]
    iad = [r["z_iad"] for r in rows if "z_iad" in r]
    if iad:
        summary[IAD_KEY] = z_summary(iad)
        ok &= summary[IAD_KEY]["ok"]
    return summary, bool(ok)


IAD_KEY = "ideal vs adding-doubling"


def _print_summary(report: dict[str, Any]) -> None:
    from trimeter.forward.transport.agreement import Z_MEAN_MAX, Z_P95_MAX

    print(f"{report['seconds']:.0f} s; z = (tracer − volpath) / combined std-error; targets p95 |z| ≤ {Z_P95_MAX}, "
          f"|mean z| ≤ {Z_MEAN_MAX}")
    for key, s in report["summary"].items():
        if key == IAD_KEY:
            print(f"{key} n={s['count']:3d}  mean z {s['mean']:+.2f}  p95 |z| {s['p95_abs']:.2f}  "
                  f"max |z| {s['max_abs']:.2f}  {'ok' if s['ok'] else 'MISSED'}")
            continue
        per_rho = "ρ=" in key
        print(f"{key:15s} n={s['count']:3d}  mean z {s['mean']:+.2f} (±{s['mean_stderr']:.2f})  std {s['std']:.2f}  "
              f"p95 |z| {s['p95_abs']:.2f}  max |z| {s['max_abs']:.2f}" + ("" if per_rho else
                                                                          f"  {'ok' if s['ok'] else 'MISSED'}"))
