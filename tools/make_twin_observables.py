"""Compute the twin's virtual samples directly (no appearance map): host/trimeter/data/twin_observables/.

    .venv/bin/python tools/make_twin_observables.py                      # the default set-ups, all materials
    .venv/bin/python tools/make_twin_observables.py --setup device:0.4 --paths 2097152
    .venv/bin/python tools/make_twin_observables.py --setup ideal:0.5:adding-doubling
    .venv/bin/python tools/make_twin_observables.py --setup device:0.6 --polarisation on

Per set-up (geometry preset, n, ℓ, and the integrator: `tracer` unless the set-up names another) and catalogue
material, at wavelength nodes every --step-nm over the spectrometer's range:
- tracer: one tracer column (trimeter.forward.transport.trace_column) at the material's own σt and g, evaluated
  at its own α → A, B, C; for the device, the collimated beam's in-scattering from
  trimeter.forward.transport.inscatter_tracer's direct tracer → L. The nodes of one material share a seed
  (common random numbers), so the Monte Carlo error varies smoothly with λ. Fresnel per polarisation or
  unpolarised (--polarisation): by default as the shipped map recipe of the set-up (maps/recipes/<set-up>.toml)
  traces it, unpolarised where there is none, so the twin's physics is the maps' best model.
- adding-doubling (ideal geometry only): A, B, C from Prahl's adding-doubling at IAD_QUAD_POINTS quadrature
  points (trimeter.forward.adding_doubling), L = 0; the change in I_b, I_w at twice the points is recorded per
  node as the quadrature's error. Deterministic: no seed, no paths.
See trimeter.twin.observables for how the twin uses it. Each material records how it was made; the file's
provenance is the last run over the whole catalogue (a run over some materials or mixtures, --material /
--twin-mixtures, adds to the file and leaves it). A file holds one integrator's observables.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime, timezone

import numpy as np

from trimeter import __version__
from trimeter.errors import InputError
from trimeter.forward.adding_doubling import IAD_QUAD_POINTS, ideal_abc
from trimeter.forward.transport.inscatter_tracer import traced_log1p_ratio
from trimeter.geometry import load_geometry
from trimeter.forward.transport import Stack, k_max_for, trace_column
from trimeter.twin.optics import catalogue_entry, material_names, material_spectra
from trimeter.maps.recipe import load_recipe
from trimeter.model.response import background_response
from trimeter.paths import MAPS_DIR
from trimeter.twin.observables import DATA_DIR, FORMAT_VERSION, INTEGRATOR_PHYSICS, content_hash, setup_name

# the shipped device maps', the HIL map's (adding-doubling itself: its twin is traced, so that a round trip
# crosses two integrators) and the shipped ideal map's (traced: its twin by adding-doubling, for the same reason)
DEFAULT_SETUPS = ("device:0.4", "device:0.8", "ideal:0.4", "ideal:0.5:adding-doubling")
TRUNCATION = 1e-5
ERROR_RHOS = (0.03, 0.99)  # the backgrounds a node's error is stated at (black, white)
STEP_NM = {"tracer": 20.0, "adding-doubling": 5.0}  # default node spacing (see --step-nm)


def trace_material(name: str, geometry: str, params: dict, n: float, thickness_mm: float, nodes, paths: int,
                   photons: int, seed: int, polarisation: bool) -> dict:
    s = material_spectra(name, nodes)
    stack = Stack.from_recipe(geometry, params, n, thickness_mm)
    k_max = k_max_for(float(s["alpha"].max()), TRUNCATION)
    out: dict[str, list[float]] = {k: [] for k in ("A", "B", "C", "L", "stderr_black", "stderr_white")}
    for alpha, sigma_t, g in zip(s["alpha"], s["sigma_t"], s["g"], strict=True):
        tally = trace_column(stack, float(sigma_t), float(g), paths, seed, k_max, polarisation=polarisation)
        A, B, C = (float(v[0]) for v in tally.abc([alpha]))
        out["A"].append(A)
        out["B"].append(B)
        out["C"].append(C)
        out["stderr_black"].append(float(tally.stderr([alpha], ERROR_RHOS[0])[0]))
        out["stderr_white"].append(float(tally.stderr([alpha], ERROR_RHOS[1])[0]))
        out["L"].append(float(traced_log1p_ratio([alpha], float(sigma_t), float(g), thickness_mm, n, params,
                                                 photons, seed)[0]) if geometry == "device" else 0.0)
    return {"material_hash": content_hash(catalogue_entry(name)), "paths_per_node": paths, "seed": seed,
            "wavelength_nm": [float(v) for v in nodes], **_rounded(out)}


def adding_doubling_material(name: str, n: float, thickness_mm: float, nodes) -> dict:
    """A, B, C at the nodes by adding-doubling, and the quadrature's error in I at ERROR_RHOS: the change
    from doubling its points."""
    s = material_spectra(name, nodes)
    abc = ideal_abc(s["alpha"], s["sigma_t"], s["g"], thickness_mm=thickness_mm, n=n)
    finer = ideal_abc(s["alpha"], s["sigma_t"], s["g"], thickness_mm=thickness_mm, n=n,
                      quad_points=2 * IAD_QUAD_POINTS)
    out = {"A": abc[:, 0], "B": abc[:, 1], "C": abc[:, 2], "L": np.zeros(len(abc))}
    for key, rho in zip(("quadrature_error_black", "quadrature_error_white"), ERROR_RHOS, strict=True):
        out[key] = np.abs(background_response(finer[:, 0], finer[:, 1], finer[:, 2], rho)
                          - background_response(abc[:, 0], abc[:, 1], abc[:, 2], rho))
    return {"material_hash": content_hash(catalogue_entry(name)), "quad_points": IAD_QUAD_POINTS,
            "wavelength_nm": [float(v) for v in nodes], **_rounded(out)}


def _rounded(columns: dict) -> dict[str, list[float]]:
    return {k: [float(f"{v:.7g}") for v in vals] for k, vals in columns.items()}


def parse_setup(text: str) -> tuple[str, float, str]:
    """GEOMETRY:THICKNESS_MM[:INTEGRATOR] → (geometry, ℓ, integrator)."""
    geometry, _, rest = text.partition(":")
    thickness, _, integrator = rest.partition(":")
    integrator = integrator or "tracer"
    try:
        thickness_mm = float(thickness)
    except ValueError:
        raise InputError(f"--setup {text!r}: expected GEOMETRY:THICKNESS_MM[:INTEGRATOR]") from None
    if integrator not in INTEGRATOR_PHYSICS:
        raise InputError(f"--setup {text!r}: integrator must be one of {', '.join(INTEGRATOR_PHYSICS)}")
    if integrator == "adding-doubling" and geometry != "ideal":
        raise InputError(f"--setup {text!r}: adding-doubling is exact only for the ideal geometry")
    return geometry, thickness_mm, integrator


def traced_polarisation(choice: str, geometry: str, n: float, thickness_mm: float) -> bool:
    """Whether a traced set-up tracks polarisation: --polarisation on/off, or `recipe`: as the shipped map
    recipe of the same set-up does (off without one)."""
    if choice != "recipe":
        return choice == "on"
    recipe = MAPS_DIR / "recipes" / f"{setup_name(geometry, n, thickness_mm)}.toml"
    return recipe.is_file() and load_recipe(recipe).polarisation


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--setup", action="append", help="GEOMETRY:THICKNESS_MM[:INTEGRATOR], the integrator tracer "
                   "(the default) or adding-doubling (repeatable; default: " + ", ".join(DEFAULT_SETUPS) + ")")
    p.add_argument("--n", type=float, default=1.5, help="the samples' refractive index")
    p.add_argument("--material", action="append", help="only these materials (default: all); a mixture by volume "
                                                       "fractions is MATERIAL:F+MATERIAL:F")
    p.add_argument("--twin-mixtures", action="store_true",
                   help="the mixtures `trimeter library mixtures --twin` measures, instead of the catalogue")
    p.add_argument("--paths", type=int, default=1 << 21, help="detector paths per wavelength node")
    p.add_argument("--photons", type=int, default=40_000, help="collimated in-scattering photons per node (device)")
    p.add_argument("--step-nm", type=float, help="node spacing (default: 20 nm traced; 5 nm by adding-doubling, "
                   "whose nodes cost little: a spline through 20 nm nodes misses the sharpest band by about a "
                   "trace's Monte Carlo error, through 5 nm ones by far less than the quadrature's)")
    p.add_argument("--range-nm", type=float, nargs=2, default=(340.0, 1000.0))
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--polarisation", choices=("recipe", "on", "off"), default="recipe",
                   help="traced set-ups: Fresnel per polarisation (on) or unpolarised (off); default: as the "
                   "shipped map recipe of the set-up, off without one")
    args = p.parse_args(argv)
    if args.twin_mixtures:
        from trimeter.library.mixtures import default_twin_mixtures, mixture_label

        materials = [mixture_label(m) for m in default_twin_mixtures()]
    else:
        materials = args.material or list(material_names())
    DATA_DIR.mkdir(parents=True, exist_ok=True)
    setups = [parse_setup(text) for text in args.setup or DEFAULT_SETUPS]  # all checked before any work
    for geometry, thickness_mm, integrator in setups:
        params = load_geometry(geometry)
        step_nm = args.step_nm or STEP_NM[integrator]
        nodes = np.arange(args.range_nm[0], args.range_nm[1] + 1e-9, step_nm)
        path = DATA_DIR / f"{setup_name(geometry, args.n, thickness_mm)}.json"
        polarisation = integrator == "tracer" and traced_polarisation(args.polarisation, geometry, args.n,
                                                                        thickness_mm)
        doc = json.loads(path.read_text()) if path.is_file() else {"materials": {}}
        if (doc.get("integrator", "tracer"), doc.get("polarisation", False)) != (integrator, polarisation):
            doc = {"materials": {}}   # one integrator and one model per file: another's entries go
        t0 = time.monotonic()
        for i, name in enumerate(materials):
            t = time.monotonic()
            if integrator == "adding-doubling":
                entry = doc["materials"][name] = adding_doubling_material(name, args.n, thickness_mm, nodes)
                errors = "quadrature_error"
                made = {"quad_points": IAD_QUAD_POINTS, "error_from_quad_points": 2 * IAD_QUAD_POINTS}
            else:
                entry = doc["materials"][name] = trace_material(name, geometry, params, args.n, thickness_mm, nodes,
                                                                args.paths, args.photons, args.seed + i,
                                                                polarisation)
                errors = "stderr"
                made = {"paths_per_node": args.paths, "inscatter_photons": args.photons, "seed": args.seed}
            print(f"{path.name}: {name} by the {integrator} at {len(nodes)} nodes in {time.monotonic() - t:.0f} s "
                  f"(I {errors.replace('_', ' ')} black ≤ {max(entry[errors + '_black']):.1e}, white ≤ "
                  f"{max(entry[errors + '_white']):.1e})", flush=True)
            doc.update({"format_version": FORMAT_VERSION, "geometry": geometry, "n": args.n,
                        "thickness_mm": thickness_mm, "geometry_hash": content_hash(params),
                        "integrator": integrator, "polarisation": polarisation})
            if "provenance" not in doc or not (args.material or args.twin_mixtures):  # a subset: its entries say
                doc["provenance"] = {"tool": "tools/make_twin_observables.py", "trimeter_version": __version__,
                                     **made, "step_nm": step_nm,
                                     "written_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}
            path.write_text(json.dumps(doc, indent=None, separators=(",", ":")) + "\n")  # after each: resumable
        print(f"{path.name}: {len(materials)} materials in {time.monotonic() - t0:.0f} s, "
              f"{path.stat().st_size / 1e3:.0f} kB", flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except InputError as exc:
        sys.exit(f"make_twin_observables: {exc}")
