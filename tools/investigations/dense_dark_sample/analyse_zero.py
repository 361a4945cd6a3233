"""Zero-offset renders (zero_eps.py) vs the shipped scene and the tracer.
usage: analyse_zero.py zero_json [zero_json ...] -- tracer_json [...]"""

from typing import Any

import sys
import json
import math
import numpy as np

args = sys.argv[1:]
cut = args.index("--")
zs, ts = args[:cut], args[cut + 1 :]
B: dict[str, dict[int, np.ndarray]] = {}
meta: dict[str, Any] = {}
for f in zs:
    r = json.load(open(f))
    meta = meta or r
    for k, v in r["batches"].items():
        var, seed = k.split("|")
        B.setdefault(var, {})[int(seed)] = np.array(v)
out: dict[str, Any] = {"variants": {}, "differences": {}}
for var, d in B.items():
    seeds = sorted(d)
    y = np.concatenate([d[s] for s in seeds])
    out["variants"][var] = {
        "seeds": seeds,
        "spp_total": meta["spp"] * len(seeds),
        "I": y.mean(),
        "se": y.std(ddof=1) / math.sqrt(len(y)),
    }
    print(
        f"{var:22s} seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}x{meta['spp'] / 1e6:.1f}M): "
        f"I = {y.mean():.6f} ± {y.std(ddof=1) / math.sqrt(len(y)):.6f}"
    )
base = "1.0:0.0:0.0"
for var, d in B.items():
    if var == base or base not in B:
        continue
    common = sorted(set(d) & set(B[base]))
    if not common:
        continue
    diff = np.concatenate([d[s] - B[base][s] for s in common])
    print(
        f"  {var} − shipped scene (same seeds {common[0]}..{common[-1]}): "
        f"{diff.mean():+.6f} ± {diff.std(ddof=1) / math.sqrt(len(diff)):.6f}"
    )
    out["differences"][var] = {"seeds": common, "d": diff.mean(), "se": diff.std(ddof=1) / math.sqrt(len(diff))}
tr = []
for f in ts:
    for u in json.load(open(f))["runs"]:
        tr.append((u["I_0.02"], u["se_0.02"]))
if tr:
    I = np.array([a for a, _ in tr])
    se = np.array([b for _, b in tr])
    w = 1 / se**2
    m, s = (I * w).sum() / w.sum(), 1 / math.sqrt(w.sum())
    print(f"tracer: {len(tr)} seeds: {m:.6f} ± {s:.6f} (spread se {I.std(ddof=1) / math.sqrt(len(I)):.6f})")
    out["tracer"] = {"n": len(tr), "I": m, "se": s, "spread_se": I.std(ddof=1) / math.sqrt(len(I))}
    for var, v in out["variants"].items():
        d = m - v["I"]
        e = math.hypot(s, v["se"])
        print(f"  tracer − {var}: {d:+.6f} ± {e:.6f} ({100 * d / v['I']:+.2f} %, z {d / e:+.1f})")
json.dump(out, open(zs[-1].replace(".json", "_analysis.json"), "w"), indent=1)
