"""`trimeter map build | inscatter | list | info | query` — appearance maps and their children (trimeter.maps)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.errors import InputError, MapFileError
from trimeter.formats.stages import DEFAULT_STAGES, STAGES, parse_stages
from trimeter.validation import require_material, require_reflectance


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "build", help="build maps from recipes and their children: .tmap → .tins → .tlut → .onnx",
        description="Build appearance maps from recipes (maps/recipes/*.toml), every (σt, g) column of every "
                    "map a task on a Dask cluster (a local one by default), then each map's children. "
                    "See maps/README.md.")
    p.add_argument("recipe", nargs="+", help="recipe TOML file(s); several build a library on one cluster")
    p.add_argument("--out", help="output map file, one recipe only (default: <out-dir>/<recipe name>.tmap)")
    p.add_argument("--out-dir", help="directory for the maps of several recipes (default: the current one)")
    p.add_argument("--stages", default=",".join(DEFAULT_STAGES),
                   help=f"comma-separated stages of {', '.join(STAGES)} (default: {','.join(DEFAULT_STAGES)}; "
                        "onnx trains for minutes, so it is opt-in); without tmap the maps must exist")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="local Dask cluster of N worker processes, one core each "
                                                   f"(default: this machine's {os.cpu_count()} cores)")
    where.add_argument("--scheduler", metavar="ADDRESS", help="run on an existing Dask cluster (tcp://host:8786)")
    p.add_argument("--connect-timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long to wait for the --scheduler to answer (default 10)")
    p.add_argument("--retries", type=int, default=2, help="runs of a failed column (worker killed, out of memory, "
                                                          "error) beyond the first before the build stops "
                                                          "(default 2)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted build from its checkpoint")
    p.add_argument("--checkpoint", help="checkpoint directory, one recipe only (default: .<out name>.checkpoint "
                                        "next to the output)")
    p.add_argument("--keep-checkpoint", action="store_true", help="keep the checkpoint after a successful build")
    p.add_argument("--inscatter-photons", type=int, default=30_000, help="tins: photons per (σt, g) column")
    p.add_argument("--backend", default="llvm",
                   help="tracer backend: llvm (CPU, the default: what the shipped maps were traced on), cuda "
                        "(a GPU; an error without one) or auto (cuda if there is a GPU, else llvm); checked on "
                        "this machine, so a --scheduler cluster's workers must have it too")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_build)

    p = subparsers.add_parser("inscatter", help="trace a device map's in-scattering table (<map>.tins, next to it); "
                                                "the same as `map build RECIPE --stages tins`")
    p.add_argument("map", help="map file or shipped map name (device geometry)")
    p.add_argument("--photons", type=int, default=30_000, help="photons per (σt, g) column (default 30000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="output file (default: the map's path with suffix .tins)")
    p.set_defaults(func=cmd_inscatter)

    p = subparsers.add_parser("list", help="the appearance maps shipped in maps/")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_list)

    p = subparsers.add_parser("info", help="describe an appearance map (recipe, grid, MC error, provenance) or a "
                                           "device table (.tlut)")
    p.add_argument("map", help="map file, shipped map name or device table file (.tlut)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = subparsers.add_parser("query", help="interpolate (I_b, I_w, I_c) for one material from a map")
    p.add_argument("map", help="map file or shipped map name")
    p.add_argument("--alpha", required=True)
    p.add_argument("--sigma-t", required=True, help="extinction [1/mm]")
    p.add_argument("--g", required=True)
    p.add_argument("--rho-b", required=True, help="black background reflectance")
    p.add_argument("--rho-w", required=True, help="white background reflectance")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_query)


def load_appearance_map(name_or_path):
    """Load a map, with a clear message when the file is some other trimeter file (e.g. a map table)."""
    from trimeter.formats.appearance import MAP_KIND, AppearanceMap, find_map

    path = find_map(name_or_path)
    try:
        return AppearanceMap.load(path)
    except MapFileError as exc:
        if "expected a" in str(exc) and MAP_KIND in str(exc):
            raise MapFileError(f"{path} is not an appearance map ({exc})") from None
        raise


def cmd_build(args) -> int:
    from trimeter.maps import pipeline
    from trimeter.maps.recipe import load_recipe
    from trimeter.forward.transport import resolve_backend

    stages = parse_stages(args.stages)
    backend = resolve_backend(args.backend)
    if len(args.recipe) > 1 and (args.out or args.checkpoint):
        raise InputError("--out and --checkpoint name one map's files: with several recipes use --out-dir")
    if args.retries is not None and not 0 <= args.retries <= 100:
        raise InputError(f"--retries must be 0…100, got {args.retries}")
    if args.workers is not None and not 1 <= args.workers <= 1024:
        raise InputError(f"--workers must be 1…1024, got {args.workers}")
    if not 0.1 <= args.connect_timeout <= 600:
        raise InputError(f"--connect-timeout must be 0.1…600 s, got {args.connect_timeout:g}")
    if args.inscatter_photons < 1000:
        raise InputError("--inscatter-photons: at least 1000")
    out_dir = Path(args.out_dir) if args.out_dir else Path(".")
    targets = []
    for path in args.recipe:
        recipe = load_recipe(path)
        out = Path(args.out) if args.out else out_dir / f"{recipe.name}.tmap"
        targets.append(pipeline.Target(recipe, Path(path), out))
    for t in targets:
        na, ns, ng = t.recipe.shape
        print(f"{t.recipe.name}: {t.recipe.geometry}, n = {t.recipe.n:g}, ℓ = {t.recipe.thickness_mm:g} mm, "
              f"grid α×σt×g = {na}×{ns}×{ng} ({ns * ng} columns) → {t.out} [{','.join(stages)}]")
    if "tmap" in stages:
        print(f"tracer backend: {backend}")
    options = pipeline.Options(tracer_backend=backend, inscatter_photons=args.inscatter_photons)
    run = dict(resume=args.resume, progress=not args.quiet, keep_checkpoint=args.keep_checkpoint,
               checkpoint_dir=Path(args.checkpoint) if args.checkpoint else None, retries=args.retries,
               options=options)
    if "tmap" not in stages and not any(s in ("tins", "onnx") for s in stages):
        pipeline.run(targets, stages, **run)         # a table or two: not worth starting a cluster
        return 0
    from trimeter.maps.distributed import local_client, remote_client

    cluster = (remote_client(args.scheduler, args.connect_timeout) if args.scheduler else
               local_client(args.workers, args.retries))
    with cluster as client:
        pipeline.run(targets, stages, client=client, **run)
    return 0


def cmd_inscatter(args) -> int:
    from trimeter.maps.pipeline import Options, make_child

    amap = load_appearance_map(args.map)
    if args.photons < 1000:
        raise InputError("--photons: at least 1000")
    make_child("tins", amap, Options(inscatter_photons=args.photons, inscatter_seed=args.seed),
               out=Path(args.out) if args.out else None)
    return 0


def _describe(amap) -> dict:
    info = amap.info()
    if amap.path is not None:
        info["size_bytes"] = amap.path.stat().st_size
    table = amap.inscatter
    info["inscatter"] = None if table is None else {
        "path": str(amap.path.with_suffix(".tins")), "sha256": table.checksum, "grid": list(table.L.shape),
        "tau_max": table.tau_max, "max_log1p_ratio": float(table.L.max()), "provenance": table.provenance}
    return info


def cmd_list(args) -> int:
    from trimeter.formats.appearance import shipped_maps

    rows: list[dict[str, Any]] = []
    for path in shipped_maps():
        try:
            info = _describe(load_appearance_map(path))
        except MapFileError as exc:
            rows.append({"name": path.stem, "error": str(exc)})
            continue
        rows.append(info)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    if not rows:
        print("no shipped maps (maps/*.tmap)")
    for info in rows:
        if "error" in info:
            print(f"{info['name']:<24} UNREADABLE: {info['error']}")
            continue
        r, gr = info["recipe"], info["grid"]
        print(f"{info['name']:<24} {r['geometry']:<7} n={r['n']:<5g} ℓ={r['thickness_mm']:g} mm  "
              f"{gr['alpha']}×{gr['sigma_t']}×{gr['g']}  σt "
              f"{info['range']['sigma_t'][0]:g}…{info['range']['sigma_t'][1]:g}/mm  "
              f"stderr med {info['mc_stderr']['median']:.1e}  {info['size_bytes'] / 1e6:.2f} MB")
    return 0


def cmd_info(args) -> int:
    from trimeter.maps.recipe import fresnel_model

    if str(args.map).endswith(".tlut"):
        return _table_info(args)
    info = _describe(load_appearance_map(args.map))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    r, gr, rg, p = info["recipe"], info["grid"], info["range"], info["provenance"]
    lines = [
        f"name        {info['name']}   ({info['path']}, {info.get('size_bytes', 0) / 1e6:.2f} MB)",
        f"sha256      {info['checksum_sha256']}",
        f"geometry    {r['geometry']}, n = {r['n']:g}, thickness = {r['thickness_mm']:g} mm, "
        f"reference ρ_b = {r.get('reference_rho_b')}, ρ_w = {r.get('reference_rho_w')}",
        f"Fresnel     {fresnel_model(r.get('polarisation', False))}",
        f"grid        α {gr['alpha']} ({rg['alpha'][0]:g}…{rg['alpha'][1]:g}), σt {gr['sigma_t']} "
        f"({rg['sigma_t'][0]:g}…{rg['sigma_t'][1]:g} 1/mm), g {gr['g']} ({rg['g'][0]:g}…{rg['g'][1]:g}); "
        f"{gr['points']} points",
        f"MC stderr   median {info['mc_stderr']['median']:.2e}, max {info['mc_stderr']['max']:.2e}",
    ]
    for key in ("builder", "mitsuba_version", "drjit_version", "trace_seconds", "built_utc"):
        if key in p:
            lines.append(f"{key:<11} {p[key]}")
    ins = info["inscatter"]
    lines.append("inscatter   " + ("none: I_c is modelled as the unscattered beam alone" if ins is None else
                                   f"{ins['path']} (grid {'×'.join(map(str, ins['grid']))}, σt·ℓ ≤ {ins['tau_max']:g}, "
                                   f"largest ln(1 + r) {ins['max_log1p_ratio']:.3f})"))
    print("\n".join(lines))
    return 0


def _table_info(args) -> int:
    """`map info` of a device table (.tlut)."""
    from trimeter.formats.device_table import describe_table

    info = describe_table(args.map)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    s, fg, ig, rg = info["sample"], info["forward_grid"], info["inverse_grid"], info["range"]
    ins = info["inscatter_grid"]
    print("\n".join([
        f"name        {info['name']}   ({info['path']}, device table format {info['format_version']}, "
        f"{info['size_bytes']} of {info['slot_capacity_bytes']} bytes)",
        f"sha256      {info['sha256']}  (own CRC-32 {info['crc32']})",
        f"parent map  sha256 {info['parent_map_sha256']}",
        f"sample      n = {s['n']:g}, thickness = {s['thickness_mm']:g} mm, cover slides "
        f"{'none' if s['cover_slide_n'] is None else format(s['cover_slide_n'], '.4g')}; reference ρ_b = "
        f"{info['reference_rho']['black']:g}, ρ_w = {info['reference_rho']['white']:g}",
        f"forward     α {fg['alpha']} ({rg['alpha'][0]:g}…{rg['alpha'][1]:g}), σt {fg['sigma_t']} "
        f"({rg['sigma_t'][0]:g}…{rg['sigma_t'][1]:g} 1/mm), g {fg['g']} ({rg['g'][0]:g}…{rg['g'][1]:g})",
        f"inverse     {ig['x']}×{ig['y']} per σt node",
        "inscatter   " + ("none" if ins is None else "×".join(map(str, ins))),
    ]))
    return 0


def cmd_query(args) -> int:
    alpha, sigma_t, g = require_material(args.alpha, args.sigma_t, args.g)
    rho_b, rho_w = require_reflectance("rho_b", args.rho_b), require_reflectance("rho_w", args.rho_w)
    amap = load_appearance_map(args.map)
    for field, value, axis in (("alpha", alpha, amap.alpha), ("sigma_t", sigma_t, amap.sigma_t), ("g", g, amap.g)):
        if not axis[0] <= value <= axis[-1]:
            raise InputError(f"{field} = {value:g} is outside the map's range {axis[0]:g}…{axis[-1]:g}")
    I_b, I_w, I_c = (float(np.asarray(v)) for v in amap.query(alpha, sigma_t, g, rho_b, rho_w))
    if not all(math.isfinite(v) for v in (I_b, I_w, I_c)):
        raise InputError("the map has no finite value at this point")
    out = {"I_b": I_b, "I_w": I_w, "I_c": I_c}
    print(json.dumps(out) if args.json else "  ".join(f"{k} = {v:.6f}" for k, v in out.items()))
    return 0
