"""The bounce series (detector paths traced on past their 2nd background bounce): the survival of the
Russian roulette past that bounce, and the control variate of a path's return from its first bounce."""

from __future__ import annotations

import functools
import math

import numpy as np

from trimeter.forward.transport.estimators import straight_through
from trimeter.forward.transport.sampling import mix64
from trimeter.forward.transport.scene import Stack
from trimeter.forward.transport.tally import N_BACKGROUND_ORDERS, Tally, detector_path_variance, detector_sums
from trimeter.forward.transport.walk import CARRIED, LOOP_STATE, OUTCOME
from trimeter.model.fresnel import fresnel, fresnel_polarised
from trimeter.model.response import REFERENCE_RHOS

LATER_WAVES = 4

# Paths that go on past the 2nd background bounce first, as a pilot for the others: 1 in this many.
CONTINUATION_PILOT = 8
# Paths whose value up to the 2nd bounce gives the spread that continuation_share weighs the pilot against.
CONTINUATION_SAMPLE = 1 << 18


def continuation_share(n_paths: int, first_terms, first_iterations: int, later_terms, later_iterations: int,
                       orders: int, rho: float = REFERENCE_RHOS[1]) -> float:
    """The survival past the 2nd background bounce that minimises the variance of I(ρ) for the work,
    from a pilot of 1/CONTINUATION_PILOT of the paths there (`later_terms`, `later_iterations`): with
    V the per-path variance of a path's value up to that bounce (`first_terms`), M the mean square of
    its value after it (at survival 1) and c₁, c_L the iterations per path before and after,
    f = √(M·c₁ / (V·c_L)) (the largest over α = 0.9 … 0.999), within [1/CONTINUATION_PILOT, 1].
    Terms as detector_sums takes them."""
    if later_iterations <= 0:
        return 1.0
    alpha = np.array([0.9, 0.99, 0.999])
    # V from the first CONTINUATION_SAMPLE paths (any will do: they are independent): the sums are
    # the costliest part of a trace's bookkeeping.
    sample = min(n_paths, CONTINUATION_SAMPLE)
    first_terms = [tuple(part[:np.searchsorted(term[0], sample)] if np.ndim(part) else part for part in term)
                   for term in first_terms]
    first, later = (Tally(counts=counts, second=second, n_paths=n, weight=1.0, specular=0.0, truncated=0, k_max=0)
                    for n, (counts, second) in ((sample, detector_sums(sample, first_terms, orders)),
                                                (n_paths, detector_sums(n_paths, later_terms, orders))))
    variance = detector_path_variance(first, alpha, rho)
    _, later_second = later._moments(alpha)
    mean_square = sum(later_second[p] * rho**p for p in range(len(later_second))) * CONTINUATION_PILOT
    cost_ratio = first_iterations / (later_iterations * CONTINUATION_PILOT)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.sqrt(mean_square / variance * cost_ratio)
    share = float(np.max(np.where(np.isfinite(share), share, 1.0)))
    return min(max(share, 1 / CONTINUATION_PILOT), 1.0)


def returns_control_variate(dr, B, stack: Stack, sigma_t: float, seed: int, straight_through, final: dict,
                             second_bounce: dict, at, value, polarisation: bool = False):
    """A bounce series' control variate for its noisiest outcome: whether a path comes back to the
    background after its first bounce (for a clear sample mostly a Fresnel reflection off the stack's
    back face). `at`: the paths that reached their 2nd bounce, `value` their next-event estimates
    there; a path that came back by exactly one reflection and nothing else (`final`'s reflections
    since its first bounce, `second_bounce`: where the paths landed) has its estimate replaced by the
    expectation of it given its first bounce's position (_expected_plain_returns, for every path that
    bounced). Returns the estimates without those paths', and the expectation per path (α^k at the
    first bounce's k, row 2). `polarisation`: the walk's (single_reflection_returns)."""
    value = np.where(final["reflections"][at] == 1, 0.0, value)
    expected = np.zeros(len(final["m"]))
    bounced = np.flatnonzero(final["m"] >= 1)
    if len(bounced):
        expected[bounced] = _expected_plain_returns(dr, B, stack, sigma_t, seed, straight_through,
                                                    final["bounce_x"][bounced], final["bounce_y"][bounced],
                                                    polarisation)
    return value, expected


def _expected_plain_returns(dr, B, stack: Stack, sigma_t: float, seed: int, straight_through, x, y,
                            polarisation: bool = False):
    """A bounce series' control variate for its noisiest outcome: whether a path comes back to the
    background after its first bounce (for a clear sample mostly a Fresnel reflection off the stack's
    back face). A path that came back by exactly one reflection and nothing else has its second
    bounce's next-event estimate replaced by the expectation of that estimate given the first
    bounce's position (x, y) (numpy): over the bounce's cosine-distributed direction, Σ_i P_i ·
    v(landing_i) (single_reflection_returns), from RETURN_DIRECTIONS fresh directions per path, each
    with one interface drawn ∝ P_i and one next-event estimate from where it lands (unbiased). Fresh
    directions, not the path's own: the trace need not carry its first bounce's direction."""
    Float = B.Float
    xs, ys = Float(x), Float(y)
    total_value = np.zeros(len(x))
    state = mix64(seed ^ 0x5245)
    rng = B.PCG32(len(x), initstate=dr.opaque(B.UInt64, state), initseq=dr.opaque(B.UInt64, mix64(state ^ 0x5EED)))
    for _ in range(RETURN_DIRECTIONS):
        u1, u2, pick_u, u, v = (rng.next_float32() for _ in range(5))
        r, phi = dr.sqrt(u1), 2 * math.pi * u2
        P, landings = single_reflection_returns(dr, stack, sigma_t, xs, ys, r * dr.cos(phi), r * dr.sin(phi),
                                                 dr.safe_sqrt(1 - u1), polarisation)
        total = P[0]
        for p in P[1:]:
            total = total + p
        # the interface whose cumulative share first reaches pick_u (the last one if rounding leaves none)
        target, cumulative = pick_u * total, Float(0.0)
        land_x, land_y = landings[-1]
        chosen = dr.zeros(dr.mask_t(Float), len(x))
        for p, (lx, ly) in zip(P[:-1], landings[:-1], strict=True):
            cumulative = cumulative + p
            take = ~chosen & (cumulative >= target) & (p > 0)
            land_x, land_y = dr.select(take, lx, land_x), dr.select(take, ly, land_y)
            chosen |= take
        total_value += np.asarray(total * straight_through(land_x, land_y, u, v), dtype=np.float64)
    return total_value / RETURN_DIRECTIONS


# Fresh first-bounce directions per path for the bounce series' returns control variate.
RETURN_DIRECTIONS = 2


def single_reflection_returns(dr, stack: Stack, sigma_t: float, x, y, dx, dy, dz, polarisation: bool = False):
    """For rays leaving the background at (x, y) upward in direction (dx, dy, dz) (Dr.Jit arrays of one
    backend): per interface i of the stack (0 = its bottom face … L = its top face), the probability
    P_i that the ray comes back to the background after one Fresnel reflection there and nothing else
    (refracted through the interfaces below it both ways, unscattered, past no side face, landing on
    the background), and where it lands: ([P_i], [(x_i, y_i)]). The ray's way up and down is
    symmetric, so P_i = F_i·(transmittance up to i)², and it stays over the footprint if its entry,
    the reflection and its exit do (each leg is monotonic sideways). `polarisation` (Walk's): P_i =
    (R_s,i·T_s² + R_p,i·T_p²)/2 with each polarisation's transmittance T up to i (the background's light is
    unpolarised, and the faces, parallel to one another, keep s and p apart)."""
    n_layers = len(stack.layer_n)
    W, WB = stack.stack_half_width, stack.background_half_width
    sin2 = dr.maximum(1 - dz * dz, 0.0)
    gap = (stack.plane_z[-1] - stack.background_z) / dz     # sideways travel per unit of (dx, dy)
    step, transmit = gap, dr.ones(type(dz), dr.width(dz))
    transmit_s = transmit_p = transmit          # polarisation: per polarisation, instead of `transmit`
    cos_below, n_below = dz, 1.0

    def over(px, py, half):
        return (dr.abs(px) <= half) & (dr.abs(py) <= half)

    entry_ok = over(x + gap * dx, y + gap * dy, W)
    P, landings = [], []
    for i in range(n_layers + 1):
        layer = n_layers - i                     # the medium above interface i: layer − 1, or air at 0
        n_above = stack.layer_n[layer - 1] if layer >= 1 else 1.0
        if polarisation:
            R_s, R_p, _ = fresnel_polarised(dr, cos_below, n_above / n_below)
        else:
            F, _ = fresnel(dr, cos_below, n_above / n_below)
        land_x, land_y = x + 2 * step * dx, y + 2 * step * dy
        ok = (entry_ok & over(x + step * dx, y + step * dy, W) & over(land_x - gap * dx, land_y - gap * dy, W)
              & over(land_x, land_y, WB))
        if polarisation:
            P.append(dr.select(ok, 0.5 * (R_s * transmit_s * transmit_s + R_p * transmit_p * transmit_p), 0.0))
        else:
            P.append(dr.select(ok, F * transmit * transmit, 0.0))
        landings.append((land_x, land_y))
        if layer >= 1:                           # on through layer − 1 to the next interface up
            li = layer - 1
            n_l = stack.layer_n[li]
            cos_l = dr.safe_sqrt(1 - sin2 / (n_l * n_l))
            depth = stack.plane_z[li] - stack.plane_z[li + 1]
            if polarisation:
                transmit_s, transmit_p = transmit_s * (1 - R_s), transmit_p * (1 - R_p)
                if li == stack.sample_layer:
                    beer = dr.exp(-sigma_t * depth / cos_l)
                    transmit_s, transmit_p = transmit_s * beer, transmit_p * beer
            else:
                transmit = transmit * (1 - F)
                if li == stack.sample_layer:
                    transmit = transmit * dr.exp(-sigma_t * depth / cos_l)
            step = step + depth / (n_l * cos_l)
            cos_below, n_below = cos_l, n_l
    return P, landings


def trace_on(walk, passes, seed: int, n_paths: int, terms: list, own):
    """A bounce series past its first pass: the 2nd bounce's next-event estimate (with the returns'
    control variate) for every path that reached it, then those paths traced on, bounce by bounce, to
    the walk's `orders` with Russian roulette. Adds their terms to `terms` (as detector_sums takes them)
    and returns the paths' own way to the light, weighted for the roulette."""
    final, cut_record = passes.final, passes.cut_record
    k_np, m_np = final["k"], final["m"]
    every = np.arange(n_paths)
    at = np.flatnonzero(m_np == N_BACKGROUND_ORDERS)
    value = _next_events(walk, seed, at, cut_record["x"][at], cut_record["y"][at], N_BACKGROUND_ORDERS)
    if walk.returns_cv:
        value, expected = returns_control_variate(walk.dr, walk.B, walk.stack, walk.sigma_t_value, seed,
                                                  functools.partial(straight_through, walk), final, cut_record, at,
                                                  value, walk.polarisation)
        terms.append((every, final["nee_k"], expected, N_BACKGROUND_ORDERS))
    terms.append((at, k_np[at], value, N_BACKGROUND_ORDERS))
    first = [*terms, (every, k_np.copy(), np.where(m_np < N_BACKGROUND_ORDERS, own, 0.0), m_np.copy())]
    first_iterations = int(passes.it_total.sum())
    # Past the 2nd bounce, Russian roulette (a constant weight, no α in it: the polynomial stays):
    # light that comes back into a dense sample from below diffuses for thousands of scatterings
    # and hardly changes I. A pilot, 1 in CONTINUATION_PILOT of the paths there, always goes on;
    # from its cost and spread (continuation_share) the others go on with a probability p and
    # weight 1/p. The pilot's outcomes decide only the others' p: unbiased.
    draw = np.random.default_rng([seed, 0x5255]).random(len(at))
    pilot = draw < 1 / CONTINUATION_PILOT
    weight = np.ones(n_paths)

    def go_on_from_the_second(chosen):
        return go_on(walk, passes, chosen, {name: values[chosen] for name, values in cut_record.items()},
                     k_np[chosen], m_np[chosen])

    reached = [go_on_from_the_second(at[pilot])]      # per group, per bounce 3 …: (paths, x, y, k)
    later_terms = [(at[pilot], k_np[at[pilot]], own[at[pilot]], m_np[at[pilot]])]
    for j, (p_j, x_j, y_j, k_j) in enumerate(reached[0]):
        later_terms.append((p_j, k_j, _next_events(walk, seed, p_j, x_j, y_j, N_BACKGROUND_ORDERS + 1 + j),
                            N_BACKGROUND_ORDERS + 1 + j))
    share = continuation_share(n_paths, first, first_iterations, later_terms,
                               int(passes.it_total.sum()) - first_iterations, walk.orders)
    others = at[~pilot & (draw < share)]
    if len(others):
        weight[others] = (1 - 1 / CONTINUATION_PILOT) / (share - 1 / CONTINUATION_PILOT)
    reached.append(go_on_from_the_second(others))
    own = np.where(m_np >= N_BACKGROUND_ORDERS, own * weight, own)   # the paths that went on (others': 0)
    for j in range(walk.orders - N_BACKGROUND_ORDERS - 1):  # bounces 3 … orders − 1, both groups, in path order
        parts = [group[j] for group in reached if len(group) > j]
        p_j, x_j, y_j, k_j = (np.concatenate([part[i] for part in parts]) for i in range(4))
        order = np.argsort(p_j, kind="stable")
        p_j, x_j, y_j, k_j = p_j[order], x_j[order], y_j[order], k_j[order]
        terms.append((p_j, k_j, _next_events(walk, seed, p_j, x_j, y_j, N_BACKGROUND_ORDERS + 1 + j) * weight[p_j],
                      N_BACKGROUND_ORDERS + 1 + j))
    return own


def _next_events(walk, seed: int, at, x, y, bounce: int):
    """The next-event estimates at a later bounce of the paths `at`, landed at (x, y), from direction
    samples of their own (any independent uniforms will do), seeded from the trace's."""
    if not len(at):
        return np.zeros(0)
    u, v = np.random.default_rng([seed, 0x4E45, bounce - 2]).random((2, len(at)), dtype=np.float32)
    Float = walk.Float
    return np.asarray(straight_through(walk, Float(x), Float(y), Float(u), Float(v)), dtype=np.float64)


def go_on(walk, passes, paths, record, k_at, m_at):
    """A bounce series: `paths`, cut at a bounce with `record` (their CARRIED values and random
    streams) and (k, m), go on from there, pass by pass, each with its own random stream (so a
    path is what one unbroken trace would make it) to the next bounce, until the walk's `orders`.
    Their outcomes go into `passes`; returns, per bounce after the cut, the paths that reached it,
    where and k."""
    dr, B, Float, UInt32, Bool = walk.dr, walk.B, walk.Float, walk.UInt32, walk.Bool
    reached = []
    while len(paths):
        n, bounce = len(paths), int(m_at[0])
        rng = B.PCG32(n)
        rng.state, rng.inc = B.UInt64(record["rng_state"]), B.UInt64(record["rng_inc"])
        start = {name: (UInt32 if dtype == np.uint32 else Float)(record[name]) for name, dtype in CARRIED}
        start.update(k=UInt32(k_at), m=UInt32(m_at), it=dr.zeros(UInt32, n), alive=dr.full(Bool, True, n),
                     hit=dr.full(Bool, False, n), straight=dr.full(Bool, True, n), clean=dr.full(Bool, False, n),
                     escape=dr.full(Bool, False, n), nee_k=dr.zeros(UInt32, n),   # the first bounce's: unused
                     **{name: dr.zeros(Float, n) for name in ("bounce_x", "bounce_y", "nee_u", "nee_v")})
        walk.stop_at(bounce + 1)
        # few paths: longer waves, fewer of each wave's fixed costs (tracing the loop, launching it)
        state = [start[name] for name in LOOP_STATE] + walk.polarisation_start(n) + [rng]
        current, next_record = walk.run(state, OUTCOME, bounce + 1 if bounce + 1 < walk.orders else None,
                                        LATER_WAVES * walk.wave)
        for name in ("k", "m", "hit", "light"):
            if name in current:
                passes.final[name][paths] = current[name]
        passes.it_total[paths] += current["it"]
        passes.over_iter[paths] |= current["it"] >= walk.max_iter
        if bounce + 1 >= walk.orders:
            break
        cut = np.flatnonzero(current["m"] == bounce + 1)
        paths, k_at, m_at = paths[cut], current["k"][cut], current["m"][cut]
        record = {name: values[cut] for name, values in next_record.items()}
        reached.append((paths, record["x"], record["y"], k_at))
    return reached
