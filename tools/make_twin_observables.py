"""Trace the twin's virtual samples directly (no appearance map): host/trimeter/data/twin_observables/.

    .venv/bin/python tools/make_twin_observables.py                      # the default set-ups, all materials
    .venv/bin/python tools/make_twin_observables.py --setup device:0.4 --paths 2097152

Per set-up (geometry preset, n, ℓ) and catalogue material, at wavelength nodes every --step-nm over the
spectrometer's range: one tracer column (trimeter.forward.transport.trace_column) at the material's own σt and g,
evaluated at its own α → A, B, C; for the device, the collimated beam's in-scattering from
trimeter.forward.transport.inscatter_tracer's direct tracer → L. The nodes of one material share a seed (common random
numbers), so the Monte Carlo error varies smoothly with λ. See trimeter.twin.traced for how the twin uses it.
Each material records its paths and seed; the file's provenance is the last run over the whole catalogue
(a run over some materials or mixtures, --material / --twin-mixtures, adds to the file and leaves it).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime, timezone

import numpy as np

from trimeter import __version__
from trimeter.forward.transport.inscatter_tracer import traced_log1p_ratio
from trimeter.geometry import load_geometry
from trimeter.forward.transport import Stack, k_max_for, trace_column
from trimeter.twin.optics import catalogue_entry, material_names, material_spectra
from trimeter.twin.traced import DATA_DIR, FORMAT_VERSION, content_hash, setup_name

DEFAULT_SETUPS = ("device:0.4", "device:0.8", "ideal:0.4")  # the shipped device maps' and the HIL map's
TRUNCATION = 1e-5


def trace_material(name: str, geometry: str, params: dict, n: float, thickness_mm: float, nodes, paths: int,
                   photons: int, seed: int) -> dict:
    s = material_spectra(name, nodes)
    stack = Stack.from_recipe(geometry, params, n, thickness_mm)
    k_max = k_max_for(float(s["alpha"].max()), TRUNCATION)
    out: dict[str, list[float]] = {k: [] for k in ("A", "B", "C", "L", "stderr_black", "stderr_white")}
    for alpha, sigma_t, g in zip(s["alpha"], s["sigma_t"], s["g"], strict=True):
        tally = trace_column(stack, float(sigma_t), float(g), paths, seed, k_max)
        A, B, C = (float(v[0]) for v in tally.abc([alpha]))
        out["A"].append(A)
        out["B"].append(B)
        out["C"].append(C)
        out["stderr_black"].append(float(tally.stderr([alpha], 0.03)[0]))
        out["stderr_white"].append(float(tally.stderr([alpha], 0.99)[0]))
        out["L"].append(float(traced_log1p_ratio([alpha], float(sigma_t), float(g), thickness_mm, n, params,
                                                 photons, seed)[0]) if geometry == "device" else 0.0)
    return {"material_hash": content_hash(catalogue_entry(name)), "paths_per_node": paths, "seed": seed,
            "wavelength_nm": [float(v) for v in nodes], **{k: [float(f"{v:.7g}") for v in vals]
                                                            for k, vals in out.items()}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--setup", action="append", help="GEOMETRY:THICKNESS_MM (repeatable; default: "
                   + ", ".join(DEFAULT_SETUPS) + ")")
    p.add_argument("--n", type=float, default=1.5, help="the samples' refractive index")
    p.add_argument("--material", action="append", help="only these materials (default: all); a mixture by volume "
                                                       "fractions is MATERIAL:F+MATERIAL:F")
    p.add_argument("--twin-mixtures", action="store_true",
                   help="the mixtures `trimeter library mixtures --twin` measures, instead of the catalogue")
    p.add_argument("--paths", type=int, default=1 << 21, help="detector paths per wavelength node")
    p.add_argument("--photons", type=int, default=40_000, help="collimated in-scattering photons per node (device)")
    p.add_argument("--step-nm", type=float, default=20.0)
    p.add_argument("--range-nm", type=float, nargs=2, default=(340.0, 1000.0))
    p.add_argument("--seed", type=int, default=7)
    args = p.parse_args(argv)
    nodes = np.arange(args.range_nm[0], args.range_nm[1] + 1e-9, args.step_nm)
    if args.twin_mixtures:
        from trimeter.library.mixtures import default_twin_mixtures, mixture_label

        materials = [mixture_label(m) for m in default_twin_mixtures()]
    else:
        materials = args.material or list(material_names())
    DATA_DIR.mkdir(parents=True, exist_ok=True)
    for setup in args.setup or DEFAULT_SETUPS:
        geometry, _, thickness = setup.partition(":")
        thickness_mm = float(thickness)
        params = load_geometry(geometry)
        path = DATA_DIR / f"{setup_name(geometry, args.n, thickness_mm)}.json"
        doc = json.loads(path.read_text()) if path.is_file() else {"materials": {}}
        t0 = time.monotonic()
        for i, name in enumerate(materials):
            t = time.monotonic()
            doc["materials"][name] = trace_material(name, geometry, params, args.n, thickness_mm, nodes, args.paths,
                                                    args.photons, args.seed + i)
            print(f"{path.name}: {name} traced at {len(nodes)} nodes in {time.monotonic() - t:.0f} s "
                  f"(I stderr black ≤ {max(doc['materials'][name]['stderr_black']):.1e}, white ≤ "
                  f"{max(doc['materials'][name]['stderr_white']):.1e})", flush=True)
            doc.update({"format_version": FORMAT_VERSION, "geometry": geometry, "n": args.n,
                        "thickness_mm": thickness_mm, "geometry_hash": content_hash(params)})
            if "provenance" not in doc or not (args.material or args.twin_mixtures):  # a subset: its entries say
                doc["provenance"] = {"tool": "tools/make_twin_observables.py", "trimeter_version": __version__,
                                     "paths_per_node": args.paths, "inscatter_photons": args.photons,
                                     "step_nm": args.step_nm, "seed": args.seed,
                                     "written_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}
            path.write_text(json.dumps(doc, indent=None, separators=(",", ":")) + "\n")  # after each: resumable
        print(f"{path.name}: {len(materials)} materials in {time.monotonic() - t0:.0f} s, "
              f"{path.stat().st_size / 1e3:.0f} kB", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
