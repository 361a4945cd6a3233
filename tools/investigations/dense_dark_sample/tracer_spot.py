"""Tracer with a different detector spot (mm diameter).
usage: tracer_spot.py out.json alpha sigma_t g n_paths seeds spot_mm"""

from typing import Any

import sys
import json
import math
import dataclasses
from trimeter.forward.transport import Stack, k_max_for, trace_column
from trimeter.model.response import background_response
from trimeter.geometry import load_geometry

out, alpha, sigma_t, g, N = sys.argv[1], *map(float, sys.argv[2:5]), int(sys.argv[5])
seeds = [int(s) for s in sys.argv[6].split(",")]
spot = float(sys.argv[7])
stack = Stack.from_recipe("device", load_geometry("device"), 1.5, 0.4)
stack = dataclasses.replace(stack, detector_half_side=spot * math.sqrt(math.pi) / 4)
res: dict[str, Any] = {"alpha": alpha, "sigma_t": sigma_t, "g": g, "n_paths": N, "spot_mm": spot, "runs": []}
for s in seeds:
    tally = trace_column(stack, sigma_t, g, N, s, k_max_for(0.999, 1e-5))
    A, B, C = (float(v[0]) for v in tally.abc([alpha]))
    row = {
        "seed": s,
        "I_0.02": float(background_response(A, B, C, 0.02)),
        "se_0.02": float(tally.stderr([alpha], 0.02)[0]),
    }
    res["runs"].append(row)
    print(row, flush=True)
    json.dump(res, open(out, "w"), indent=1)
