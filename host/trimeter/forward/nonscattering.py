"""The α = 0 limit in closed form: a purely absorbing layer stack on a Lambertian background.

Without scattering, light crosses the stack along straight lines: Beer-Lambert inside each layer,
unpolarised Fresnel at each smooth interface, incoherent inter-reflections (the same model as the
collimated I_c, at any angle). With R(μ), T(μ) the stack's reflectance and transmittance for light from
air at direction cosine μ (the stack is symmetric, so from above and below alike), a Lambertian
background of reflectance ρ carries radiance L_bg = ρ·(E_T/π + R_d·L_bg), so

    I(ρ) = A + B·ρ/(1 − C·ρ)    with    C = R_d = 2∫₀¹ R(μ) μ dμ  (the stack seen from the background),

  ideal:  A = R(1),  B = T(1)·T_d,  T_d = 2∫₀¹ T(μ) μ dμ       (uniform sky of radiance 1)
  device: A = 0 (nothing bright is mirrored into the normal), B = T(1)·E_T/E with E_T = ∫_panels T(μ)
          cosθ dω and E the same integral without sample (the white-reference normalisation).

The device values neglect the stack's and background's finite width (the background's hemisphere is
covered to 86° from the spot): a reference for tests at the per-cent level, not a map source.
Vectorised over σt (any shape); angle integrals by Gauss-Legendre.
"""

from __future__ import annotations

import numpy as np

from trimeter.forward.scenes import panel_corners, resolve_geometry
from trimeter.geometry import cover_slide_n
from trimeter.model.fresnel import NUMPY, fresnel

_MU, _MU_W = np.polynomial.legendre.leggauss(256)
_MU, _MU_W = (_MU + 1) / 2, _MU_W / 2           # nodes and weights on [0, 1]


def stack_rt(mu_air, indices, optical_depths):
    """(R, T) of a stack of smooth interfaces between media `indices` (air first and last) with
    non-scattering layers of normal optical depths `optical_depths` (one per inner medium), for light
    from air at direction cosine `mu_air`. Arrays broadcast (μ against optical depths)."""
    mu_air = np.asarray(mu_air, dtype=float)
    sin2 = 1.0 - mu_air**2
    ra = rb = None
    t = None
    for j in range(len(indices) - 1):
        n1, n2 = indices[j], indices[j + 1]
        cos1 = np.sqrt(np.clip(1.0 - sin2 / n1**2, 0.0, 1.0))
        r = fresnel(NUMPY, cos1, n2 / n1)[0]
        if j > 0:
            # cross layer j (medium indices[j]) along its internal direction
            x = np.exp(-np.asarray(optical_depths[j - 1], dtype=float) / np.maximum(cos1, 1e-300))
            ra, rb, t = _combine((ra, rb, t), (0.0, 0.0, x))
            ra, rb, t = _combine((ra, rb, t), (r, r, 1.0 - r))
        else:
            ra, rb, t = r, r, 1.0 - r
    return ra, t


def _combine(a, b):
    ra, ra_back, ta = a
    rb, rb_back, tb = b
    denom = 1.0 - ra_back * rb
    return ra + ta * ta * rb / denom, rb_back + tb * tb * ra_back / denom, ta * tb / denom


def _stack(params: dict, n: float, thickness_mm: float, sigma_t):
    sigma_t = np.asarray(sigma_t, dtype=float)
    tau = sigma_t * thickness_mm
    ns = cover_slide_n(params)
    if ns is not None:
        return [1.0, ns, n, ns, 1.0], [np.zeros_like(tau), tau, np.zeros_like(tau)]
    return [1.0, n, 1.0], [tau]


def nonscattering_coefficients(geometry, sigma_t, thickness_mm: float, n: float):
    """(A, B, C) of I(ρ) = A + Bρ/(1 − Cρ) at α = 0 for `geometry` (preset name or dict)."""
    name, params = resolve_geometry(geometry)
    indices, depths = _stack(params, n, thickness_mm, sigma_t)
    shape = np.shape(depths[0])
    depths = [np.expand_dims(d, -1) for d in depths]              # broadcast against μ nodes
    R, T = stack_rt(_MU, indices, depths)
    C = 2.0 * (R * _MU) @ _MU_W
    R1, T1 = (v[..., 0] for v in stack_rt(np.ones(1), indices, depths))
    if name == "ideal":
        return R1.reshape(shape), (T1 * (2.0 * (T * _MU) @ _MU_W)).reshape(shape), C.reshape(shape)
    mu_p, w_p = _panel_directions(params)
    T_p = stack_rt(mu_p, indices, depths)[1]
    ratio = (T_p @ w_p) / w_p.sum()
    return np.zeros(shape), (T1 * ratio).reshape(shape), C.reshape(shape)


def _panel_directions(params: dict, n_u: int = 96, n_v: int = 48):
    """Direction cosines μ and weights cosθ·dω of a midpoint grid over the panels, seen from the
    background spot (the white reference's position)."""
    point = np.array([0.0, 0.0, -float(params["background_gap_mm"])])
    mus, weights = [], []
    for quad in panel_corners(params):
        eu, ev = quad[1] - quad[0], quad[3] - quad[0]
        normal = np.cross(eu, ev)
        normal /= np.linalg.norm(normal)
        su, sv = (np.arange(n_u) + 0.5) / n_u, (np.arange(n_v) + 0.5) / n_v
        pts = quad[0] + su[:, None, None] * eu + sv[None, :, None] * ev
        d = (pts - point).reshape(-1, 3)
        dist = np.linalg.norm(d, axis=1)
        mu = d[:, 2] / dist
        cos_panel = np.abs(d @ normal) / dist
        area = np.linalg.norm(np.cross(eu, ev)) / (n_u * n_v)
        mus.append(mu)
        weights.append(mu * cos_panel * area / dist**2)
    return np.concatenate(mus), np.concatenate(weights)
