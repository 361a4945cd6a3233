"""Physics checks of the direct renders: shared by tests/forward and `trimeter forward validate`.

- `iad_agreement`: the `ideal` geometry against Prahl's adding-doubling (iadpython, a dev/test
  dependency) over random materials, both backgrounds: per-observable relative error and z-score.
- `rho_closed_form`: for one material in a geometry, fit I(ρ) = A + Bρ/(1 − Cρ) to renders at three ρ
  and compare the closed form with renders at other ρ (exact for `ideal`; a model for `device`).
All renders use deterministic seeds; the same seed at every ρ, so MC noise is largely common to them.
"""

from __future__ import annotations

import math
import time

import numpy as np

from trimeter.forward.render import render_diffuse
from trimeter.maps.appearance import background_response

# Adding-doubling with its default 4 quadrature points is off by up to 1.7 % at g = 0.5 (measured);
# 32 points converge to < 0.05 % over the map's range (16 → 32 → 64 checked).
IAD_QUAD_POINTS = 32


def random_materials(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) materials (α, σt [1/mm], g) over the map's range: σt log-uniform in [0.05, 50], g
    uniform in [0, 0.9], α half uniform in [0, 0.999] and half crowded towards 1 (1 − 10^U(−3, −1)),
    where the map is finest and the maps are used most."""
    rng = np.random.default_rng(seed)
    alpha = np.where(np.arange(count) % 2 == 0, rng.uniform(0.0, 0.999, count),
                     1.0 - 10.0 ** rng.uniform(-3, -1, count))
    sigma_t = 10.0 ** rng.uniform(math.log10(0.05), math.log10(50.0), count)
    g = rng.uniform(0.0, 0.9, count)
    return np.column_stack([alpha, sigma_t, g])


def iad_reflectance(alpha, sigma_t, g, n, thickness_mm, rho):
    """I(ρ) of the ideal geometry from adding-doubling: UR1 + UT1·ρ·UTU/(1 − ρ·URU)."""
    try:
        import iadpython
    except ImportError as exc:  # a dev dependency: the device side doesn't have it
        raise RuntimeError("the adding-doubling cross-check needs iadpython (pip install 'trimeter[dev]')") from exc
    ur1, ut1, uru, utu = iadpython.Sample(a=alpha, b=sigma_t * thickness_mm, g=g, d=thickness_mm, n=n,
                                          n_above=1.0, n_below=1.0, quad_pts=IAD_QUAD_POINTS).rt()
    rho = np.asarray(rho, dtype=float)
    return float(ur1) + float(ut1) * rho * float(utu) / (1.0 - rho * float(uru))


def iad_agreement(materials, n: float = 1.5, thickness_mm: float = 0.5, rhos=(0.02, 0.99),
                  spp: int = 262144, seed: int = 0, progress=None) -> dict:
    """Render every material in the ideal geometry at every ρ and compare with adding-doubling."""
    rows = []
    render_seconds = []
    for i, (alpha, sigma_t, g) in enumerate(np.asarray(materials, dtype=float)):
        reference = iad_reflectance(alpha, sigma_t, g, n, thickness_mm, np.asarray(rhos))
        for rho, ref in zip(rhos, np.atleast_1d(reference), strict=True):
            start = time.perf_counter()
            value, stderr = render_diffuse("ideal", alpha, sigma_t, g, n, thickness_mm, rho, spp, seed + i)
            render_seconds.append(time.perf_counter() - start)
            rows.append({"alpha": alpha, "sigma_t": sigma_t, "g": g, "rho": rho, "mitsuba": value,
                         "stderr": stderr, "iad": float(ref), "rel_err_pct": 100.0 * (value / ref - 1.0),
                         "z": (value - ref) / stderr if stderr > 0 else float("nan")})
        if progress:
            progress(i + 1, len(materials))
    abs_err = np.abs([r["rel_err_pct"] for r in rows])
    return {"materials": len(materials), "comparisons": len(rows), "spp": spp, "n": n, "thickness_mm": thickness_mm,
            "median_abs_err_pct": float(np.median(abs_err)), "max_abs_err_pct": float(abs_err.max()),
            "median_rel_stderr_pct": float(np.median([100 * r["stderr"] / r["mitsuba"] for r in rows])),
            "seconds_per_render": float(np.mean(render_seconds)), "rows": rows}


def fit_closed_form(rhos, values):
    """A, B, C of I(ρ) = A + Bρ/(1 − Cρ) through three points (ρ_0 = 0 not required)."""
    r, v = np.asarray(rhos, dtype=float), np.asarray(values, dtype=float)
    # I(1 − Cρ) = A(1 − Cρ) + Bρ  ⇔  I = A + (B − AC)ρ + C·ρI : linear in (A, B − AC, C).
    m = np.column_stack([np.ones(3), r, r * v])
    a, b_minus_ac, c = np.linalg.solve(m, v)
    return float(a), float(b_minus_ac + a * c), float(c)


def closed_form(abc, rho):
    return background_response(*abc, rho)


def rho_closed_form(geometry, alpha, sigma_t, g, n: float, thickness_mm: float, fit_rhos=(0.0, 0.5, 0.99),
                    check_rhos=(0.02, 0.8), spp: int = 262144, seed: int = 0) -> dict:
    """Fit A, B, C from renders at `fit_rhos`; error of the closed form at `check_rhos`."""
    fit = [render_diffuse(geometry, alpha, sigma_t, g, n, thickness_mm, r, spp, seed) for r in fit_rhos]
    abc = fit_closed_form(fit_rhos, [v for v, _ in fit])
    checks = []
    for rho in check_rhos:
        value, stderr = render_diffuse(geometry, alpha, sigma_t, g, n, thickness_mm, rho, spp, seed)
        predicted = float(closed_form(abc, rho))
        checks.append({"rho": rho, "rendered": value, "stderr": stderr, "closed_form": predicted,
                       "abs_err": predicted - value, "rel_err_pct": 100.0 * (predicted / value - 1.0)})
    return {"material": {"alpha": alpha, "sigma_t": sigma_t, "g": g}, "A": abc[0], "B": abc[1], "C": abc[2],
            "fit_rhos": list(fit_rhos), "checks": checks}


# ------------------------------------------------------------------ the map tracer against volpath
# The check of trimeter.maps.tracer against Mitsuba's volpath: many random materials, both reference
# backgrounds, each side at a high sample count; judged by the distribution of z = (tracer − volpath) /
# combined std-error, which is ~N(0, 1) when both agree and both std-errors are right. p95 |z| catches
# wrong std-errors and scattered disagreement, the mean catches a bias a per-point tolerance hides.
CHECK_RHOS = (0.02, 0.9)          # the shipped recipes' reference backgrounds
Z_P95_MAX = 2.5                   # N(0, 1): 1.96; volpath's 16-batch std-error: t(15), 2.13
Z_MEAN_MAX = 0.5


def tracer_agreement(geometry: str, materials, n: float, thickness_mm: float, rhos=CHECK_RHOS,
                     paths: int = 1 << 21, spp: int = 1 << 19, seed: int = 0, backend: str = "llvm",
                     progress=None) -> list[dict]:
    """Per material: one tracer column (trimeter.maps.tracer.trace_column, its (σt, g) at `paths`
    detector paths) evaluated at the material's α and each ρ, against one volpath render per ρ
    (trimeter.forward.render.render_diffuse, `spp` samples). For the ideal geometry the rows also carry
    adding-doubling (iad, z_iad) when iadpython is installed. Seeds: material i uses seed + i on both sides."""
    from trimeter.geometry import load_geometry
    from trimeter.maps.tracer import Stack, k_max_for, trace_column

    params = load_geometry(geometry)
    stack = Stack.from_recipe(geometry, params, n, thickness_mm)
    k_max = k_max_for(0.999, 1e-5)          # the shipped recipes' truncation
    try:
        import iadpython  # noqa: F401 - only to know whether the ideal rows can carry adding-doubling
        with_iad = geometry == "ideal"
    except ImportError:
        with_iad = False
    rows = []
    for i, (alpha, sigma_t, g) in enumerate(np.asarray(materials, dtype=float)):
        t0 = time.perf_counter()
        tally = trace_column(stack, float(sigma_t), float(g), paths, seed + i, k_max, backend=backend)
        A, B, C = (float(v[0]) for v in tally.abc([alpha]))
        trace_seconds = time.perf_counter() - t0
        iad = iad_reflectance(alpha, sigma_t, g, n, thickness_mm, np.asarray(rhos)) if with_iad else None
        for k, rho in enumerate(rhos):
            traced = float(background_response(A, B, C, rho))
            traced_err = float(tally.stderr([alpha], rho)[0])
            t0 = time.perf_counter()
            rendered, rendered_err = render_diffuse(geometry, float(alpha), float(sigma_t), float(g), n,
                                                    thickness_mm, float(rho), spp, seed + i)
            row = {"geometry": geometry, "thickness_mm": thickness_mm, "alpha": float(alpha),
                   "sigma_t": float(sigma_t), "g": float(g), "rho": float(rho), "tracer": traced,
                   "tracer_stderr": traced_err, "volpath": rendered, "volpath_stderr": rendered_err,
                   "z": (traced - rendered) / math.hypot(traced_err, rendered_err),
                   "trace_seconds": trace_seconds / len(rhos), "render_seconds": time.perf_counter() - t0}
            if with_iad:
                row["iad"] = float(iad[k])
                # 2e-4: adding-doubling's own quadrature error at 32 points (see IAD_QUAD_POINTS)
                row["z_iad"] = (traced - row["iad"]) / math.hypot(traced_err, 2e-4)
            rows.append(row)
        if progress:
            progress(i + 1, len(materials))
    return rows


def z_summary(z) -> dict:
    """The distribution of z-scores and whether it meets the check (p95 |z| ≤ Z_P95_MAX, |mean| ≤ Z_MEAN_MAX)."""
    z = np.asarray(z, dtype=float)
    if z.size == 0:
        raise ValueError("no z-scores to summarise")
    out = {"count": int(z.size), "mean": float(z.mean()), "std": float(z.std(ddof=1)) if z.size > 1 else 0.0,
           "mean_stderr": float(z.std(ddof=1) / math.sqrt(z.size)) if z.size > 1 else float("nan"),
           "p95_abs": float(np.percentile(np.abs(z), 95)), "max_abs": float(np.abs(z).max())}
    out["ok"] = bool(out["p95_abs"] <= Z_P95_MAX and abs(out["mean"]) <= Z_MEAN_MAX)
    return out
