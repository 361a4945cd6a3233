"""`trimeter predict`: the spectral reflectance and sRGB colour of a slab of any thickness, on black and on white.

  trimeter predict RESULT --thickness 5                          # one measured material
  trimeter predict A B --fractions 0.3 0.7 --thickness 5 -o DIR  # a mixture by volume fractions
  trimeter predict --checker A B C D --thickness 5 -o DIR        # a color checker of the materials and their mixtures

A material is a measurement directory, a parameters file (`trimeter fit -o`) or `sample:NAME` (a virtual material
of the twin, `trimeter sim --list-materials`). Traced per wavelength node (trimeter.prediction), a few seconds each.
"""

from __future__ import annotations

import json
from itertools import combinations
from pathlib import Path

from trimeter.errors import InputError
from trimeter.validation import require_number


def register(subparsers) -> None:
    p = subparsers.add_parser("predict", help="predicted colour and reflectance of a thick slab or a mixture",
                              description=__doc__, formatter_class=__import__("argparse").RawDescriptionHelpFormatter)
    p.add_argument("materials", nargs="+", help="measurement directories, parameters files or sample:NAME")
    p.add_argument("--thickness", required=True, help="slab thickness [mm]")
    p.add_argument("--fractions", nargs="+", help="volume fractions of the materials (a mixture; normalised)")
    p.add_argument("--checker", action="store_true", help="a grid: each material and their pairwise mixtures")
    p.add_argument("--steps", default="3", help="--checker: mixing steps between two materials (default 3: "
                                                "2:1 and 1:2)")
    p.add_argument("--geometry", choices=("ideal", "device"), default="ideal",
                   help="ideal: slab in air on a Lambertian background under a uniform sky (default); device: "
                        "the instrument")
    p.add_argument("--n", default="1.5", help="refractive index of the slab (default 1.5)")
    p.add_argument("--rho-black", default="0", help="black background reflectance (default 0)")
    p.add_argument("--rho-white", default="1", help="white background reflectance (default 1)")
    p.add_argument("--paths", default=str(1 << 16), help="tracer paths per wavelength node (default 65536)")
    p.add_argument("-o", "--output", help="directory for the spectra CSV and the swatch PNG")
    p.add_argument("--json", action="store_true", help="print one JSON object (single prediction)")
    p.set_defaults(func=run)


def _options(args) -> dict:
    return {"thickness_mm": require_number("--thickness", args.thickness, lo=0.0, lo_open=True, hi=1e4),
            "n": require_number("--n", args.n, lo=1.0, hi=4.0),
            "rho_black": require_number("--rho-black", args.rho_black, lo=0.0, hi=1.0),
            "rho_white": require_number("--rho-white", args.rho_white, lo=0.0, hi=1.0),
            "paths": int(require_number("--paths", args.paths, lo=1024, hi=1 << 28)), "geometry": args.geometry}


def _checker_patches(materials, names, steps: int):
    from trimeter.prediction import mixture

    patches = [(name, m) for name, m in zip(names, materials, strict=True)]
    for (i, a), (j, b) in combinations(enumerate(materials), 2):
        for k in range(1, steps):
            f = k / steps
            patches.append((f"{names[i]} {1 - f:.2g}+{names[j]} {f:.2g}", mixture([a, b], [1 - f, f])))
    return patches


def run(args) -> int:
    from trimeter.prediction import draw_swatches, hex_colour, load_material, mixture, predict_slab, write_spectra_csv

    opts = _options(args)
    loaded = [load_material(spec) for spec in args.materials]
    materials, names = [m for m, _ in loaded], [n for _, n in loaded]
    out = Path(args.output) if args.output else None
    if args.checker:
        if args.fractions:
            raise InputError("--checker mixes the materials itself: drop --fractions")
        if out is None:
            raise InputError("--checker needs -o DIR (it writes checker.png and checker.csv)")
        steps = int(require_number("--steps", args.steps, lo=1, hi=10))
        patches = _checker_patches(materials, names, steps)
        rows = []
        for label, m in patches:
            p = predict_slab(m, **opts)
            rows.append((label, p))
            print(f"{label:40s} on white {hex_colour(p.srgb_white)}  on black {hex_colour(p.srgb_black)}  "
                  f"({p.info['seconds']:.1f} s)", flush=True)
        title = (f"predicted, {opts['thickness_mm']:g} mm slabs ({opts['geometry']} geometry, D65): top on white, "
                 "bottom on black")
        out.mkdir(parents=True, exist_ok=True)
        write_spectra_csv(out / "checker.csv", rows)
        draw_swatches(out / "checker.png", rows, columns=max(4, len(materials)), title=title)
        print(f"checker: {out / 'checker.png'}, spectra: {out / 'checker.csv'}")
        return 0
    fractions = None
    if args.fractions:
        fractions = [require_number("--fractions", f, lo=0.0, hi=1e6) for f in args.fractions]
        if len(fractions) != len(materials):
            raise InputError(f"--fractions: {len(fractions)} given for {len(materials)} materials")
    material = mixture(materials, fractions)
    label = " + ".join(f"{n} {f:g}" for n, f in zip(names, fractions, strict=True)) if fractions else names[0]
    p = predict_slab(material, **opts)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_spectra_csv(out / "prediction.csv", [(label, p)])
        draw_swatches(out / "prediction.png", [(label, p)], columns=1, title=f"{opts['thickness_mm']:g} mm")
    if args.json:
        print(json.dumps({"material": label, **p.info, "wavelength_nm": p.wavelengths_nm.tolist(),
                          "on_black": p.on_black.tolist(), "on_white": p.on_white.tolist(),
                          "stderr_black": p.stderr_black.tolist(), "stderr_white": p.stderr_white.tolist(),
                          "srgb_hex_black": hex_colour(p.srgb_black), "srgb_hex_white": hex_colour(p.srgb_white)}))
        return 0
    print(f"{label}, {opts['thickness_mm']:g} mm slab ({opts['geometry']} geometry, n {opts['n']:g}), traced at "
          f"{p.info['nodes']} wavelengths in {p.info['seconds']:.1f} s:")
    print(f"  on white (ρ {opts['rho_white']:g}): sRGB {hex_colour(p.srgb_white)}   "
          f"on black (ρ {opts['rho_black']:g}): sRGB {hex_colour(p.srgb_black)}")
    print(f"  {'λ nm':>6} {'R black':>9} {'R white':>9}")
    for i in range(0, len(p.wavelengths_nm), 5):
        print(f"  {p.wavelengths_nm[i]:6.0f} {p.on_black[i]:9.4f} {p.on_white[i]:9.4f}")
    if out is not None:
        print(f"spectra: {out / 'prediction.csv'}, swatch: {out / 'prediction.png'}")
    return 0
