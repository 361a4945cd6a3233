"""`trimeter bench polarisation`: how much do the observables and the fitted α, σt, g move when the
polarisations are tracked?

Unpolarised Fresnel at every interface is what the ideal map, adding-doubling and the direct renders the
tracer is checked against use (the device maps track the polarisations: the tracer's option, which
`bench polarisation-tracer` checks against these renders). Here a few materials per geometry are rendered
with Mitsuba's volpath in the unpolarised variant (u) and twice in its polarised one (`*_polarized`:
Fresnel as Mueller matrices at the dielectric faces; emitters and the Lambertian background unpolarised;
the detector reads the intensity element):
with Mitsuba's `hg` (p), whose Mueller matrix is the identity, so scattered light keeps the polarisation
the faces gave it, and with `hg_depolarising` (d, trimeter.forward.phase), whose scattering leaves
unpolarised light. A real medium lies between the two. All renders of a material share their seeds, so
the batch-wise differences carry the difference's own std-error. Both backgrounds are the map's
reference ones. Every set is fitted with the geometry's shipped map (I_c: the map's own, the same for all:
the collimated beam crosses the faces at normal incidence, where s and p reflect alike). Per material the
shift Δ = p − u (and d − u) of α, σt, g is printed against
- σ_map: the std fit() reports with noise-free intensities, i.e. the map's own error budget (its
  Monte Carlo std-error and interpolation term at the solution), and
- σ_Δ: the shift's own render noise, propagated through the fit.
A shift beyond σ_map (and beyond 2σ_Δ, so not render noise) is one the maps should not ignore.
The renders are not extrapolated to no ray offset (trimeter.forward.render.render_diffuse_offset_free): the
offset darkens a dense sample in all three treatments' renders alike (same paths), so the shifts keep it only
to second order, while the levels, and so the fitted values themselves, carry it.

First the set-up is checked on a clear, lossless slab (ideal geometry) over a grey background, where the
slab's diffuse reflectance R_d enters and has a closed form per treatment of Fresnel: the rendered I of
each variant gives R_d back, to compare with the closed forms.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.bench import write_figures
from trimeter.errors import InputError

# (label, α, σt [1/mm], g): a nearly clear (so thin a fit flags it UNDERDETERMINED), a grey, an ink, a milky, a
# near-white and a thin one (the thinnest here that a fit pins down), all inside every shipped map and with enough
# collimated light through both thicknesses to fix σt
MATERIALS = (("clear", 0.5, 0.2, 0.0), ("grey", 0.6, 2.0, 0.3), ("ink", 0.9, 5.0, 0.6), ("milky", 0.99, 10.0, 0.7),
             ("white", 0.998, 12.0, 0.5), ("thin", 0.5, 0.5, 0.3))
MAPS = {"ideal": "ideal-n1.5-l0.5", "device": "device-n1.5-l0.4"}  # the shipped map each geometry is fitted with
PARAMS = ("alpha", "sigma_t", "g")
# the renders' treatments of polarisation: key → (which variant: 0 unpolarised, 1 polarised; the phase function)
TREATMENTS = {"unpolarised": (0, "hg"), "polarised": (1, "hg"), "depolarising": (1, "hg_depolarising")}
SHIFTED = ("polarised", "depolarising")  # compared with the unpolarised renders
# the clear-slab check: where R_d moves I most (dI/dR_d ∝ ρ(1 − ρ)), the ideal slab of the ideal map
SLAB_RHO, SLAB_N, SLAB_THICKNESS_MM = 0.5, 1.5, 0.5
DEFAULT_SPP, DEFAULT_SLAB_SPP, DEFAULT_SEED = 1 << 18, 1 << 22, 11


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("polarisation", help="observables and fitted α, σt, g: Mitsuba's polarised "
                                                         "variant against its unpolarised one",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--geometry", choices=("ideal", "device", "both"), default="both")
    p.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"volpath samples per render (default {DEFAULT_SPP})")
    p.add_argument("--slab-spp", type=int, default=DEFAULT_SLAB_SPP,
                   help=f"samples per render of the clear-slab check (default {DEFAULT_SLAB_SPP}; 0: not run)")
    p.add_argument("--materials", type=int, default=len(MATERIALS),
                   help=f"how many of the {len(MATERIALS)} built-in materials, in order (default all)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED)
    p.add_argument("--out", type=Path, default=Path("out/bench-polarisation/results.json"))
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report = measure(args)
    _print(report)
    write_figures(report, args.out)
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


# ------------------------------------------------------------------------------------- the clear slab
def slab_diffuse_reflectance(n: float) -> tuple[float, float]:
    """(unpolarised, polarised) diffuse reflectance R_d = ∫ R_slab(μ) 2μ dμ of a clear, lossless slab of index n in
    air under uniform light: R_slab = 2r/(1 + r) (both faces, every internal reflection) from the averaged Fresnel
    r = (R_s + R_p)/2 (unpolarised, as the tracer has it) or per polarisation, then averaged (polarised)."""
    from trimeter.model.fresnel import NUMPY, fresnel_polarised

    x, w = np.polynomial.legendre.leggauss(96)
    mu, w = (x + 1) / 2, w / 2
    R_s, R_p, _ = fresnel_polarised(NUMPY, mu, n)

    def slab(r):
        return 2 * r / (1 + r)

    return (float(np.sum(w * 2 * mu * slab((R_s + R_p) / 2))),
            float(np.sum(w * 2 * mu * (slab(R_s) + slab(R_p)) / 2)))


def _slab_normal(n: float) -> tuple[float, float]:
    """(R_0, T_0): the lossless slab's reflectance and transmittance along its normal."""
    from trimeter.model.fresnel import normal_incidence_reflectance

    r = float(normal_incidence_reflectance(1.0, n))
    return 2 * r / (1 + r), 1 - 2 * r / (1 + r)


def clear_slab_over(rho: float, n: float, R_d: float) -> float:
    """The clear slab's reflectance factor along its normal over a Lambertian ρ under uniform light:
    I = R_0 + T_0·(1 − R_d)·ρ / (1 − R_d·ρ) (light reaching the background through the slab, bouncing between
    the two, leaving along the normal)."""
    R0, T0 = _slab_normal(n)
    return R0 + T0 * (1 - R_d) * rho / (1 - R_d * rho)


def slab_diffuse_from(I: np.ndarray, rho: float, n: float) -> np.ndarray:
    """clear_slab_over inverted: the R_d a rendered I implies."""
    R0, T0 = _slab_normal(n)
    y = (np.asarray(I) - R0) / (T0 * rho)
    return (1 - y) / (1 - y * rho)


def _slab_check(spp: int, seed: int, unpolarised: str, polarised: str) -> dict[str, Any]:
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    batches = {}
    for key, variant in (("unpolarised", unpolarised), ("polarised", polarised)):
        mitsuba(variant)
        I = render_diffuse_batches("ideal", 0.0, 1e-4, 0.0, SLAB_N, SLAB_THICKNESS_MM, SLAB_RHO, spp, seed)
        batches[key] = slab_diffuse_from(I, SLAB_RHO, SLAB_N)
    expected = dict(zip(("unpolarised", "polarised"), slab_diffuse_reflectance(SLAB_N), strict=True))
    out: dict[str, Any] = {"rho": SLAB_RHO, "n": SLAB_N, "thickness_mm": SLAB_THICKNESS_MM, "spp": spp}
    for key, R_d in batches.items():
        mean, se = _stats(R_d)
        out[key] = {"R_d": float(mean), "stderr": float(se), "closed_form": expected[key],
                    "I": clear_slab_over(SLAB_RHO, SLAB_N, float(mean))}
    mean, se = _stats(batches["polarised"] - batches["unpolarised"])
    out["delta"] = {"R_d": float(mean), "stderr": float(se),
                    "closed_form": expected["polarised"] - expected["unpolarised"]}
    return out


# ------------------------------------------------------------------------------------- the materials
def measure(args: argparse.Namespace) -> dict[str, Any]:
    """{"variants", "spp", "seed", "slab": the clear-slab check (or None), "geometries": [{"geometry", "map",
    "rows": per material and background each treatment's I and the shifts, "fits": per material the fitted
    values, shifts and σ's}]}."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.formats.appearance import AppearanceMap, find_map

    if args.spp < 16:
        raise InputError("--spp must be ≥ 16")
    if args.slab_spp and args.slab_spp < 16:
        raise InputError("--slab-spp must be 0 (not run) or ≥ 16")
    if not 1 <= args.materials <= len(MATERIALS):
        raise InputError(f"--materials must be 1…{len(MATERIALS)}")
    materials = MATERIALS[:args.materials]
    names = variants()
    geometries = ("ideal", "device") if args.geometry == "both" else (args.geometry,)
    report: dict[str, Any] = {"variants": list(names), "phases": {k: v[1] for k, v in TREATMENTS.items()},
                              "spp": args.spp, "seed": args.seed, "slab": None, "geometries": []}
    try:
        if args.slab_spp:
            report["slab"] = _slab_check(args.slab_spp, args.seed, *names)
        for geometry in geometries:
            amap = AppearanceMap.load(find_map(MAPS[geometry]))
            batches = {key: _render(amap, materials, names[which], phase, args.spp, args.seed)
                       for key, (which, phase) in TREATMENTS.items()}
            report["geometries"].append(_compare(amap, geometry, materials, batches))
    finally:
        mitsuba(names[0])  # the process renders unpolarised again afterwards
    return report


def _render(amap, materials, variant: str, phase: str, spp: int, seed: int) -> np.ndarray:
    """Batch means, (materials, 2 backgrounds, batches), rendered in `variant` with the map's geometry."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    mitsuba(variant)
    geometry = amap.recipe["geometry_params"]
    out = []
    for k, (label, a, s, g) in enumerate(materials):
        row = [render_diffuse_batches(geometry, a, s, g, amap.n, amap.thickness_mm, rho, spp, seed + k, phase=phase)
               for rho in amap.reference_rhos]
        out.append(row)
        print(f"  {variant:<24} {phase:<16} {amap.name} {label:<6} I_b {row[0].mean():.5f}  I_w {row[1].mean():.5f}",
              flush=True)
    return np.asarray(out)


def _stats(batches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std-error over the last axis (the batches)."""
    return batches.mean(axis=-1), batches.std(axis=-1, ddof=1) / math.sqrt(batches.shape[-1])


def _compare(amap, geometry: str, materials, batches: dict[str, np.ndarray]) -> dict[str, Any]:
    from trimeter.inversion.artifacts import fit

    truth = {k: np.array([m[i + 1] for m in materials]) for i, k in enumerate(PARAMS)}
    I_c = amap.collimated_measured(truth["alpha"], truth["sigma_t"], truth["g"])
    zero = np.zeros(len(materials))

    def fitted(I, stds):
        return fit(amap, I[:, 0], I[:, 1], I_c, method="lut", I_b_std=stds[:, 0], I_w_std=stds[:, 1], I_c_std=zero)

    level = {key: _stats(b) for key, b in batches.items()}
    shift = {key: _stats(batches[key] - batches["unpolarised"]) for key in SHIFTED}
    map_only = {key: fitted(I, np.zeros_like(I)) for key, (I, _) in level.items()}
    with_noise = {key: fitted(level["unpolarised"][0], se) for key, (_, se) in shift.items()}  # render noise added
    rows, fits = [], []
    for k, (label, *_) in enumerate(materials):
        for j, background in enumerate(("black", "white")):
            row: dict[str, Any] = {"material": label, "background": background, "rho": amap.reference_rhos[j]}
            for key, (I, se) in level.items():
                row[f"I_{key}"], row[f"stderr_{key}"] = float(I[k, j]), float(se[k, j])
            for key, (d, se) in shift.items():
                suffix = "" if key == "polarised" else f"_{key}"
                row[f"delta{suffix}"], row[f"stderr_delta{suffix}"] = float(d[k, j]), float(se[k, j])
                row[f"z{suffix}"] = float(d[k, j] / se[k, j]) if se[k, j] > 0 else None
            rows.append(row)
        entry: dict[str, Any] = {"material": label, "I_c": float(I_c[k]),
                                 "flags": {key: int(r.flags[k]) for key, r in map_only.items()}}
        for p in PARAMS:
            sigma_map = float(getattr(map_only["unpolarised"], f"{p}_std")[k])
            c: dict[str, Any] = {"truth": float(truth[p][k]), "sigma_map": sigma_map}
            c.update({key: float(getattr(r, p)[k]) for key, r in map_only.items()})
            for key in SHIFTED:
                suffix = "" if key == "polarised" else f"_{key}"
                moved = c[key] - c["unpolarised"]
                total = float(getattr(with_noise[key], f"{p}_std")[k])
                sigma_delta = math.sqrt(max(total ** 2 - sigma_map ** 2, 0.0))
                c[f"shift{suffix}"], c[f"sigma_delta{suffix}"] = moved, sigma_delta
                c[f"beyond_map_error{suffix}"] = bool(abs(moved) > sigma_map and abs(moved) > 2 * sigma_delta)
            entry[p] = c
        fits.append(entry)
    return {"geometry": geometry, "map": amap.name, "rows": rows, "fits": fits}


# ------------------------------------------------------------------------------------- the print-out
def _print(report: dict[str, Any]) -> None:
    unpolarised, polarised = report["variants"]
    slab = report["slab"]
    if slab:
        print(f"\nclear slab check (ideal, n {slab['n']}, ℓ {slab['thickness_mm']} mm, lossless, over ρ {slab['rho']}, "
              f"{slab['spp']} samples per render): its diffuse reflectance R_d from the rendered I")
        for key, variant in (("unpolarised", unpolarised), ("polarised", polarised)):
            s = slab[key]
            print(f"   {variant:<24} R_d {s['R_d']:.4f} ± {s['stderr']:.4f}   closed form {s['closed_form']:.4f}  "
                  f"({(s['R_d'] - s['closed_form']) / s['stderr']:+.1f}σ)")
        d = slab["delta"]
        print(f"   {'difference':<24} ΔR_d {d['R_d']:+.4f} ± {d['stderr']:.4f}  closed form {d['closed_form']:+.4f}  "
              f"({(d['R_d'] - d['closed_form']) / d['stderr']:+.1f}σ)")
    print(f"\nvolpath {unpolarised} (u) against {polarised} with hg (p: scattering keeps the polarisation) and "
          f"with hg_depolarising (d: scattering depolarises), {report['spp']} samples per render, shared seeds; "
          "Δ = p − u, d − u with their own std-error")
    for geo in report["geometries"]:
        print(f"\n{geo['geometry']} (fitted with {geo['map']})")
        print(f"   {'material':<9}{'bg':<6}{'I u':>16}{'Δ p − u':>18}{'z':>6}{'Δ d − u':>18}{'z':>6}")
        for r in geo["rows"]:
            print(f"   {r['material']:<9}{r['background']:<6}{r['I_unpolarised']:>9.5f}±{r['stderr_unpolarised']:<6.5f}"
                  f"{r['delta']:>+10.5f}±{r['stderr_delta']:<7.5f}{_z(r['z']):>6}"
                  f"{r['delta_depolarising']:>+10.5f}±{r['stderr_delta_depolarising']:<7.5f}"
                  f"{_z(r['z_depolarising']):>6}")
        print("   fitted: u, the shifts p − u and d − u, σ_map = the map's error budget fit() reports, σ_Δ = the "
              "shift p − u's render noise (d − u's in the JSON); ! = beyond σ_map and 2σ_Δ (each its own)")
        columns = (f"{name + ' u':>10}{'p − u':>9}{'d − u':>10}{'σ_map':>8}{'σ_Δ':>8}" for name in ("α", "σt", "g"))
        print(f"   {'material':<9}{'I_c':>8}" + "".join(columns))
        for f in geo["fits"]:
            line = f"   {f['material']:<9}{f['I_c']:>8.4f}"
            for p in PARAMS:
                c = f[p]
                line += (f"{c['unpolarised']:>10.4f}{c['shift']:>+8.4f}{'!' if c['beyond_map_error'] else ' '}"
                         f"{c['shift_depolarising']:>+9.4f}{'!' if c['beyond_map_error_depolarising'] else ' '}"
                         f"{c['sigma_map']:>8.4f}{c['sigma_delta']:>8.4f}")
            if any(f["flags"].values()):
                line += f"  flags {sorted(set(f['flags'].values()))}"
            print(line)
        for key, suffix in (("p", ""), ("d", "_depolarising")):
            moved = sum(f[p][f"beyond_map_error{suffix}"] for f in geo["fits"] for p in PARAMS)
            print(f"   {key}: {moved} of {len(geo['fits']) * len(PARAMS)} fitted values moved beyond the map's error")


def _z(z: float | None) -> str:
    return "—" if z is None else f"{z:+.1f}"
