"""Render a measured material (its exported Mitsuba medium) as a sphere on a checker plane, beside its plot.

    .venv/bin/python tools/render_medium.py RESULT_DIR [-o docs/img/measured-material.png] [--spp 64]

RESULT_DIR is a measurement directory (medium.json, figure.png). The scene is in millimetres (the medium's
scale 1): a 10 mm sphere with a smooth n = 1.5 boundary holding the medium, on a grey checker plane, under
a rectangular area light and a dim constant sky, rendered with volpath in a spectral Mitsuba variant
(llvm_ad_spectral, else scalar_spectral) so the medium stays spectral.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"


def build(mi, medium: dict, width: int, height: int, spp: int) -> dict:
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": 96, "rr_depth": 24},
        "sensor": {"type": "perspective", "fov": 32,
                   "to_world": T().look_at(origin=[0, -62, 30], target=[0, 0, 8], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "gaussian"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "sky": {"type": "constant", "radiance": {"type": "d65", "scale": 0.15}},
        "light": {"type": "rectangle",
                  "to_world": T().look_at(origin=[-30, -25, 70], target=[0, 0, 0], up=[0, 0, 1]) @ T().scale(15),
                  "emitter": {"type": "area", "radiance": {"type": "d65", "scale": 6.0}}},
        "sphere": {"type": "sphere", "center": [0, 0, 10], "radius": 10,
                   "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}, "interior": medium},
        "floor": {"type": "rectangle", "to_world": T().scale(80),
                  "bsdf": {"type": "diffuse", "reflectance": {
                      "type": "checkerboard", "color0": {"type": "rgb", "value": 0.15},
                      "color1": {"type": "rgb", "value": 0.7}, "to_uv": mi.ScalarTransform3f().scale([16, 16])}}},
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("result", type=Path)
    p.add_argument("-o", "--output", type=Path, default=Path("docs/img/measured-material.png"))
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--width", type=int, default=360)
    p.add_argument("--height", type=int, default=300)
    args = p.parse_args(argv)
    if os.path.exists(LLVM):
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", LLVM)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mitsuba as mi
    import numpy as np

    for variant in ("llvm_ad_spectral", "scalar_spectral"):
        try:
            mi.set_variant(variant)
            break
        except (ImportError, AttributeError):
            continue
    medium = json.loads((args.result / "medium.json").read_text())
    t0 = time.monotonic()
    image = mi.render(mi.load_dict(build(mi, medium, args.width, args.height, args.spp)))
    seconds = time.monotonic() - t0
    rgb = np.clip(np.asarray(mi.Bitmap(image).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                                                      srgb_gamma=True)), 0, 1)
    plot = plt.imread(args.result / "figure.png")
    fig, axes = plt.subplots(1, 2, figsize=(15, 3.9), gridspec_kw={"width_ratios": [args.width / args.height,
                                                                                    plot.shape[1] / plot.shape[0]]})
    axes[0].imshow(rgb)
    axes[0].set_title(f"10 mm sphere, Mitsuba {mi.variant()}, {args.spp} spp", fontsize=8)
    axes[1].imshow(plot)
    axes[1].set_title(f"the measurement: {args.result.name}", fontsize=8)
    for ax in axes:
        ax.set_axis_off()
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=110)
    print(f"{args.output}: rendered in {seconds:.1f} s with {mi.variant()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
