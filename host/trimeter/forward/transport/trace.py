"""One trace: `n_paths` paths of one kind at one (σt, g), in named parts — where the paths start, the
first pass of the random walk (trimeter.forward.transport.walk), and the tally of each kind of path:
background paths (C), factorised detector paths (A, UT1), detector paths with their next-event
estimates, control variates and, in a bounce series, their passes past the 2nd bounce."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from trimeter.errors import InputError
from trimeter.forward.transport.estimators import (PLAIN_RETURN_ITERATIONS, clean_pass_probability, plain_return,
                                                   straight_through)
from trimeter.forward.transport.sampling import cosine_direction, nee_points, pcg_streams
from trimeter.forward.transport.scene import Stack
from trimeter.forward.transport.series import trace_on
from trimeter.forward.transport.tally import (N_BACKGROUND_ORDERS, Tally, add_constant, background_sums,
                                              detector_sums)
from trimeter.forward.transport.walk import FIRST_BOUNCE_RECORD, OUTCOME, Walk
from trimeter.model.fresnel import normal_incidence_reflectance


@dataclass
class Passes:
    """What the passes of a trace leave per path (numpy): `final` the outcome records (Walk.run), the
    first pass's `cut_record` of the paths it cut at their 2nd bounce, the loop iterations per path and
    whether a path hit the iteration limit. A bounce series' later passes update them in place."""
    final: dict
    cut_record: dict
    it_total: np.ndarray
    over_iter: np.ndarray


def trace(stack: Stack, sigma_t: float, g: float, n_paths: int, seed: int, k_max: int, wave: int = 48,
          from_below: bool = False, backend: str = "llvm", control_variates: bool = True,
          factorise: bool = False, next_event: bool = True,
          background_orders: int = N_BACKGROUND_ORDERS, polarisation: bool = False) -> Tally:
    """Trace `n_paths` adjoint paths from the detector at extinction σt [1/mm] and HG anisotropy g;
    or, `from_below`, paths leaving the background (under the detector spot) cosine-distributed
    upward, tallying those that come back to the background (row 0) — the C coefficient.
    `factorise` (ColumnTally): detector paths stop at the background and tally it in row 1 (UT1);
    background paths also tally those that reach the light, in row 1 (UTU); no control variates.
    `next_event` False (comparisons only): detector paths count their own straight way out instead
    of a next-event estimate at the first bounce (no control variates either, they build on it).
    `background_orders`: detector paths stop at that background bounce (rows m < it; not factorised);
    beyond 2 (a bounce series, with next-event estimates), past their 2nd bounce in passes, with
    roulette (see the package's docstring).
    `polarisation`: the two polarisations tracked at the interfaces (Walk's docstring has the model)."""
    if background_orders < N_BACKGROUND_ORDERS or (factorise and background_orders != N_BACKGROUND_ORDERS):
        raise InputError(f"background_orders must be ≥ {N_BACKGROUND_ORDERS} (and {N_BACKGROUND_ORDERS} for a "
                         f"factorised column), got {background_orders}")
    t0 = time.perf_counter()
    walk = Walk(stack, sigma_t, g, k_max, wave=wave, from_below=from_below, backend=backend,
                control_variates=control_variates, factorise=factorise, next_event=next_event,
                background_orders=background_orders, polarisation=polarisation)
    state, start_cos = _start(walk, n_paths, seed)
    walk.stop_at(min(walk.orders, N_BACKGROUND_ORDERS) if walk.series else walk.orders)
    passes = _first_pass(walk, state)
    if from_below:
        tally = _background_tally(walk, passes, n_paths, start_cos)
    elif factorise:
        tally = _factorised_tally(walk, passes, n_paths)
    else:
        tally = _detector_tally(walk, passes, n_paths, seed)
    tally.seconds = time.perf_counter() - t0
    tally.path_events = int(passes.it_total.sum())
    return tally


def _start(walk: Walk, n_paths: int, seed: int):
    """The loop's initial state (LOOP_STATE, the returns' count in a bounce series, the random streams)
    and, for background paths with control variates, their starting cosines. Detector paths start just
    inside the top layer, straight down (the first interface is done in closed form), on the detector's
    spot; background paths on the background under it, cosine-distributed upward."""
    dr, Float, UInt32, Bool = walk.dr, walk.Float, walk.UInt32, walk.Bool
    stack = walk.stack
    rng = pcg_streams(dr, walk.B, n_paths, seed)
    if stack.detector_half_side > 0:
        x = stack.detector_half_side * (2 * rng.next_float32() - 1)
        y = stack.detector_half_side * (2 * rng.next_float32() - 1)
    else:
        x, y = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths)
    k = dr.zeros(UInt32, n_paths)
    start_cos = None
    if walk.from_below:
        z = dr.full(Float, stack.background_z, n_paths)
        u1, u2 = rng.next_float32(), rng.next_float32()
        dx, dy, dz = cosine_direction(dr, u1, u2)
        start_cos = np.asarray(dz, dtype=np.float64) if walk.control_variates else None
        li = dr.full(UInt32, walk.L, n_paths)
        m = dr.full(UInt32, 1, n_paths)          # has left the background once
    else:
        z = dr.full(Float, walk.planes[0], n_paths)
        dx, dy, dz = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths), dr.full(Float, -1.0, n_paths)
        li = dr.zeros(UInt32, n_paths)
        m = dr.zeros(UInt32, n_paths)
    it = dr.zeros(UInt32, n_paths)
    alive = dr.full(Bool, True, n_paths)
    hit = dr.full(Bool, False, n_paths)
    # The first background bounce: scatterings before it, where, two unused random numbers (for its
    # next-event estimate, computed once per path after the loop), and whether the path has gone
    # straight on since (nothing but refraction).
    nee_k = dr.zeros(UInt32, n_paths)
    cv_state = [dr.zeros(UInt32, n_paths)] if walk.returns_cv else []
    bounce_x, bounce_y = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths)
    nee_u, nee_v = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths)
    straight = dr.full(Bool, False, n_paths)
    clean = dr.full(Bool, False, n_paths)   # reached the first bounce straight from the detector
    # For the rotation average of a path's own way to the light (Walk.rotation_average): where it
    # started, how far from there it has been (squared), and whether it left through the top face
    # towards where a light could be (a way out that counts).
    x0, y0 = Float(x), Float(y)
    reach2 = dr.zeros(Float, n_paths)
    escape = dr.full(Bool, False, n_paths)
    state = [x, y, z, dx, dy, dz, li, k, m, it, alive, hit, nee_k, bounce_x, bounce_y, nee_u, nee_v, straight, clean,
             x0, y0, reach2, escape, *walk.polarisation_start(n_paths), *cv_state, rng]
    return state, start_cos


def _first_pass(walk: Walk, state) -> Passes:
    """Every path to its end, or (a bounce series) to its 2nd bounce, recording where those stopped."""
    recorded = OUTCOME + FIRST_BOUNCE_RECORD + ([("reflections", np.uint32)] if walk.returns_cv else [])
    final, cut_record = walk.run(state, recorded, N_BACKGROUND_ORDERS if walk.series else None)
    return Passes(final, cut_record, final["it"].astype(np.int64), final["it"] >= walk.max_iter)


def _background_tally(walk: Walk, passes: Passes, n_paths: int, start_cos) -> Tally:
    """Background paths: by k, those that came back to the background (row 0; C) and, factorised, those
    that reached the light (row 1; UTU)."""
    final = passes.final
    k_np, m_np, hit_np = final["k"], final["m"], final["hit"]
    truncated = int(np.count_nonzero((k_np >= walk.k_max) | passes.over_iter))
    # factorised: `hit` is "reached the light", and a path came back iff it met the background again
    if walk.factorise:
        counts, second = background_sums(k_np, m_np >= 2, hit_np)
    else:
        counts, second = background_sums(k_np, hit_np)
    if start_cos is not None:  # control variates on
        # The light the stack's interfaces send straight back (no scattering, few reflections):
        # its expectation is a 1-D integral, so those paths' 0/1 outcomes are replaced by it.
        min_cos, expected = plain_return(walk.stack, walk.sigma_t_value, walk.polarisation)
        plain = hit_np & (k_np == 0) & (passes.it_total <= PLAIN_RETURN_ITERATIONS) & (start_cos >= min_cos)
        counts, second = background_sums(k_np, hit_np & ~plain)
        counts, second = add_constant(counts, second, n_paths, expected, row=0)
    return Tally(counts=counts, n_paths=n_paths, weight=1.0, specular=0.0, truncated=truncated, k_max=walk.k_max,
                 second=second)


def _top_face_reflectance(walk: Walk) -> float:
    """The first interface (air → top layer) at normal incidence, in closed form."""
    return normal_incidence_reflectance(walk.layer_n[0], 1.0)


def _factorised_tally(walk: Walk, passes: Passes, n_paths: int) -> Tally:
    """Factorised detector paths: A from those that reached the light, and each path that reached the
    background adds 1 to UT1 at its scatterings so far."""
    final = passes.final
    k_np, m_np, hit_np = final["k"], final["m"], final["hit"]
    truncated = int(np.count_nonzero((k_np >= walk.k_max) | passes.over_iter))
    every = np.arange(n_paths)
    counts, second = detector_sums(n_paths, [(every, k_np, np.where(m_np < 1, hit_np, 0.0), m_np),
                                             (every, final["nee_k"], np.where(m_np >= 1, 1.0, 0.0), 1)])
    r0 = _top_face_reflectance(walk)
    return Tally(counts=counts, n_paths=n_paths, weight=(1 - r0) * walk.stack.scale, specular=r0 * walk.stack.scale,
                 truncated=truncated, k_max=walk.k_max, second=second)


def _detector_tally(walk: Walk, passes: Passes, n_paths: int, seed: int) -> Tally:
    """Detector paths: each path's terms (its next-event estimate at its first bounce, its own way to
    the light, and in a bounce series its later bounces' estimates), with the control variates' exact
    expectations in place of the noisiest outcomes."""
    final = passes.final
    k_np, m_np, hit_np = final["k"], final["m"], final["hit"]
    bounced = np.flatnonzero(m_np >= 1)
    nee_value = np.zeros(n_paths)
    Float = walk.Float
    if walk.nee and len(bounced):
        value = straight_through(walk, *(Float(final[name][bounced])
                                         for name in ("bounce_x", "bounce_y", "nee_u", "nee_v")))
        nee_value[bounced] = np.asarray(value, dtype=np.float64)
    offset_variance = clean_pass = fresh_mean = 0.0
    if walk.control_variates:
        nee_value, clean_pass, fresh_mean, offset_variance = _clean_first_pass(walk, final, nee_value, n_paths, seed)
    every = np.arange(n_paths)
    terms = [(every, final["nee_k"], nee_value, 1)]
    own = final["light"] if walk.averaged else hit_np
    if walk.series:
        own = trace_on(walk, passes, seed, n_paths, terms, own)
    terms.append((every, k_np, np.where(m_np < walk.orders, own, 0.0), m_np))
    truncated = int(np.count_nonzero((k_np >= walk.k_max) | passes.over_iter))
    counts, second = detector_sums(n_paths, terms, walk.orders)
    if walk.control_variates:
        counts, second = add_constant(counts, second, n_paths, clean_pass * fresh_mean, row=1)
    r0 = _top_face_reflectance(walk)
    stack = walk.stack
    specular = r0 * stack.scale if not stack.panels else 0.0  # the device's detector sees no panel specularly
    return Tally(counts=counts, n_paths=n_paths, weight=(1 - r0) * stack.scale, specular=specular,
                 truncated=truncated, k_max=walk.k_max, second=second, offset_variance=offset_variance)


def _clean_first_pass(walk: Walk, final: dict, nee_value, n_paths: int, seed: int):
    """The control variate of a detector path's straight first pass. Most detector paths of a clear
    sample go straight down to the background; whether one does (a Fresnel or free-flight draw) and its
    next-event value are noise that does not depend on α. Their estimates are replaced by the exact
    probability of that first pass × the mean next-event value from fresh samples of the same
    estimator (unbiased). (the estimates without those paths', that probability, the mean, the
    variance of the constant it adds as n²·Var)."""
    dr, Float, stack = walk.dr, walk.Float, walk.stack
    nee_value = np.where(final["clean"], 0.0, nee_value)
    clean_pass = clean_pass_probability(stack, walk.sigma_t_value)
    replicas = []
    for points in nee_points(seed, n_paths):
        if stack.detector_half_side > 0:
            sx, sy = (Float(stack.detector_half_side * (2 * points[:, i] - 1)) for i in (0, 1))
        else:
            sx, sy = dr.zeros(Float, len(points)), dr.zeros(Float, len(points))
        value = straight_through(walk, sx, sy, Float(points[:, 2]), Float(points[:, 3]))
        replicas.append(float(np.mean(np.asarray(value, dtype=np.float64))))
    fresh_mean = float(np.mean(replicas))
    offset_variance = (clean_pass * n_paths) ** 2 * float(np.var(replicas, ddof=1)) / len(replicas)
    return nee_value, clean_pass, fresh_mean, offset_variance
