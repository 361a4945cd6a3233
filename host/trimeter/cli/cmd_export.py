"""`trimeter export RESULT --to mitsuba|pbrt|blender|rgb [-o DIR]`: a measured material for a renderer.

RESULT: a measurement directory or a parameters file from `trimeter fit -o` (CSV or JSON). The files and
what they mean: trimeter.results.export. Every export writes provenance.json beside its files.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from trimeter.validation import require_number


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("export", help="write a measured material for Mitsuba, PBRT-v4, Blender or RGB renderers",
                              description=__doc__)
    p.add_argument("result", help="measurement directory or parameters file (CSV/JSON)")
    p.add_argument("--to", required=True, choices=("mitsuba", "pbrt", "blender", "rgb"), dest="fmt")
    p.add_argument("-o", "--output", help="output directory (default: RESULT/export-FORMAT for a measurement "
                                          "directory, else RESULT's name + -FORMAT next to it)")
    p.add_argument("--step-nm", default="5", help="spectral resampling step of mitsuba/pbrt spectra "
                                                  "(window means; 0: the measured bins), default 5")
    p.add_argument("--reference-thickness", help="rgb/blender: thickness [mm] at which the RGB coefficients reproduce "
                                                 "the measured colour (default: the measured sample's, else 1)")
    p.add_argument("--illuminant", default="D65", help="rgb/blender: CIE illuminant of the conversion, default D65")
    p.add_argument("--scene-unit-mm", help="millimetres per scene unit (default: 1 for mitsuba/pbrt/rgb, "
                                           "1000 for blender's metres)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from trimeter.results.export import export
    from trimeter.results.reader import load_result

    step = require_number("--step-nm", args.step_nm, lo=0.0, hi=100.0)
    thickness = (require_number("--reference-thickness", args.reference_thickness, lo=0.0, lo_open=True, hi=1e4)
                 if args.reference_thickness is not None else None)
    unit = (require_number("--scene-unit-mm", args.scene_unit_mm, lo=0.0, lo_open=True, hi=1e9)
            if args.scene_unit_mm is not None else None)
    result = load_result(args.result)
    if thickness is None:
        thickness = result.measured_thickness_mm() or 1.0
    source = Path(args.result)
    if args.output:
        out = Path(args.output)
    elif source.is_dir():
        out = source / f"export-{args.fmt}"
    else:
        out = source.with_name(f"{source.stem}-{args.fmt}")
    provenance = export(result, args.fmt, out, step_nm=step, reference_thickness_mm=thickness,
                        illuminant=args.illuminant, scene_unit_mm=unit)
    print(f"{args.fmt}: {', '.join(provenance['files'])} + provenance.json in {out}")
    kept = provenance.get("gamut_saturation", {})
    if any(v < 1 for v in kept.values()):
        print("note: the transmittance colour at the reference thickness lies outside sRGB; desaturated towards its "
              "luminance to fit (saturation kept: " + ", ".join(f"{k} {v:.0%}" for k, v in kept.items()) + "); a "
              "thinner --reference-thickness keeps more")
    if args.fmt == "mitsuba":
        print(f"note: {provenance['spectral_variants']}")
    return 0
