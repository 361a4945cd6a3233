"""The column driver: a (σt, g) column's detector paths and, for C, its background paths or the detector
paths' bounce series, traced in chunks and summed (the map builder's one call per column)."""

from __future__ import annotations

import math

import numpy as np

from trimeter.errors import InputError
from trimeter.forward.transport.sampling import mix64
from trimeter.forward.transport.scene import Stack
from trimeter.forward.transport.tally import N_BACKGROUND_ORDERS, ColumnTally, Tally, detector_path_variance
from trimeter.forward.transport.trace import trace
from trimeter.model.response import REFERENCE_RHOS

TRACE_CHUNK = 1 << 24


def trace_column(stack: Stack, sigma_t: float, g: float, n_paths: int, seed: int, k_max: int,
                 below_fraction: float | None = None, backend: str = "llvm",
                 control_variates: bool = True, factorise: bool | None = None,
                 background_orders: int = N_BACKGROUND_ORDERS, white_rho: float = REFERENCE_RHOS[1],
                 polarisation: bool = False) -> ColumnTally:
    """Detector paths for one (σt, g), and for C either (a fraction as many) background paths or the
    detector paths' own later background orders (ColumnTally); seeds derived from `seed`; in chunks of
    at most TRACE_CHUNK paths (memory), chunk i > 0 seeded with mix64(seed + i).
    `background_orders`: at 2 (the maps'), C comes from background paths; at ≥ 3 (not factorised),
    detector paths go on to that many background bounces with a next-event estimate at each, no
    background paths are traced and C is matched to their bounce series at `white_rho` (A and B are,
    bit for bit, what a trace to 2 orders gives).
    `below_fraction` (background paths) None: as many as minimise the error of I(ρ = 0.9) for the
    work (below_share, from a pilot of 1/16); `control_variates` False: the plain estimator
    (comparisons; factorised columns never use them, see the module's docstring).
    `backend`: "llvm" or "cuda" (resolve_backend); the same seed gives the same paths on either, up to
    the backends' floating-point differences. `factorise` (B = UT1·UTU, see ColumnTally): None = where
    it is exact (Stack.factorises); True elsewhere is an InputError; False: detector paths carry on
    past the background (comparisons). `polarisation`: the two polarisations tracked at the interfaces
    (Walk's docstring has the model; off, the default and the shipped maps', unpolarised Fresnel)."""
    n_paths = int(n_paths)
    if factorise is None:
        factorise = stack.factorises
    elif factorise and not stack.factorises:
        raise InputError("B = UT1·UTU factorises only for an unbounded slab over an unbounded background "
                         "(the ideal geometry)")
    if not 0 < white_rho <= 1:
        raise InputError(f"white_rho must be within (0, 1], got {white_rho!r}")
    if below_fraction is not None and background_orders > N_BACKGROUND_ORDERS:
        raise InputError("below_fraction sets the background paths, and a bounce series traces none")
    parts = []
    for i, start in enumerate(range(0, max(n_paths, 1), TRACE_CHUNK)):
        n = min(TRACE_CHUNK, n_paths - start)
        s = seed if i == 0 else mix64(seed + i)
        above = trace(stack, sigma_t, g, n, s, k_max, backend=backend, control_variates=control_variates,
                      factorise=factorise, background_orders=background_orders, polarisation=polarisation)
        if background_orders > N_BACKGROUND_ORDERS:
            parts.append(ColumnTally(above, None, white_rho=white_rho))
            continue
        share = below_fraction if below_fraction is not None else 1 / BELOW_PILOT
        below = trace(stack, sigma_t, g, max(1024, int(n * share)), mix64(s ^ 0xB0B0B0B0), k_max,
                      from_below=True, backend=backend, control_variates=control_variates, factorise=factorise,
                      polarisation=polarisation)
        if below_fraction is None:
            more = int(n * below_share(above, below, factorised=factorise)) - below.n_paths
            if more > 0:
                below += trace(stack, sigma_t, g, max(1024, more), mix64(s ^ 0xB0B0B0B1), k_max, from_below=True,
                               backend=backend, control_variates=control_variates, factorise=factorise,
                               polarisation=polarisation)
        parts.append(ColumnTally(above, below, factorised=factorise, white_rho=white_rho))
    total = parts[0]  # the range above has at least one chunk
    for part in parts[1:]:
        total += part
    return total


# Background paths: a pilot of 1/BELOW_PILOT of the detector paths, then as many as below_share says.
BELOW_PILOT = 16


def below_share(above: Tally, below: Tally, rho: float = 0.9, factorised: bool = False) -> float:
    """Background paths per detector path that minimise the variance of I(ρ) for the work: with
    per-path variances s_a² (detector paths' value) and s_c² (C's, × (∂I/∂C)²) and loop iterations e_a,
    e_c per path, N_c/N_a = (s_c/s_a)·√(e_a/e_c) (the largest over α = 0.5 … 0.999), within
    [1/BELOW_PILOT, 1]. Iterations, not seconds, so the count does not depend on the machine's load.
    Clear samples' C is noisy and matters on white; a dense sample's C hardly matters."""
    tally = ColumnTally(above, below, factorised=factorised)
    alpha = np.array([0.5, 0.9, 0.99, 0.999])
    if factorised:
        var_a, var_c, _ = tally._factorised_path_variances(alpha, rho)
    else:
        A, B, C = tally.abc(alpha)
        q = rho / (1 - C * rho)
        var_a = detector_path_variance(above, alpha, q)
        g1, g2 = below._moments(alpha)
        var_c = np.maximum(g2[0] - g1[0] ** 2, 0.0) * (B * q * q) ** 2
    cost = (above.path_events / max(above.n_paths, 1)) / max(below.path_events / max(below.n_paths, 1), 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(var_c / var_a * cost)
    ratio = float(np.max(np.where(np.isfinite(ratio), ratio, 1.0)))
    return min(max(ratio, 1 / BELOW_PILOT), 1.0)


def k_max_for(alpha_max: float, truncation: float) -> int:
    """Smallest K with α_max^K ≤ truncation."""
    if alpha_max <= 0:
        return 1
    return max(1, math.ceil(math.log(truncation) / math.log(alpha_max)))

