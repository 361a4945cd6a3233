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

from trimeter.forward.adding_doubling import ideal_abc
from trimeter.forward.render import render_diffuse
from trimeter.model.response import background_response



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
        import iadpython  # noqa: F401 - a dev dependency: the device side doesn't have it
    except ImportError as exc:
        raise RuntimeError("the adding-doubling cross-check needs iadpython (pip install 'trimeter[dev]')") from exc
    A, B, C = ideal_abc([alpha], [sigma_t], [g], thickness_mm=thickness_mm, n=n)[0]
    return background_response(A, B, C, np.asarray(rho, dtype=float))


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


def fit_closed_form(rhos, values) -> tuple[float, float, float]:
    """A, B, C of I(ρ) = A + Bρ/(1 − Cρ) through three points (ρ_0 = 0 not required)."""
    r, v = np.asarray(rhos, dtype=float), np.asarray(values, dtype=float)
    # I(1 − Cρ) = A(1 − Cρ) + Bρ  ⇔  I = A + (B − AC)ρ + C·ρI : linear in (A, B − AC, C).
    m = np.column_stack([np.ones(3), r, r * v])
    a, b_minus_ac, c = np.linalg.solve(m, v)
    return float(a), float(b_minus_ac + a * c), float(c)


def closed_form(abc: tuple[float, float, float], rho):
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
