"""The calibration's white reference rendered by Mitsuba (no sample, no slides): must return rho_ref = 0.99 if the
scene's panels give the closed-form irradiance E that both the renders' and the tracer's normalisation use."""

import json
import os
import math
import numpy as np
from trimeter.forward.render import render_diffuse_batches
from trimeter.geometry import load_geometry

DIR = os.environ.get("DENSE_DIR", "out/dense-dark-sample")  # run.sh's output directory

bare = {**load_geometry("device"), "cover_slides": False}
rows = []
for seed in (401, 402, 403, 404):
    b = render_diffuse_batches(bare, 0.5, 0.0, 0.0, 1.0, 0.5, 0.99, 1 << 23, seed)
    rows.append(b.tolist())
    print(seed, b.mean(), b.std(ddof=1) / 4, flush=True)
y = np.concatenate(rows)
res = {"I": y.mean(), "se": y.std(ddof=1) / math.sqrt(len(y)), "ratio_to_0.99": y.mean() / 0.99, "spp": 4 << 23}
print(res)
json.dump({"batches": rows, **res}, open(f"{DIR}/white.json", "w"), indent=1)
