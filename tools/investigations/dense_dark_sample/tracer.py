"""Tracer for one material: independent seeds, I at rho 0.02 and 0.9.
usage: tracer.py out.json alpha sigma_t g n_paths seeds [orders]"""

from typing import Any

import sys
import json
import time
from trimeter.forward.transport import Stack, k_max_for, trace_column
from trimeter.model.response import background_response
from trimeter.geometry import load_geometry

out, alpha, sigma_t, g, N = sys.argv[1], *map(float, sys.argv[2:5]), int(sys.argv[5])
seeds = [int(s) for s in sys.argv[6].split(",")]
orders = int(sys.argv[7]) if len(sys.argv) > 7 else None
ell = 0.4
stack = Stack.from_recipe("device", load_geometry("device"), 1.5, ell)
res: dict[str, Any] = {
    "alpha": alpha,
    "sigma_t": sigma_t,
    "g": g,
    "n_paths": N,
    "k_max": k_max_for(0.999, 1e-5),
    "orders": orders,
    "runs": [],
}
for s in seeds:
    t = time.time()
    kw: dict[str, Any] = {"background_orders": orders} if orders else {}
    tally = trace_column(stack, sigma_t, g, N, s, k_max_for(0.999, 1e-5), **kw)
    A, B, C = (float(v[0]) for v in tally.abc([alpha]))
    row = {
        "seed": s,
        "A": A,
        "B": B,
        "C": C,
        "truncated": int(tally.truncated),
        "trunc_bound": float(tally.truncation_bound(0.999)),
    }
    for rho in (0.02, 0.9):
        row[f"I_{rho}"] = float(background_response(A, B, C, rho))
        row[f"se_{rho}"] = float(tally.stderr([alpha], rho)[0])
    row["sec"] = time.time() - t
    res["runs"].append(row)
    print(row, flush=True)
    json.dump(res, open(out, "w"), indent=1)
