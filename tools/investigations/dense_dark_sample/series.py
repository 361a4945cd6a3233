"""Render one material at several scene shifts (z_offset) with COMMON seeds (common random numbers), save batch means.
usage: series.py out.json alpha sigma_t g rho spp_per_seed seeds(comma) offsets(comma)"""

from typing import Any

import sys
import json
import time
from trimeter.forward.render import render_diffuse_batches
from trimeter.forward.scenes import top_face_z

out, alpha, sigma_t, g, rho, spp = sys.argv[1], *map(float, sys.argv[2:6]), int(sys.argv[6])
seeds = [int(s) for s in sys.argv[7].split(",")]
offsets = [float(s) for s in sys.argv[8].split(",")]
ell, n = 0.4, 1.5
res: dict[str, Any] = {
    "alpha": alpha,
    "sigma_t": sigma_t,
    "g": g,
    "rho": rho,
    "n": n,
    "ell": ell,
    "spp_per_seed": spp,
    "seeds": seeds,
    "offsets": offsets,
    "top": top_face_z("device", ell),
    "batches": {},
}
for z in offsets:
    for s in seeds:
        t = time.time()
        b = render_diffuse_batches("device", alpha, sigma_t, g, n, ell, rho, spp, s, z_offset=z)
        res["batches"][f"{z}|{s}"] = b.tolist()
        print(f"z={z} seed={s} I={b.mean():.6f} se={b.std(ddof=1) / 4:.6f} t={time.time() - t:.1f}s", flush=True)
    json.dump(res, open(out, "w"))
print("done")
