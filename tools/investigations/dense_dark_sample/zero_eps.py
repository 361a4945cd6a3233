"""Render the device scene scaled by S (coordinates × S, σt / S) and shifted by dz (in mm, before scaling) with an
optional smaller detector spot: Mitsuba's ray offset eps = RayEpsilon(1 + max|P|) in scene units is, in mm,
RayEpsilon(1/S + max|p|), so S = 1000 with the sample's front face at the origin and a small spot makes it
~50x smaller than in the shipped scene. Common seeds across variants.
usage: zero_eps.py out.json alpha sigma_t g rho spp seeds variants
variants: 'S:dz:spot;S:dz:spot;...' (spot in mm, 0 = the shipped 2 mm)"""

from typing import Any

import sys
import json
import time
import copy
import numpy as np
from trimeter.forward.mitsuba_env import mitsuba
from trimeter.forward.phase import register_phases
from trimeter.forward.scenes import scene_dict, _Transform, reflectance_scale, PARAM_KEYS
from trimeter.forward.render import to_mitsuba, render_pixel, _integrator
from trimeter.geometry import load_geometry

out, alpha, sigma_t, g, rho, spp = sys.argv[1], *map(float, sys.argv[2:6]), int(sys.argv[6])
seeds = [int(s) for s in sys.argv[7].split(",")]
variants = [tuple(float(v) for v in s.split(":")) for s in sys.argv[8].split(";")]
n, ell = 1.5, 0.4
mi = mitsuba()
register_phases(mi)


def transformed(scene, S, dz):
    M = np.diag([S, S, S, 1.0])
    M[2, 3] = S * dz
    out = {}
    for key, value in scene.items():
        if isinstance(value, dict):
            value = dict(value)
            if isinstance(value.get("to_world"), _Transform):
                value["to_world"] = _Transform(M @ value["to_world"].matrix)
            assert value.get("type") != "radiancemeter"
            if value.get("type") == "orthographic":
                value["far_clip"] = 1e4 * S  # the default 1e4 (scene units) would clip the scaled scene
        out[key] = value
    return out


res: dict[str, Any] = {"alpha": alpha, "sigma_t": sigma_t, "g": g, "rho": rho, "spp": spp, "seeds": seeds,
                       "batches": {}}
for S, dz, spot in variants:
    geo = copy.deepcopy(load_geometry("device"))
    if spot > 0:
        geo["detector"]["spot_diameter_mm"] = spot
    d = transformed(scene_dict(geo, alpha, sigma_t / S, g, n, ell, rho), S, dz)
    scene = mi.load_dict(to_mitsuba(d, mi))
    p = mi.traverse(scene)
    for name, value in (("alpha", alpha), ("sigma_t", sigma_t / S), ("g", g), ("rho", rho)):
        p[PARAM_KEYS[name]] = value
    p.update()
    integ, _ = _integrator(mi, alpha)
    scale = reflectance_scale(geo)
    for s in seeds:
        t = time.time()
        b = render_pixel(scene, integ, spp, s) * scale
        res["batches"][f"{S}:{dz}:{spot}|{s}"] = b.tolist()
        print(
            f"S={S} dz={dz} spot={spot} seed={s} I={b.mean():.6f} se={b.std(ddof=1) / 4:.6f} t={time.time() - t:.1f}",
            flush=True,
        )
        json.dump(res, open(out, "w"))
    del scene, p
print("done")
