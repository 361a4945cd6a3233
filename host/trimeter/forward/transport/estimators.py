"""Estimators of the map tracer besides a path's own 0/1 outcome: the next-event estimate at a background
bounce (light straight out through the stack), and the exact expectations its control variates put in
place of noisy outcomes (a detector path's clean first pass, a background path's plain return)."""

from __future__ import annotations

import functools
import math

import numpy as np

from trimeter.forward.transport.sampling import cosine_direction
from trimeter.forward.transport.scene import Stack, sees_panel
from trimeter.model.fresnel import NUMPY, fresnel, fresnel_polarised, normal_incidence_reflectance


def clean_pass_probability(stack: Stack, sigma_t: float) -> float:
    """Probability that a detector path, past the top face, crosses every interface straight down
    without a Fresnel reflection and the sample without scattering (normal incidence)."""
    indices = [float(n) for n in stack.layer_n] + [1.0]
    p = 1.0
    for above, below in zip(indices[:-1], indices[1:], strict=True):
        p *= 1 - normal_incidence_reflectance(above, below)
    depth = stack.plane_z[stack.sample_layer] - stack.plane_z[stack.sample_layer + 1]
    return p * math.exp(-sigma_t * depth)


# A background path that returns unscattered within this many loop iterations (a few reflections
# inside the stack) is a "plain return", replaced by its expectation (see plain_return).
PLAIN_RETURN_ITERATIONS = 24


def plain_return(stack: Stack, sigma_t: float, polarisation: bool = False) -> tuple[float, float]:
    """(μ_min, E): background paths leaving at cosθ ≥ μ_min that return unscattered within
    PLAIN_RETURN_ITERATIONS iterations never meet a side face or the background's edge (their sideways
    travel is bounded), so the probability of that return is the same as for an infinite stack; E is
    its expectation over the cosine-distributed start, ∫ P(μ) 2μ dμ over [μ_min, 1], P from the
    layers' Fresnel reflectances and the sample's Beer-Lambert attenuation, iteration by iteration.
    `polarisation` (Walk's): P for s and p light each, averaged (the background's light is unpolarised,
    and an unscattered path meets only faces parallel to one another, where the two never mix)."""
    n_layers = len(stack.layer_n)
    layer_n = np.array(stack.layer_n, dtype=float)
    depth = -np.diff(np.asarray(stack.plane_z, dtype=float))
    gap = stack.plane_z[-1] - stack.background_z
    reach = min(stack.stack_half_width, stack.background_half_width) - stack.detector_half_side
    steps = PLAIN_RETURN_ITERATIONS

    def sideways(tan_air):  # an upper bound on the travel of such a path, the gap crossed twice
        sin_air = tan_air / math.sqrt(1 + tan_air * tan_air)
        sin_l = sin_air / layer_n
        return 2 * gap * tan_air + (steps - 2) * float(np.max(depth * sin_l / np.sqrt(1 - sin_l * sin_l)))

    if not math.isfinite(reach):
        min_cos = 0.0
    else:
        lo, hi = 0.0, 1e6
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if sideways(mid) <= reach else (lo, mid)
        min_cos = 1 / math.sqrt(1 + lo * lo)
    nodes, weights = _gauss_legendre()
    mu = min_cos + (1 - min_cos) * (nodes + 1) / 2
    weights = weights * (1 - min_cos) / 2
    sin2 = 1 - mu * mu
    cos_l = np.sqrt(1 - sin2[None, :] / layer_n[:, None] ** 2)        # (layer, μ)
    survive = np.ones_like(cos_l)
    survive[stack.sample_layer] = np.exp(-sigma_t * depth[stack.sample_layer] / cos_l[stack.sample_layer])
    media = np.concatenate([[1.0], layer_n, [1.0]])
    cos_media = np.vstack([mu, cos_l, mu])
    # interface i lies between medium i (above) and i + 1 (below); F is the same from either side
    if polarisation:
        per_face = [fresnel_polarised(NUMPY, cos_media[i], media[i + 1] / media[i]) for i in range(n_layers + 1)]
        returned = np.mean([_returned(np.array([face[which] for face in per_face]), survive, n_layers, steps)
                            for which in (0, 1)], axis=0)
    else:
        reflectance = np.array([fresnel(NUMPY, cos_media[i], media[i + 1] / media[i])[0]
                                for i in range(n_layers + 1)])
        returned = _returned(reflectance, survive, n_layers, steps)
    return min_cos, float(np.sum(weights * returned * 2 * mu))


def _returned(reflectance: np.ndarray, survive: np.ndarray, n_layers: int, steps: int) -> np.ndarray:
    """plain_return's probability per start cosine of coming back within `steps` iterations, from the
    faces' reflectances (face, μ) and the layers' survival (layer, μ)."""
    shape = (n_layers + 1, survive.shape[1])
    up, down = np.zeros(shape), np.zeros(shape)      # index n_layers: the gap
    up[n_layers] = 1.0
    returned = np.zeros(survive.shape[1])
    for _ in range(steps):
        returned += down[n_layers]
        new_up, new_down = np.zeros_like(up), np.zeros_like(down)
        new_down[n_layers] += up[n_layers] * reflectance[n_layers]
        new_up[n_layers - 1] += up[n_layers] * (1 - reflectance[n_layers])
        for layer in range(n_layers):
            going_down, going_up = down[layer] * survive[layer], up[layer] * survive[layer]
            new_up[layer] += going_down * reflectance[layer + 1]
            new_down[layer + 1] += going_down * (1 - reflectance[layer + 1])
            new_down[layer] += going_up * reflectance[layer]
            if layer > 0:
                new_up[layer - 1] += going_up * (1 - reflectance[layer])
        up, down = new_up, new_down
    return returned


@functools.cache
def _gauss_legendre() -> tuple[np.ndarray, np.ndarray]:
    """256-point Gauss-Legendre nodes and weights on [-1, 1], computed once per process (an
    eigenvalue problem that, with BLAS threads competing with Dr.Jit's, took longer than the trace)."""
    return np.polynomial.legendre.leggauss(256)



def straight_through(walk, px, py, u_a, u_b):
    """Next-event estimate at a background bounce (px, py): the light that leaves the bounce upward and
    reaches the light *straight*, i.e. through every interface of the stack (Fresnel transmission, no
    reflection), unscattered (Beer-Lambert through the sample) and past no side face. Device: a
    direction towards a point drawn uniformly on one panel (chosen by u_a) enlarged by the walk's
    `margin`, which holds every point the refracted ray can reach; ideal: a cosine-distributed
    direction. Value = (cos/π)/pdf · transmittance · reached the light. Dr.Jit arrays of the walk's
    backend. With the walk's `polarisation`, the Fresnel transmittance is the mean of the s and p
    chains' products (the background's light is unpolarised; faces parallel to one another keep the
    two apart, so that is exact); the reflected rest is the paths' own (Walk.step)."""
    dr, Float, Bool, UInt32 = walk.dr, walk.Float, walk.Bool, walk.UInt32
    stack, planes, W = walk.stack, walk.planes, walk.W
    if stack.panels:
        count = len(stack.panels)
        pick = dr.minimum(UInt32(u_a * count), count - 1)
        u_a = u_a * count - Float(pick)
        cx = cy = cz = ux = uy = uz = vx = vy = vz = hu = hv = Float(0.0)
        for i, p in enumerate(stack.panels):
            on = pick == i
            cx, cy, cz = (dr.select(on, p.center[j], c) for j, c in enumerate((cx, cy, cz)))
            ux, uy, uz = (dr.select(on, p.axis_u[j], c) for j, c in enumerate((ux, uy, uz)))
            vx, vy, vz = (dr.select(on, p.axis_v[j], c) for j, c in enumerate((vx, vy, vz)))
            hu, hv = dr.select(on, p.half_u + walk.margin, hu), dr.select(on, p.half_v + walk.margin, hv)
        a, b = (2 * u_a - 1) * hu, (2 * u_b - 1) * hv
        tx, ty, tz = cx + a * ux + b * vx - px, cy + a * uy + b * vy - py, cz + a * uz + b * vz - stack.background_z
        dist2 = tx * tx + ty * ty + tz * tz
        inv = dr.rsqrt(dist2)
        ex, ey, ez = tx * inv, ty * inv, tz * inv
        nx_, ny_, nz_ = (ux * 0, uy * 0, uz * 0)
        for i, p in enumerate(stack.panels):
            on = pick == i
            nx_, ny_, nz_ = (dr.select(on, p.normal[j], c) for j, c in enumerate((nx_, ny_, nz_)))
        cos_panel = dr.maximum(-(ex * nx_ + ey * ny_ + ez * nz_), 1e-6)
        # (cos/π) / pdf_ω, pdf_ω = dist² / (area · cos_panel) / count
        value = ez / math.pi * (4 * hu * hv) * cos_panel / dist2 * count
    else:
        ex, ey, ez = cosine_direction(dr, u_a, u_b)
        value = Float(1.0)
    # Through the gap to the stack's bottom face; a ray missing the stack goes straight on.
    to_stack = (planes[-1] - stack.background_z) / ez
    qx, qy = px + to_stack * ex, py + to_stack * ey
    hits_stack = (dr.abs(qx) <= W) & (dr.abs(qy) <= W) if walk.finite else Bool(True)
    sin2 = ex * ex + ey * ey                    # n·sinθ is the same in every layer
    transmit = Float(1.0)
    pol = walk.polarisation
    transmit_s = transmit_p = Float(1.0)        # polarisation: the Fresnel part per polarisation; `transmit` the rest
    inside = Bool(True)
    n_before = 1.0
    for layer in range(walk.L - 1, -1, -1):     # bottom layer first
        n_l = walk.layer_n[layer]
        cos_before = dr.safe_sqrt(1 - sin2 / (n_before * n_before))
        if pol:
            R_s, R_p, cos_l = fresnel_polarised(dr, cos_before, n_l / n_before)
            transmit_s, transmit_p = transmit_s * (1 - R_s), transmit_p * (1 - R_p)
        else:
            F, cos_l = fresnel(dr, cos_before, n_l / n_before)
            transmit *= 1 - F
        depth = planes[layer] - planes[layer + 1]
        shift = depth / (n_l * cos_l)           # horizontal step per unit of the air direction's (x, y)
        qx, qy = qx + shift * ex, qy + shift * ey
        if layer == walk.sample:
            transmit *= dr.exp(-walk.sigma_t * depth / cos_l)
        if walk.finite:
            inside &= (dr.abs(qx) <= W) & (dr.abs(qy) <= W)
        n_before = n_l
    if pol:
        R_s, R_p, _ = fresnel_polarised(dr, dr.safe_sqrt(1 - sin2 / (n_before * n_before)), 1.0 / n_before)
        transmit = transmit * 0.5 * (transmit_s * (1 - R_s) + transmit_p * (1 - R_p))
    else:
        F, _ = fresnel(dr, dr.safe_sqrt(1 - sin2 / (n_before * n_before)), 1.0 / n_before)
        transmit *= 1 - F
    qz = dr.select(hits_stack, planes[0], stack.background_z)
    qx, qy = dr.select(hits_stack, qx, px), dr.select(hits_stack, qy, py)
    transmit = dr.select(hits_stack, transmit, 1.0)
    if walk.finite:  # from the rim outside the footprint: a ray into a side face is not straight
        meets_x, meets_y, _ = walk.side_entry(px, py, Float(stack.background_z), ex, ey, ez)
        passes = hits_stack | ~(meets_x | meets_y)
    else:
        passes = Bool(True)
    if stack.panels:
        seen = Bool(False)
        for i, p in enumerate(stack.panels):
            seen |= (pick == i) & sees_panel(dr, p, qx, qy, qz, ex, ey, ez)
    else:
        seen = ez > 0
    return dr.select(seen & (inside | ~hits_stack) & passes & (ez > 0), value * transmit, 0.0)
