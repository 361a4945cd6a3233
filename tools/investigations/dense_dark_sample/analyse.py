"""Analyse a shift series (series.py JSON) against tracer JSONs.
usage: analyse.py series.json tracer.json [more tracer json]"""

import sys
import json
import math
import numpy as np

r = json.load(open(sys.argv[1]))
offsets, seeds, top = r["offsets"], r["seeds"], r["top"]
# replicates: (seed, batch) pairs share random numbers across offsets (common random numbers)
Y = np.array([np.concatenate([r["batches"][f"{z}|{s}"] for s in seeds]) for z in offsets]).T  # (reps, nz)
nrep = Y.shape[0]
mean = Y.mean(0)
cov = np.cov(Y.T) / nrep
out = {"file": sys.argv[1], "replicates": nrep, "spp_per_offset": r["spp_per_seed"] * len(seeds), "points": []}
print(
    f"{sys.argv[1]}: alpha={r['alpha']} sigma_t={r['sigma_t']} rho={r['rho']} "
    f"spp/offset={r['spp_per_seed'] * len(seeds) / 1e6:.0f}M seeds={seeds}"
)
for z, m, s in zip(offsets, mean, np.sqrt(np.diag(cov)), strict=True):
    print(
        f"  z={z:5.1f}  x=1+top+z={1 + top + z:6.2f}  I={m:.6f} ± {s:.6f}   I(z)-I(0)={m - mean[0]:+.6f} ± "
        f"{np.sqrt(cov[0, 0] + np.diag(cov)[offsets.index(z)] - 2 * cov[0, offsets.index(z)]):.6f}"
    )
    out["points"].append({"z": z, "I": m, "se": s})


def gls(xs, deg, idx=None):
    idx = list(range(len(xs))) if idx is None else idx
    X = np.vander(np.asarray(xs)[idx], deg + 1, increasing=True)
    C = cov[np.ix_(idx, idx)]
    Ci = np.linalg.inv(C)
    P = np.linalg.inv(X.T @ Ci @ X)
    beta = P @ X.T @ Ci @ mean[idx]
    res = mean[idx] - X @ beta
    chi2 = float(res @ Ci @ res)
    return beta, P, chi2, len(idx) - deg - 1


for label, xs in (
    ("x = 1+top+z (shipped)", [1 + top + z for z in offsets]),
    (
        "x = eps proxy E[1+max|p|] at sample face",
        [1.6615 if z == 0 else max(1.6615, 1 + (top - 0.15) + z) for z in offsets],
    ),
):
    print(" ", label)
    for deg in (1, 2):
        for name, idx in (("all", None), ("z<=20", [i for i, z in enumerate(offsets) if z <= 20])):
            beta, P, chi2, dof = gls(xs, deg, idx)
            print(
                f"    deg {deg} {name:6s}: I(x=0) = {beta[0]:.6f} ± {math.sqrt(P[0, 0]):.6f}  slope={beta[1]:.3e}"
                + (f" curv={beta[2]:.3e}±{math.sqrt(P[2, 2]):.1e}" if deg == 2 else "")
                + f"  chi2/dof={chi2:.1f}/{dof}"
            )
            out.setdefault("fits", []).append(
                {
                    "x": label,
                    "deg": deg,
                    "subset": name,
                    "I0": beta[0],
                    "se": math.sqrt(P[0, 0]),
                    "coef": beta.tolist(),
                    "chi2": chi2,
                    "dof": dof,
                }
            )
# the shipped two-point extrapolation with common seeds
if 10.0 in offsets:
    i10 = offsets.index(10.0)
    k = (1 + top) / 10
    v = (1 + k) * Y[:, 0] - k * Y[:, i10]
    print(f"  shipped 2-point (z=0,10; k={k:.3f}) with CRN: {v.mean():.6f} ± {v.std(ddof=1) / math.sqrt(nrep):.6f}")
    out["two_point"] = {"I": v.mean(), "se": v.std(ddof=1) / math.sqrt(nrep)}
tr = []
for f in sys.argv[2:]:
    t = json.load(open(f))
    runs = t["runs"]
    I = np.array([u["I_0.02"] for u in runs])
    se = np.array([u["se_0.02"] for u in runs])
    print(
        f"  tracer {f}: seeds {[u['seed'] for u in runs]}, {t['n_paths'] / 1e6:.1f}M each: "
        + ", ".join(f"{a:.6f}±{b:.6f}" for a, b in zip(I, se, strict=True))
    )
    w = 1 / se**2
    m = (I * w).sum() / w.sum()
    s = 1 / math.sqrt(w.sum())
    print(
        f"    mean {m:.6f} ± {s:.6f} (spread-based se {I.std(ddof=1) / math.sqrt(len(I)):.6f}); "
        f"I(0.9) mean {np.mean([u['I_0.9'] for u in runs]):.6f}"
    )
    tr.append((m, s))
    out.setdefault("tracer", []).append({"file": f, "I": m, "se": s})
if tr and "two_point" in out:
    m, s = tr[0]
    for name, (I, e) in [("two-point", (out["two_point"]["I"], out["two_point"]["se"]))] + [
        (f"fit deg{f['deg']} {f['subset']} [{f['x'][:6]}]", (f["I0"], f["se"])) for f in out["fits"]
    ]:
        d = m - I
        de = math.hypot(s, e)
        print(f"  tracer − {name:28s}: {d:+.6f} ± {de:.6f}  ({100 * d / I:+.2f} %, z {d / de:+.1f})")
json.dump(out, open(sys.argv[1].replace(".json", "_analysis.json"), "w"), indent=1)
