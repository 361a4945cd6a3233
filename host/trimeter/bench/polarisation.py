"""`trimeter bench polarisation`: how much do the observables and the fitted α, σt, g move when the
polarisations are tracked?

The maps' tracer (and the direct renders it is checked against) use unpolarised Fresnel at every
interface. Here a few materials per geometry are rendered with Mitsuba's volpath twice, in the
unpolarised variant and in its polarised one (`*_polarized`: Fresnel as Mueller matrices at the
dielectric faces; the detector reads the intensity element), with the same seeds, so the batch-wise
differences carry the difference's own std-error. Both backgrounds are the map's reference ones.
Both sets are fitted with the geometry's shipped map (I_c: the map's own, the same for both: the
collimated beam crosses the faces at normal incidence, where polarisation changes nothing). Per
material the shift Δ = polarised − unpolarised of α, σt, g is printed against
- σ_map: the std fit() reports with noise-free intensities, i.e. the map's own error budget (its
  Monte Carlo std-error and interpolation term at the solution), and
- σ_Δ: the shift's own render noise, propagated through the fit.
A shift beyond σ_map (and beyond 2σ_Δ, so not render noise) is one the maps should not ignore.
What the polarised variant leaves out: Mitsuba's `hg` phase function scales the Stokes vector
without a Mueller matrix of its own, so the light keeps its polarisation through scattering; the
Lambertian background depolarises.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.errors import InputError

# (label, α, σt [1/mm], g): a nearly clear, a grey, an ink, a milky and a near-white material, all inside every
# shipped map and with enough collimated light through both thicknesses to fix σt
MATERIALS = (("clear", 0.5, 0.2, 0.0), ("grey", 0.6, 2.0, 0.3), ("ink", 0.9, 5.0, 0.6), ("milky", 0.99, 10.0, 0.7),
             ("white", 0.998, 12.0, 0.5))
MAPS = {"ideal": "ideal-n1.5-l0.5", "device": "device-n1.5-l0.4"}  # the shipped map each geometry is fitted with
PARAMS = ("alpha", "sigma_t", "g")


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("polarisation", help="observables and fitted α, σt, g: Mitsuba's polarised "
                                                         "variant against its unpolarised one",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--geometry", choices=("ideal", "device", "both"), default="both")
    p.add_argument("--spp", type=int, default=1 << 18, help="volpath samples per render (default 262144)")
    p.add_argument("--materials", type=int, default=len(MATERIALS),
                   help=f"how many of the {len(MATERIALS)} built-in materials, in order (default all)")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--out", type=Path, default=Path("out/bench-polarisation/results.json"))
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report = measure(args)
    _print(report)
    from trimeter.atomic import atomic_write

    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out, json.dumps(report, indent=1, default=float))
    print(f"\nall figures: {args.out}")
    return 0


def variants() -> tuple[str, str]:
    """(unpolarised, polarised) Mitsuba variants: the one this machine renders with and its `_polarized` twin."""
    from trimeter.forward.mitsuba_env import MitsubaUnavailable, mitsuba

    mi = mitsuba()
    base = mi.variant().removesuffix("_polarized")
    polarised = f"{base}_polarized"
    if polarised not in mi.variants():
        raise MitsubaUnavailable(f"Mitsuba has no polarised variant of {base} ({polarised}); "
                                 f"have {', '.join(mi.variants())}")
    return base, polarised


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """{"variants", "spp", "geometries": [{"geometry", "map", "rows": per material and background the two I's
    and their difference, "fits": per material the fitted values, shifts and σ's}]}."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.maps.appearance import AppearanceMap, find_map

    if args.spp < 16:
        raise InputError("--spp must be ≥ 16")
    if not 1 <= args.materials <= len(MATERIALS):
        raise InputError(f"--materials must be 1…{len(MATERIALS)}")
    materials = MATERIALS[:args.materials]
    unpolarised, polarised = variants()
    geometries = ("ideal", "device") if args.geometry == "both" else (args.geometry,)
    report: dict[str, Any] = {"variants": [unpolarised, polarised], "spp": args.spp, "seed": args.seed,
                              "geometries": []}
    try:
        for geometry in geometries:
            amap = AppearanceMap.load(find_map(MAPS[geometry]))
            batches = {v: _render(amap, materials, v, args.spp, args.seed) for v in (unpolarised, polarised)}
            report["geometries"].append(_compare(amap, geometry, materials, batches[unpolarised],
                                                 batches[polarised]))
    finally:
        mitsuba(unpolarised)  # the process renders unpolarised again afterwards
    return report


def _render(amap, materials, variant: str, spp: int, seed: int) -> np.ndarray:
    """Batch means, (materials, 2 backgrounds, batches), rendered in `variant` with the map's geometry."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    mitsuba(variant)
    geometry = amap.recipe["geometry_params"]
    out = []
    for k, (label, a, s, g) in enumerate(materials):
        row = []
        for rho in amap.reference_rhos:
            row.append(render_diffuse_batches(geometry, a, s, g, amap.n, amap.thickness_mm, rho, spp, seed + k))
        out.append(row)
        print(f"  {variant:<24} {amap.name} {label:<6} I_b {row[0].mean():.5f}  I_w {row[1].mean():.5f}", flush=True)
    return np.asarray(out)


def _stats(batches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std-error over the last axis (the batches)."""
    return batches.mean(axis=-1), batches.std(axis=-1, ddof=1) / math.sqrt(batches.shape[-1])


def _compare(amap, geometry: str, materials, unpol: np.ndarray, pol: np.ndarray) -> dict[str, Any]:
    from trimeter.maps.artifacts import fit

    I_u, se_u = _stats(unpol)
    I_p, se_p = _stats(pol)
    dI, se_d = _stats(pol - unpol)
    truth = {k: np.array([m[i + 1] for m in materials]) for i, k in enumerate(PARAMS)}
    I_c = amap.collimated_measured(truth["alpha"], truth["sigma_t"], truth["g"])
    zero = np.zeros(len(materials))

    def fitted(I, stds):
        return fit(amap, I[:, 0], I[:, 1], I_c, method="lut", I_b_std=stds[:, 0], I_w_std=stds[:, 1], I_c_std=zero)

    map_only_u, map_only_p = fitted(I_u, np.zeros_like(I_u)), fitted(I_p, np.zeros_like(I_p))
    with_noise = fitted(I_u, se_d)  # the shift's render noise on top of the map's budget
    rows, fits = [], []
    for k, (label, *_) in enumerate(materials):
        for j, background in enumerate(("black", "white")):
            rows.append({"material": label, "background": background, "rho": amap.reference_rhos[j],
                         "I_unpolarised": I_u[k, j], "stderr_unpolarised": se_u[k, j],
                         "I_polarised": I_p[k, j], "stderr_polarised": se_p[k, j],
                         "delta": dI[k, j], "stderr_delta": se_d[k, j]})
        entry: dict[str, Any] = {"material": label, "flags": [int(map_only_u.flags[k]), int(map_only_p.flags[k])]}
        for p in PARAMS:
            shift = float(getattr(map_only_p, p)[k] - getattr(map_only_u, p)[k])
            sigma_map = float(getattr(map_only_u, f"{p}_std")[k])
            total = float(getattr(with_noise, f"{p}_std")[k])
            sigma_delta = math.sqrt(max(total ** 2 - sigma_map ** 2, 0.0))
            entry[p] = {"truth": float(truth[p][k]), "unpolarised": float(getattr(map_only_u, p)[k]),
                        "polarised": float(getattr(map_only_p, p)[k]), "shift": shift, "sigma_map": sigma_map,
                        "sigma_delta": sigma_delta,
                        "beyond_map_error": bool(abs(shift) > sigma_map and abs(shift) > 2 * sigma_delta)}
        fits.append(entry)
    return {"geometry": geometry, "map": amap.name, "rows": rows, "fits": fits}


def _print(report: dict[str, Any]) -> None:
    unpolarised, polarised = report["variants"]
    print(f"\nvolpath {unpolarised} (u) against {polarised} (p), {report['spp']} samples per render, "
          "shared seeds; Δ = p − u with its own std-error")
    for geo in report["geometries"]:
        print(f"\n{geo['geometry']} (fitted with {geo['map']})")
        print(f"   {'material':<9}{'bg':<6}{'I u':>16}{'I p':>16}{'ΔI':>18}{'ΔI/σ':>7}")
        for r in geo["rows"]:
            z = r["delta"] / r["stderr_delta"] if r["stderr_delta"] > 0 else float("nan")
            print(f"   {r['material']:<9}{r['background']:<6}{r['I_unpolarised']:>9.5f}±{r['stderr_unpolarised']:<6.5f}"
                  f"{r['I_polarised']:>9.5f}±{r['stderr_polarised']:<6.5f}{r['delta']:>+10.5f}±{r['stderr_delta']:<7.5f}"
                  f"{z:>+7.1f}")
        print("   fitted (u → p): shift, σ_map = the map's error budget fit() reports, σ_Δ = the shift's render noise; "
              "! = beyond σ_map and 2σ_Δ")
        print(f"   {'material':<9}" + "".join(f"{name + ' u→p':>22}{'shift':>10}{'σ_map':>8}{'σ_Δ':>8}  "
                                             for name in ("α", "σt", "g")))
        for f in geo["fits"]:
            line = f"   {f['material']:<9}"
            for p in PARAMS:
                c = f[p]
                line += (f"{c['unpolarised']:>10.4f}→{c['polarised']:<11.4f}{c['shift']:>+10.4f}{c['sigma_map']:>8.4f}"
                         f"{c['sigma_delta']:>8.4f}{'!' if c['beyond_map_error'] else ' '} ")
            if any(f["flags"]):
                line += f" flags {f['flags']}"
            print(line)
        moved = sum(f[p]["beyond_map_error"] for f in geo["fits"] for p in PARAMS)
        print(f"   {moved} of {len(geo['fits']) * len(PARAMS)} fitted values moved beyond the map's error")
