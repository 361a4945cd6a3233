"""The map tracer (trimeter.forward.transport) against Mitsuba's volpath (trimeter.forward.render): shared by
`trimeter bench tracer-check` and tests/maps.

Many random materials (trimeter.forward.validate.random_materials), both reference backgrounds, each
side at a high sample count; judged by the distribution of z = (tracer − volpath) / combined
std-error, which is ~N(0, 1) when both agree and both std-errors are right. p95 |z| catches wrong
std-errors and scattered disagreement, the mean catches a bias a per-point tolerance hides.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from trimeter.forward.render import render_diffuse_offset_free
from trimeter.forward.validate import iad_reflectance
from trimeter.model.response import REFERENCE_RHOS, background_response

CHECK_RHOS = REFERENCE_RHOS       # the shipped recipes' reference backgrounds
Z_P95_MAX = 2.5                   # N(0, 1): 1.96; volpath's 16-batch std-error: t(15), 2.13
Z_MEAN_MAX = 0.5


def tracer_agreement(geometry: str, materials: ArrayLike, n: float, thickness_mm: float,
                     rhos: tuple[float, ...] = CHECK_RHOS, paths: int = 1 << 21, spp: int = 1 << 19, seed: int = 0,
                     backend: str = "llvm", progress: Callable[[int, int], None] | None = None,
                     series_orders: int | None = None) -> list[dict]:
    """Per material: one tracer column (trimeter.forward.transport.trace_column, its (σt, g) at `paths`
    detector paths) evaluated at the material's α and each ρ, against volpath per ρ extrapolated to no
    ray offset (trimeter.forward.render.render_diffuse_offset_free: `spp` samples, and a quarter as many
    with the scene moved; the render as made is in `volpath_as_rendered`). For the ideal geometry the rows also carry
    adding-doubling (iad, z_iad) when iadpython is installed. Seeds: material i uses seed + i on both sides.
    The tracer's value is the map model A + Bρ/(1 − Cρ) as the builder makes it. `series_orders`
    (device only, 3…16): instead, the detector paths' own bounce series to that many background orders
    (ColumnTally.bounce_series), the model (C then matched to that series at the recipes' default white,
    ColumnTally.abc) carried as `tracer_model`."""
    from trimeter.geometry import load_geometry
    from trimeter.forward.transport import N_BACKGROUND_ORDERS, Stack, k_max_for, trace_column

    require_series_orders(geometry, series_orders)

    params = load_geometry(geometry)
    stack = Stack.from_recipe(geometry, params, n, thickness_mm)
    k_max = k_max_for(0.999, 1e-5)          # the shipped recipes' truncation
    try:
        import iadpython  # noqa: F401 - only to know whether the ideal rows can carry adding-doubling
        with_iad = geometry == "ideal"
    except ImportError:
        with_iad = False
    rows = []
    materials = np.asarray(materials, dtype=float)
    for i, (alpha, sigma_t, g) in enumerate(materials):
        t0 = time.perf_counter()
        tally = trace_column(stack, float(sigma_t), float(g), paths, seed + i, k_max, backend=backend,
                             background_orders=series_orders or N_BACKGROUND_ORDERS)
        A, B, C = (float(v[0]) for v in tally.abc([alpha]))
        trace_seconds = time.perf_counter() - t0
        iad = iad_reflectance(alpha, sigma_t, g, n, thickness_mm, np.asarray(rhos)) if with_iad else None
        for k, rho in enumerate(rhos):
            traced = model = float(background_response(A, B, C, rho))
            traced_err = float(tally.stderr([alpha], rho)[0])
            if series_orders:
                value, error = tally.bounce_series([alpha], float(rho))
                traced, traced_err = float(value[0]), float(error[0])
            t0 = time.perf_counter()
            rendered, rendered_err, as_rendered = render_diffuse_offset_free(
                geometry, float(alpha), float(sigma_t), float(g), n, thickness_mm, float(rho), spp, seed + i)
            row: dict[str, object] = {"geometry": geometry, "thickness_mm": thickness_mm, "alpha": float(alpha),
                   "sigma_t": float(sigma_t), "g": float(g), "rho": float(rho), "tracer": traced,
                   "tracer_stderr": traced_err, "volpath": rendered, "volpath_stderr": rendered_err,
                   "volpath_as_rendered": as_rendered,
                   "z": (traced - rendered) / math.hypot(traced_err, rendered_err),
                   "trace_seconds": trace_seconds / len(rhos), "render_seconds": time.perf_counter() - t0}
            if series_orders:
                row["tracer_model"] = model
            if iad is not None:
                row["iad"] = iad_value = float(iad[k])
                # 2e-4: adding-doubling's own quadrature error (trimeter.forward.adding_doubling.IAD_QUAD_POINTS)
                row["z_iad"] = (traced - iad_value) / math.hypot(traced_err, 2e-4)
            rows.append(row)
        if progress:
            progress(i + 1, len(materials))
    return rows


def require_series_orders(geometry: str, series_orders: int | None) -> None:
    """InputError unless `series_orders` is None, or 3…16 for the device geometry (the ideal map's
    model is exact, so it has no series to judge)."""
    from trimeter.errors import InputError

    if series_orders is not None and (geometry != "device" or not 3 <= series_orders <= 16):
        raise InputError("series orders: 3…16, device geometry only (the ideal map's model is exact), "
                         f"got {series_orders} for {geometry!r}")


def z_summary(z: ArrayLike) -> dict:
    """The distribution of z-scores and whether it meets the check (p95 |z| ≤ Z_P95_MAX, |mean| ≤ Z_MEAN_MAX)."""
    z = np.asarray(z, dtype=float)
    if z.size == 0:
        raise ValueError("no z-scores to summarise")
    out = {"count": int(z.size), "mean": float(z.mean()), "std": float(z.std(ddof=1)) if z.size > 1 else 0.0,
           "mean_stderr": float(z.std(ddof=1) / math.sqrt(z.size)) if z.size > 1 else float("nan"),
           "p95_abs": float(np.percentile(np.abs(z), 95)), "max_abs": float(np.abs(z).max())}
    out["ok"] = bool(out["p95_abs"] <= Z_P95_MAX and abs(out["mean"]) <= Z_MEAN_MAX)
    return out
