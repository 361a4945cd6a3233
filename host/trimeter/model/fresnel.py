"""Fresnel reflection at a smooth interface, for every tracer and closed form of the project.

One declaration, `fresnel`, written against an array namespace: `NUMPY` (numpy, float64) or Dr.Jit's
`drjit` module itself (the map tracer's kernels), which both offer `safe_sqrt` and `select`, so the two
forms are the same operations in the same order. `normal_incidence_reflectance` is its closed form at
cosθ = 1 (the collimated beam, the detector's first interface), checked against it by the tests."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np


def _safe_sqrt(x: Any) -> Any:
    return np.sqrt(np.maximum(x, 0.0))


def _select(condition: Any, a: Any, b: Any) -> Any:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(condition, a, b)


# numpy's form of the operations `fresnel` needs, spelled as Dr.Jit spells them.
NUMPY = SimpleNamespace(safe_sqrt=_safe_sqrt, select=_select)


def _amplitudes(xp: Any, cos_i: Any, eta: Any) -> tuple[Any, Any, Any, Any]:
    """(r_s, r_p, cos_t, total internal reflection): the two polarisations' amplitude reflection coefficients."""
    sin2_t = (1 - cos_i * cos_i) / (eta * eta)
    tir = sin2_t >= 1
    cos_t = xp.safe_sqrt(1 - sin2_t)
    with np.errstate(invalid="ignore", divide="ignore"):   # 0/0 only where tir selects 1
        rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
        rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return rs, rp, cos_t, tir


def fresnel(xp: Any, cos_i: Any, eta: Any) -> tuple[Any, Any]:
    """Unpolarised Fresnel reflectance F for the incidence cosine cos_i ∈ [0, 1] and the relative index
    eta = n_t / n_i (1 beyond total internal reflection), and the transmitted direction's cosine cos_t.
    `xp`: NUMPY or drjit (then cos_i, eta are Dr.Jit arrays or floats of one backend)."""
    rs, rp, cos_t, tir = _amplitudes(xp, cos_i, eta)
    return xp.select(tir, 1.0, 0.5 * (rs * rs + rp * rp)), cos_t


def fresnel_polarised(xp: Any, cos_i: Any, eta: Any) -> tuple[Any, Any, Any]:
    """`fresnel` per polarisation: (R_s, R_p, cos_t), light polarised perpendicular (s) and parallel (p) to the
    plane of incidence; F = (R_s + R_p) / 2 (the map tracer's `polarisation` option)."""
    rs, rp, cos_t, tir = _amplitudes(xp, cos_i, eta)
    return xp.select(tir, 1.0, rs * rs), xp.select(tir, 1.0, rp * rp), cos_t


def normal_incidence_reflectance(n1: Any, n2: Any) -> Any:
    """`fresnel` at cos_i = 1 in closed form: ((n1 − n2)/(n1 + n2))²."""
    return ((n1 - n2) / (n1 + n2)) ** 2
