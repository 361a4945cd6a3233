"""An independent float64 Monte Carlo of the device stack for a dense sample (third opinion): the laterally infinite
stack air | glass 0.15 | sample ℓ | glass 0.15 | air, panels as the tracer/scene declare them, background ignored
(ρ·B ≈ 1e-8 here). Adjoint paths from the detector in (z, μ) only (azimuthal symmetry), weight α per scattering,
exit into air scored by the exact fraction f(μ) of azimuths that meet a panel (tabulated), × (1−F0)·π/E.
usage: indep.py out.json alpha sigma_t g n_paths_per_chunk chunks seed"""

from typing import Any

import json
import os
import sys
import math
import time
import numpy as np
from trimeter.forward.transport import Stack
from trimeter.geometry import load_geometry

out, alpha, sigma_t, g = sys.argv[1], *map(float, sys.argv[2:5])
N, chunks, seed = int(sys.argv[5]), int(sys.argv[6]), int(sys.argv[7])
ell, n = 0.4, 1.5
stack = Stack.from_recipe("device", load_geometry("device"), n, ell)
planes = np.array(stack.plane_z)  # top → bottom: 0.7, 0.55, 0.15, 0
nl = np.array(stack.layer_n)  # glass, sample, glass
z_top = planes[0]


# f(μ): the fraction of azimuths from (0, 0, z_top) that meet a panel, on a fine μ grid (midpoint azimuths,
# exact to ~1e-6)
def f_table(M=20001, A=16384):
    mu = np.linspace(0, 1, M)
    phi = (np.arange(A) + 0.5) * 2 * np.pi / A
    f = np.zeros(M)
    for i0 in range(0, M, 500):
        m = mu[i0 : i0 + 500, None]
        s = np.sqrt(1 - m * m)
        dx, dy, dz = s * np.cos(phi), s * np.sin(phi), np.broadcast_to(m, (len(m), A))
        seen = np.zeros(dx.shape, bool)
        for p in stack.panels:
            c, nn = np.array(p.center), np.array(p.normal)
            denom = dx * nn[0] + dy * nn[1] + dz * nn[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((c[0]) * nn[0] + (c[1]) * nn[1] + (c[2] - z_top) * nn[2]) / denom
            hx, hy, hz = t * dx - c[0], t * dy - c[1], z_top + t * dz - c[2]
            u = hx * p.axis_u[0] + hy * p.axis_u[1] + hz * p.axis_u[2]
            v = hx * p.axis_v[0] + hy * p.axis_v[1] + hz * p.axis_v[2]
            seen |= (denom < 0) & (t > 0) & (np.abs(u) <= p.half_u) & (np.abs(v) <= p.half_v)
        f[i0 : i0 + 500] = seen.mean(1)
    return mu, f



DIR = os.environ.get("DENSE_DIR", "out/dense-dark-sample")  # run.sh's output directory

t0 = time.time()
if os.path.exists(f"{DIR}/ftable.npz"):
    d = np.load(f"{DIR}/ftable.npz")
    MU, F = d["mu"], d["f"]
else:
    MU, F = f_table()
    np.savez(f"{DIR}/ftable.npz", mu=MU, f=F)
    print("f table", time.time() - t0, "s; max f", F.max(), flush=True)


def fres(cos_i, eta):  # eta = n_t / n_i
    sin2 = (1 - cos_i**2) / eta**2
    tir = sin2 >= 1
    ct = np.sqrt(np.maximum(1 - sin2, 0))
    rs = (cos_i - eta * ct) / (cos_i + eta * ct)
    rp = (eta * cos_i - ct) / (eta * cos_i + ct)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp)), ct


F0 = ((nl[0] - 1) / (nl[0] + 1)) ** 2
weight = (1 - F0) * stack.scale
rng = np.random.default_rng(seed)
res: dict[str, Any] = {"alpha": alpha, "sigma_t": sigma_t, "g": g, "N_per_chunk": N, "seed": seed, "chunks": []}
L = len(nl)
for ch in range(chunks):
    t0 = time.time()
    z = np.full(N, z_top)
    mu = np.full(N, -1.0)
    li = np.zeros(N, int)
    w = np.ones(N)
    score = np.zeros(N)
    idx = np.arange(N)
    while len(idx):
        zi, mi, lii, wi = z[idx], mu[idx], li[idx], w[idx]
        zt, zb = planes[lii], planes[lii + 1]
        zp = np.where(mi < 0, zb, zt)
        dplane = (zp - zi) / mi
        in_s = lii == stack.sample_layer
        dsc = np.where(in_s, -np.log1p(-rng.random(len(idx))) / sigma_t, np.inf)
        sc = dsc < dplane
        # scattering
        k = np.flatnonzero(sc)
        zi[k] += dsc[k] * mi[k]
        wi[k] *= alpha
        u1, u2 = rng.random(len(k)), rng.random(len(k))
        if abs(g) > 1e-6:
            sq = (1 - g * g) / (1 - g + 2 * g * u1)
            ct = (1 + g * g - sq * sq) / (2 * g)
        else:
            ct = 1 - 2 * u1
        ct = np.clip(ct, -1, 1)
        st = np.sqrt(1 - ct * ct)
        m0 = mi[k]
        mi[k] = np.clip(m0 * ct + np.sqrt(np.maximum(1 - m0 * m0, 0)) * st * np.cos(2 * np.pi * u2), -1, 1)
        # interface
        c = np.flatnonzero(~sc)
        zi[c] = zp[c]
        up = mi[c] > 0
        n_here = nl[lii[c]]
        nxt = lii[c] + np.where(up, -1, 1)
        n_next = np.where((nxt < 0) | (nxt >= L), 1.0, nl[np.clip(nxt, 0, L - 1)])
        Fr, cos_t = fres(np.abs(mi[c]), n_next / n_here)
        refl = rng.random(len(c)) < Fr
        mi[c] = np.where(refl, -mi[c], np.where(up, cos_t, -cos_t))
        lii[c] = np.where(refl, lii[c], nxt)
        z[idx], mu[idx], li[idx], w[idx] = zi, mi, lii, wi
        # ends: out of the top (score), out of the bottom (lost), weight negligible
        top = lii < 0
        score[idx[top]] = wi[top] * np.interp(mi[top], MU, F)
        done = top | (lii >= L) | (wi < 1e-7)
        idx = idx[~done]
    I = weight * score.mean()
    se = weight * score.std(ddof=1) / math.sqrt(N)
    res["chunks"].append({"I": I, "se": se})
    print(f"chunk {ch}: I = {I:.6f} ± {se:.6f}  ({time.time() - t0:.1f}s)", flush=True)
    json.dump(res, open(out, "w"), indent=1)
Is = np.array([c["I"] for c in res["chunks"]])
ses = np.array([c["se"] for c in res["chunks"]])
res["I"] = Is.mean()
res["se"] = math.sqrt((ses**2).sum()) / len(ses)
print("total", res["I"], "±", res["se"])
json.dump(res, open(out, "w"), indent=1)
