"""All figures for the dense sample combined (independent seed sets only), to DIR/final.json (DIR: run.sh's)."""

import json
import os
import math
import numpy as np

DIR = os.environ.get("DENSE_DIR", "out/dense-dark-sample")  # run.sh's output directory


def load_batches(files, var):
    d = {}
    for f in files:
        r = json.load(open(f))
        for k, v in r["batches"].items():
            kv, s = k.split("|")
            if kv == var and np.any(v):
                d[int(s)] = np.array(v)
    return d


def est(d):
    y = np.concatenate([d[s] for s in sorted(d)])
    return y.mean(), y.std(ddof=1) / math.sqrt(len(y)), len(d)


out = {}
zero = load_batches(
    [f"{DIR}/zero_dense2.json", f"{DIR}/zero_dense3.json", f"{DIR}/zero_dense4.json"], "1000.0:-0.55:0.02"
)
m, s, k = est(zero)
out["render_zero_eps"] = {"I": m, "se": s, "seeds": sorted(zero), "spp_per_seed": 8388608}
print(
    f"Mitsuba zero-offset render (S=1000, spot 0.02 mm), {k} seeds x 8.4M ({min(zero)}..{max(zero)}): "
    f"{m:.6f} ± {s:.6f}"
)
base = load_batches([f"{DIR}/zero_dense.json", f"{DIR}/zero_dense3.json"], "1.0:0.0:0.0")
m0, s0, k0 = est(base)
out["render_shipped_scene"] = {"I": m0, "se": s0, "seeds": sorted(base)}
print(f"Mitsuba shipped scene (no correction), {k0} seeds x 8.4M: {m0:.6f} ± {s0:.6f}")
common = sorted(set(zero) & set(base))
d = np.concatenate([zero[c] - base[c] for c in common])
print(f"  zero-eps − shipped (CRN, {len(common)} seeds): {d.mean():+.6f} ± {d.std(ddof=1) / math.sqrt(len(d)):.6f}")
out["zero_minus_shipped"] = {"d": d.mean(), "se": d.std(ddof=1) / math.sqrt(len(d)), "seeds": common}
runs = []
for f in [f"{DIR}/tracer_dense.json", f"{DIR}/tracer_dense2.json", f"{DIR}/tracer_dense3.json"]:
    runs += json.load(open(f))["runs"]
I = np.array([u["I_0.02"] for u in runs])
se = np.array([u["se_0.02"] for u in runs])
w = 1 / se**2
tm, ts = (I * w).sum() / w.sum(), 1 / math.sqrt(w.sum())
print(
    f"tracer, {len(I)} seeds x 8.4M ({[u['seed'] for u in runs]}): {tm:.6f} ± {ts:.6f} "
    f"(spread-based {I.std(ddof=1) / math.sqrt(len(I)):.6f});"
    f" I(0.9) − I(0.02) = {np.mean([u['I_0.9'] - u['I_0.02'] for u in runs]):.2e}"
)
out["tracer"] = {
    "I": tm,
    "se": ts,
    "seeds": [u["seed"] for u in runs],
    "n_paths": 8388608,
    "I09_minus_I002": float(np.mean([u["I_0.9"] - u["I_0.02"] for u in runs])),
}
parts = [json.load(open(f)) for f in (f"{DIR}/indep_dense.json", f"{DIR}/indep_dense2.json")]
ch = [c for p in parts for c in p["chunks"]]
ind = {"I": float(np.mean([c["I"] for c in ch])), "se": math.sqrt(sum(c["se"] ** 2 for c in ch)) / len(ch)}
for p in parts:
    print(f"  independent MC seed {p['seed']}: {p['I']:.6f} ± {p['se']:.6f}")
print(f"independent float64 MC (indep.py), {len(ch)} x 2M paths, seeds 11, 12: {ind['I']:.6f} ± {ind['se']:.6f}")
out["independent_mc"] = {"I": ind["I"], "se": ind["se"]}
for name, (a, b) in {
    "tracer − zero-eps render": ((tm, ts), (m, s)),
    "independent MC − zero-eps render": ((ind["I"], ind["se"]), (m, s)),
    "tracer − independent MC": ((tm, ts), (ind["I"], ind["se"])),
}.items():
    dd, ee = a[0] - b[0], math.hypot(a[1], b[1])
    print(f"  {name}: {dd:+.6f} ± {ee:.6f} ({100 * dd / b[0]:+.3f} %, z {dd / ee:+.1f})")
    out[name] = {"d": dd, "se": ee, "rel_percent": 100 * dd / b[0], "z": dd / ee}
json.dump(out, open(f"{DIR}/final.json", "w"), indent=1)
