"""`trimeter forward`: the forward model rendered directly (Mitsuba volpath), and its validation report.

  trimeter forward --geometry ideal --alpha 0.9 --sigma-t 2 --g 0.5 --thickness 0.5 --n 1.5 \\
                   --rho-b 0.02 --rho-w 0.99 [--spp K] [--seed S] --json
  trimeter forward validate [--materials 30] [--spp K] [--device-materials 3] [--inscatter] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from trimeter.errors import InputError
from trimeter.geometry import PRESETS
from trimeter.validation import require_number


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("forward", help="render (I_b, I_w, I_c) for one material directly with Mitsuba",
                              description="Render the diffuse observables I_b, I_w with Mitsuba's volumetric "
                                          "path tracer (I_c is analytic). σt in 1/mm, thickness in mm.")
    p.add_argument("--geometry", choices=PRESETS, default="ideal")
    p.add_argument("--alpha", help="single-scattering albedo α ∈ [0, 1]")
    p.add_argument("--sigma-t", help="extinction σt ≥ 0 [1/mm]")
    p.add_argument("--g", help="Henyey-Greenstein anisotropy, |g| < 1")
    p.add_argument("--thickness", help="sample thickness ℓ > 0 [mm]")
    p.add_argument("--n", default="1.5", help="sample refractive index ≥ 1 (default 1.5)")
    p.add_argument("--rho-b", help="black background reflectance ∈ [0, 1]")
    p.add_argument("--rho-w", help="white background reflectance ∈ [0, 1]")
    p.add_argument("--spp", default=None, help="samples per render (default 262144)")
    p.add_argument("--seed", default="0", help="seed (deterministic)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run)
    sub = p.add_subparsers(dest="forward_command", metavar="SUBCOMMAND")
    v = sub.add_parser("validate", help="physics report: ideal vs adding-doubling, device I(ρ) closed form, I_c "
                                        "in-scattering",
                       description="Physics checks of the direct renders. Prints figures; exit 1 if "
                                   "the ideal geometry misses the 0.5 % median agreement.")
    v.add_argument("--materials", type=int, default=30, help="random materials for the adding-doubling check")
    v.add_argument("--spp", type=int, default=1048576, help="samples per render (ideal)")
    v.add_argument("--device-materials", type=int, default=3, help="materials for the device I(ρ) check (0: skip)")
    v.add_argument("--device-spp", type=int, default=1048576)
    v.add_argument("--inscatter", action="store_true", help="also run the I_c in-scattering light tracer")
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--json", action="store_true")
    v.set_defaults(func=_validate)


def _required(args: argparse.Namespace, attr: str, flag: str, **bounds: Any) -> float:
    value = getattr(args, attr)
    if value is None:
        raise InputError(f"{flag} is required")
    return require_number(flag, value, **bounds)


def _run(args: argparse.Namespace) -> int:
    alpha = _required(args, "alpha", "--alpha", lo=0.0, hi=1.0)
    sigma_t = _required(args, "sigma_t", "--sigma-t", lo=0.0)
    g = _required(args, "g", "--g", lo=-1.0, hi=1.0, lo_open=True, hi_open=True)
    thickness = _required(args, "thickness", "--thickness", lo=0.0, lo_open=True)
    n = _required(args, "n", "--n", lo=1.0)
    rho_b = _required(args, "rho_b", "--rho-b", lo=0.0, hi=1.0)
    rho_w = _required(args, "rho_w", "--rho-w", lo=0.0, hi=1.0)
    spp = int(require_number("--spp", args.spp, lo=16)) if args.spp is not None else None
    seed = int(require_number("--seed", args.seed, lo=0))
    from trimeter.forward.render import DEFAULT_SPP, forward

    result = forward(args.geometry, alpha, sigma_t, g, thickness, n, rho_b, rho_w, spp or DEFAULT_SPP, seed)
    if args.json:
        print(json.dumps(result))
    else:
        s = result["stderr"]
        print(f"I_b = {result['I_b']:.6f} ± {s['I_b']:.6f}")
        print(f"I_w = {result['I_w']:.6f} ± {s['I_w']:.6f}")
        print(f"I_c = {result['I_c']:.6g} (analytic)")
        prov = result["provenance"]
        print(f"{prov['geometry']}, {prov['variant']}, {prov['spp']} spp, {prov['seconds']} s")
    return 0


def _validate(args: argparse.Namespace) -> int:
    from trimeter.forward import validate as val

    if args.materials < 0 or args.device_materials < 0:
        raise InputError("--materials and --device-materials must be >= 0")
    say = (lambda *a, **k: print(*a, file=sys.stderr, **k)) if args.json else print
    report: dict[str, object] = {}
    ok = True
    if args.materials > 0:
        materials = val.random_materials(args.materials, args.seed)
        iad = val.iad_agreement(materials, spp=args.spp, seed=args.seed,
                                progress=lambda i, n: say(f"  ideal vs adding-doubling: {i}/{n}", end="\r"))
        report["ideal_vs_iad"] = iad
        ok = iad["median_abs_err_pct"] <= 0.5
        say("")
        say(f"ideal vs adding-doubling ({iad['materials']} materials x 2 backgrounds, n={iad['n']}, "
            f"l={iad['thickness_mm']} mm, {iad['spp']} spp):")
        for r in iad["rows"]:
            say(f"  a={r['alpha']:.4f} st={r['sigma_t']:8.3f} g={r['g']:.2f} rho={r['rho']:.2f}: mitsuba "
                f"{r['mitsuba']:.5f} ± {r['stderr']:.5f}  iad {r['iad']:.5f}  {r['rel_err_pct']:+.3f} %  "
                f"z={r['z']:+.1f}")
        say(f"  median |err| {iad['median_abs_err_pct']:.3f} %, max {iad['max_abs_err_pct']:.3f} %, "
            f"median MC stderr {iad['median_rel_stderr_pct']:.3f} %, {iad['seconds_per_render']:.2f} s per render")
    if args.device_materials > 0:
        device_rows = []
        for alpha, sigma_t, g in val.random_materials(args.device_materials, args.seed + 1):
            device_rows.append(val.rho_closed_form("device", alpha, sigma_t, g, 1.5, 0.4, spp=args.device_spp,
                                                   seed=args.seed))
        report["device_rho_closed_form"] = device_rows
        say("device I(rho) = A + B rho/(1 - C rho), fitted at rho = 0, 0.5, 0.99 (n=1.5, l=0.4 mm):")
        for row in device_rows:
            m = row["material"]
            for c in row["checks"]:
                say(f"  a={m['alpha']:.4f} st={m['sigma_t']:8.3f} g={m['g']:.2f} rho={c['rho']:.2f}: rendered "
                    f"{c['rendered']:.5f} ± {c['stderr']:.5f}, closed form {c['closed_form']:.5f} "
                    f"({c['abs_err']:+.5f}, {c['rel_err_pct']:+.3f} %)")
    if args.inscatter:
        from trimeter.forward.transport.inscatter_tracer import inscatter_report

        report["inscatter"] = inscatter_report(seed=args.seed, say=say)
    if args.json:
        print(json.dumps(report))
    return 0 if ok else 1
