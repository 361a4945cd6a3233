"""`trimeter map build | list | info | query` — appearance maps (trimeter.maps)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from trimeter.errors import InputError, MapFileError
from trimeter.validation import require_material, require_reflectance


def register(subparsers) -> None:
    p = subparsers.add_parser("build", help="build an appearance map from a recipe (maps/recipes/*.toml)")
    p.add_argument("recipe", help="recipe TOML file")
    p.add_argument("--out", help="output map file (default: ./<recipe name>.tmap)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted build from its checkpoint")
    p.add_argument("--checkpoint", help="checkpoint directory (default: .<out name>.checkpoint next to the output)")
    p.add_argument("--keep-checkpoint", action="store_true", help="keep the checkpoint after a successful build")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_build)

    p = subparsers.add_parser("inscatter", help="trace a device map's in-scattering table (<map>.tins, next to it)")
    p.add_argument("map", help="map file or shipped map name (device geometry)")
    p.add_argument("--photons", type=int, default=30_000, help="photons per (σt, g) column (default 30000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="output file (default: the map's path with suffix .tins)")
    p.set_defaults(func=cmd_inscatter)

    p = subparsers.add_parser("list", help="the appearance maps shipped in maps/")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_list)

    p = subparsers.add_parser("info", help="describe an appearance map (recipe, grid, MC error, provenance)")
    p.add_argument("map", help="map file or shipped map name")
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
    from trimeter.maps.appearance import MAP_KIND, AppearanceMap, find_map

    path = find_map(name_or_path)
    try:
        return AppearanceMap.load(path)
    except MapFileError as exc:
        if "expected a" in str(exc) and MAP_KIND in str(exc):
            raise MapFileError(f"{path} is not an appearance map ({exc})") from None
        raise


def cmd_build(args) -> int:
    from trimeter.maps.builder import build_map, validation_report
    from trimeter.maps.recipe import load_recipe

    recipe = load_recipe(args.recipe)
    out = Path(args.out) if args.out else Path(f"{recipe.name}.tmap")
    na, ns, ng = recipe.shape
    print(f"building {recipe.name}: {recipe.geometry}, n = {recipe.n:g}, ℓ = {recipe.thickness_mm:g} mm, "
          f"grid α×σt×g = {na}×{ns}×{ng} ({na * ns * ng} points, {ns * ng} traces) → {out}")
    amap = build_map(recipe, out, checkpoint_dir=args.checkpoint, resume=args.resume, progress=not args.quiet,
                     keep_checkpoint=args.keep_checkpoint)
    info = amap.info()
    prov = amap.provenance
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB, sha256 {amap.checksum[:16]}…)")
    print(f"trace time {prov['trace_seconds']:.1f} s (this run: {prov['wall_seconds_last_run']:.1f} s wall, "
          f"{prov['columns_traced_last_run']} columns traced, {prov['columns_resumed']} resumed)")
    print(f"MC std-error of I: median {info['mc_stderr']['median']:.2e}, max {info['mc_stderr']['max']:.2e}; "
          f"paths per column {prov['paths_per_column']['min']}…{prov['paths_per_column']['max']}; "
          f"truncation error ≤ {prov['truncation']['max_error_bound']:.1e} (K = {prov['truncation']['k_max']})")
    print("validation:", json.dumps(validation_report(amap)))
    if recipe.geometry == "device":  # I_c's in-scattered light, which the fit takes out (maps/README)
        trace_inscatter(amap, out=out.with_suffix(".tins"))
    return 0


def cmd_inscatter(args) -> int:
    from trimeter.errors import InputError

    amap = load_appearance_map(args.map)
    if amap.recipe["geometry"] != "device" or "collimated" not in amap.recipe.get("geometry_params", {}):
        raise InputError(f"map {amap.name}: in-scattering needs the device geometry's collimated set-up")
    if args.photons < 1000:
        raise InputError("--photons: at least 1000")
    trace_inscatter(amap, photons=args.photons, seed=args.seed, out=Path(args.out) if args.out else None)
    return 0


def trace_inscatter(amap, *, photons: int = 30_000, seed: int = 0, out: Path | None = None) -> Path:
    """Trace a device map's in-scattering table and write it (default: next to the map, .tins)."""
    from trimeter.forward.inscatter import InscatterTable

    out = out or amap.path.with_suffix(".tins")
    print(f"tracing the in-scattering table of {amap.name} (n = {amap.n:g}, ℓ = {amap.thickness_mm:g} mm, "
          f"{photons} photons per column) → {out}")
    table = InscatterTable.build(amap.n, amap.thickness_mm, amap.recipe["geometry_params"], photons=photons,
                                 seed=seed,
                                 progress=lambda j, n: print(f"\r  σt·ℓ column {j + 1}/{n}", end="", flush=True))
    checksum = table.save(out)
    print(f"\nwrote {out} ({out.stat().st_size} bytes, sha256 {checksum[:16]}…) in "
          f"{table.provenance['seconds']:.0f} s; largest ln(1 + r) {table.L.max():.3f}")
    return out


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
    from trimeter.maps.appearance import shipped_maps

    rows = []
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
