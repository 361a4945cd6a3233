"""How much scattered light the collimated measurement picks up besides the unscattered beam (paper Fig. 6).

The unscattered transmittance is analytic (trimeter.model.collimated). A real detector accepts a
finite solid angle, so light scattered forward near the beam adds to it: I_c = T(σt)·(1 + r), and read
as unscattered it gives σt too low by ln(1 + r)/(σt·ℓ). trimeter.model.inscatter.InscatterTable tabulates
L = ln(1 + r) per map (`trimeter map inscatter`, <map>.tins; build_inscatter_table traces it); the fit
takes it out (trimeter.inversion.newton.correct_inscatter). This is a
small volumetric light tracer for the device's `collimated` set-up (hardware/geometry.toml): a beam of
`beam_diameter_mm` enters the stack at normal incidence from behind; a photon counts if it leaves the
front and passes a disk of `aperture_diameter_mm` at `aperture_distance_mm` on the axis; the open-slot
reference (no sample) passes the whole beam, so tallies are already normalised like I_c.

Absorption only scales a path's weight by α per scattering event, so the tracer follows the paths an
α = 1 medium would take and tallies light by scattering order k: the in-scattered light at any albedo
is Σ_k tally[k]·α^k, from one trace (`_trace_orders`). Fresnel reflection is sampled.
Estimators (numpy, vectorised over photons):
- unscattered photons are tallied as they exit (they all pass the aperture) — this reproduces the
  analytic I_c, which checks the tracer;
- scattered light by next-event estimation: at every scattering event, the HG phase function towards the
  aperture × the aperture's solid angle (converted inside the sample, n²) × Beer-Lambert to the front ×
  the stack's Fresnel transmittance (a random point of the aperture per event); paths that reach the
  aperture after an internal reflection since their last scattering event are tallied when they exit
  (the NEE covers only straight exits).
Approximations: the 0.15 mm cover slides are folded into the boundaries (incoherent composite Fresnel,
their lateral offset neglected), the stack is laterally infinite, the refraction of the NEE ray
is computed as if it left from the scattering point's lateral position (≤ ℓ·tanθ_in ≈ µm off).
"""

from __future__ import annotations

import math

import numpy as np

from trimeter.geometry import cover_slide_n, cover_slide_thickness_mm, load_geometry
from trimeter.model.collimated import MEASURABLE_IC, beer_lambert_sigma_t, collimated_transmittance
from trimeter.model.fresnel import NUMPY, fresnel
from trimeter.model.inscatter import InscatterTable

SIXTEEN_BIT_FLOOR = 2.0**-16


def _boundary_reflectance(cos_in, n: float, n_slide: float | None):
    """Reflectance of the sample's face (to air, through a cover slide if any) seen from inside."""
    if n_slide is None:
        return fresnel(NUMPY, cos_in, 1.0 / n)[0]
    r1 = fresnel(NUMPY, cos_in, n_slide / n)[0]
    sin2 = (n / n_slide) ** 2 * (1.0 - cos_in**2)
    cos_glass = np.sqrt(np.clip(1.0 - sin2, 0.0, 1.0))
    r2 = np.where(sin2 >= 1.0, 1.0, fresnel(NUMPY, cos_glass, 1.0 / n_slide)[0])
    return np.where(r1 >= 1.0, 1.0, r1 + (1 - r1) ** 2 * r2 / (1 - r1 * r2))


def _hg_sample(g: float, u):
    if abs(g) < 1e-6:
        return 1.0 - 2.0 * u
    s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    return np.clip((1.0 + g * g - s * s) / (2.0 * g), -1.0, 1.0)


def _hg_pdf(g: float, cos_theta):
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * cos_theta) ** 1.5)


def _rotate(d, cos_t, phi):
    """Directions at angle acos(cos_t), azimuth phi around unit vectors d (N×3)."""
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, 1.0))
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    u = np.cross(helper, d)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(d, u)
    return (cos_t[:, None] * d + (sin_t * np.cos(phi))[:, None] * u + (sin_t * np.sin(phi))[:, None] * v)


MAX_ORDER = 4096  # scattering orders tallied apart; later ones (never seen within the gamut) are added to it


def _trace_orders(sigma_t: float, g: float, thickness_mm: float, n: float, photons: int, seed: int, geometry,
                  nee: bool):
    """The collimated measurement's light by scattering order: (unscattered, tally) with the in-scattered
    light at albedo α = Σ_k tally[k]·α^k. Absorption only scales a path's weight by α per scattering
    event, so one trace without it (the paths an α = 1 medium would take) serves every α."""
    params = geometry or load_geometry("device")
    coll = params["collimated"]
    n_slide = cover_slide_n(params)
    slide_t = cover_slide_thickness_mm(params)
    r_beam = float(coll["beam_diameter_mm"]) / 2
    r_ap = float(coll["aperture_diameter_mm"]) / 2
    z_ap = thickness_mm + slide_t + float(coll["aperture_distance_mm"])   # from the sample's back face
    rng = np.random.default_rng(seed)

    # Enter at normal incidence through the back (cover slide +) face.
    t_in = 1.0 - float(_boundary_reflectance(np.array(1.0), n, n_slide))
    radius = r_beam * np.sqrt(rng.random(photons))
    phi = 2 * math.pi * rng.random(photons)
    pos = np.column_stack([radius * np.cos(phi), radius * np.sin(phi), np.zeros(photons)])
    d = np.tile([0.0, 0.0, 1.0], (photons, 1))
    order = np.zeros(photons, dtype=np.int64)  # scattering events so far
    reflected_since_scatter = np.zeros(photons, dtype=bool)
    unscattered_tally = 0.0
    tally = np.zeros(MAX_ORDER + 1)
    events = 0
    while len(order):
        events += len(order)
        step = -np.log1p(-rng.random(len(order))) / sigma_t if sigma_t > 0 else np.full(len(order), np.inf)
        with np.errstate(divide="ignore"):
            to_face = np.where(d[:, 2] > 0, (thickness_mm - pos[:, 2]) / d[:, 2], -pos[:, 2] / d[:, 2])
        hits = step >= to_face
        # --- boundary: reflect or leave
        hit_idx = np.flatnonzero(hits)
        pos[hit_idx] += to_face[hit_idx, None] * d[hit_idx]
        cos_in = np.abs(d[hit_idx, 2])
        reflect = rng.random(len(hit_idx)) < _boundary_reflectance(cos_in, n, n_slide)
        d[hit_idx[reflect], 2] *= -1.0
        reflected_since_scatter[hit_idx[reflect]] = True
        leave = hit_idx[~reflect]
        front = leave[d[leave, 2] > 0]
        # Unscattered photons go straight along the axis: all pass the aperture.
        unscattered_tally += t_in * np.count_nonzero(order[front] == 0)
        late = front[(order[front] > 0) & (reflected_since_scatter[front] | (not nee))]
        if len(late):
            sin_air = n * np.sqrt(np.clip(1 - d[late, 2] ** 2, 0, 1))
            ok = sin_air < 1
            late, sin_air = late[ok], sin_air[ok]
            tan_air = sin_air / np.sqrt(1 - sin_air**2)
            lateral = np.linalg.norm(d[late, :2], axis=1)
            unit = np.where(lateral[:, None] > 0, d[late, :2] / np.maximum(lateral, 1e-300)[:, None], 0.0)
            at_ap = pos[late, :2] + unit * tan_air[:, None] * (z_ap - thickness_mm)
            through = late[np.linalg.norm(at_ap, axis=1) <= r_ap]
            np.add.at(tally, np.minimum(order[through], MAX_ORDER), t_in)
        alive = np.ones(len(order), dtype=bool)
        alive[leave] = False
        # --- scattering
        sc = np.flatnonzero(~hits)
        pos[sc] += step[sc, None] * d[sc]
        order[sc] += 1
        reflected_since_scatter[sc] = False
        if len(sc) and nee:
            # Next-event estimate towards a uniformly chosen point of the aperture, straight out through
            # the front face (a point, not the centre: HG g = 0.9 changes across a wide aperture).
            p = pos[sc]
            r_q, phi_q = r_ap * np.sqrt(rng.random(len(sc))), 2 * math.pi * rng.random(len(sc))
            to_ap = np.column_stack([r_q * np.cos(phi_q) - p[:, 0], r_q * np.sin(phi_q) - p[:, 1],
                                     np.full(len(sc), z_ap - p[:, 2])])
            dist = np.linalg.norm(to_ap, axis=1)
            cos_air = to_ap[:, 2] / dist
            sin_in = np.sqrt(1 - cos_air**2) / n
            cos_in = np.sqrt(1 - sin_in**2)
            lateral = np.linalg.norm(to_ap[:, :2], axis=1)
            unit = np.where(lateral[:, None] > 0, to_ap[:, :2] / np.maximum(lateral, 1e-300)[:, None], 0.0)
            d_in = np.column_stack([unit * sin_in[:, None], cos_in])
            omega_air = math.pi * r_ap**2 * cos_air / dist**2
            omega_in = omega_air * cos_air / (n * n * cos_in)
            t_out = 1.0 - _boundary_reflectance(cos_in, n, n_slide)
            beer = np.exp(-sigma_t * (thickness_mm - p[:, 2]) / cos_in)
            cos_scatter = np.einsum("ij,ij->i", d[sc], d_in)
            np.add.at(tally, np.minimum(order[sc], MAX_ORDER),
                      t_in * _hg_pdf(g, cos_scatter) * omega_in * beer * t_out)
        if len(sc):
            d[sc] = _rotate(d[sc], _hg_sample(g, rng.random(len(sc))), 2 * math.pi * rng.random(len(sc)))
        keep = np.flatnonzero(alive)
        pos, d, order, reflected_since_scatter = pos[keep], d[keep], order[keep], reflected_since_scatter[keep]
    return unscattered_tally / photons, tally / photons, events


def collimated_with_inscatter(alpha: float, sigma_t: float, g: float, thickness_mm: float, n: float,
                              photons: int = 200_000, seed: int = 0, geometry=None, nee: bool = True) -> dict:
    """Trace the collimated measurement: {'unscattered', 'inscattered', 'analytic', ...}. With
    `nee=False` scattered light is tallied only as photons exit (analog: the check of the NEE)."""
    unscattered, tally, events = _trace_orders(sigma_t, g, thickness_mm, n, photons, seed, geometry, nee)
    analytic = float(collimated_transmittance(sigma_t, thickness_mm, n, cover_slide_n(geometry or
                                                                                       load_geometry("device"))))
    return {"alpha": alpha, "sigma_t": sigma_t, "g": g, "thickness_mm": thickness_mm, "n": n,
            "analytic": analytic, "unscattered": unscattered,
            "inscattered": float(np.polynomial.polynomial.polyval(alpha, tally)), "photons": photons,
            "events": events}


def inscatter_report(seed: int = 0, photons: int = 100_000, say=print) -> list[dict]:
    """In-scattered light against I_c over the shipped maps' range, and the σt it costs: I_c is modelled
    as unscattered light only, so a measured I_c·(1 + r) reads as σt too low by ln(1 + r)/(σt·ℓ).
    Optical depths σt·ℓ up to the measurable gamut's edge (I_c ≥ MEASURABLE_IC), ℓ = 0.4 and 0.8 mm,
    g = 0.5 and 0.9 (most forward), α = 0.9 and 0.999."""
    rows = []
    # the σt·ℓ where I_c falls to MEASURABLE_IC (a hair inside, so that it counts as measurable)
    edge = 0.999 * float(beer_lambert_sigma_t(MEASURABLE_IC, 1.0, 1.5, cover_slide_n(load_geometry("device"))))
    say(f"I_c in-scattering (device collimated set-up, ≤ {photons} photons; σt·ℓ up to {edge:.1f}, the measurable "
        f"gamut's edge; 16-bit floor {SIXTEEN_BIT_FLOOR:.1e}):")
    for ell in (0.4, 0.8):
        for tau in (0.1, 0.5, 1.0, 2.0, 4.0, edge, 15.0):
            sigma_t = tau / ell
            for g in (0.5, 0.9):
                # Work per photon grows like τ²; the NEE tally converges fast, so deep slabs get fewer.
                budget = max(2000, int(photons * min(1.0, (8.0 / tau) ** 2)))
                unscattered, tally, _ = _trace_orders(sigma_t, g, ell, 1.5, budget, seed, None, nee=True)
                analytic = float(collimated_transmittance(sigma_t, ell, 1.5, cover_slide_n(load_geometry("device"))))
                for alpha in (0.9, 0.999):  # one trace serves both
                    inscattered = float(np.polynomial.polynomial.polyval(alpha, tally))
                    r = {"alpha": alpha, "sigma_t": sigma_t, "g": g, "thickness_mm": ell, "analytic": analytic,
                         "unscattered": unscattered, "inscattered": inscattered, "photons": budget,
                         "ratio": inscattered / analytic if analytic > 0 else math.inf}
                    r["sigma_t_bias"] = -math.log1p(r["ratio"]) / tau  # relative, < 0: σt read too low
                    rows.append(r)
                    say(f"  l={ell} st={sigma_t:6.2f} (σt·ℓ {tau:4.1f}) g={g} a={alpha}: I_c {analytic:.3e}, "
                        f"in-scattered {inscattered:.2e} = {100 * r['ratio']:.3g} % of it → σt "
                        f"{100 * r['sigma_t_bias']:+.2f} %")
    for floor in (0.1, 0.01, MEASURABLE_IC, SIXTEEN_BIT_FLOOR):
        inside = [r for r in rows if r["analytic"] >= floor]
        worst = max(inside, key=lambda r: r["ratio"], default=None)
        if worst is not None:
            say(f"  where I_c >= {floor:.3g}: in-scattered light <= {100 * worst['ratio']:.3g} % of I_c, σt read "
                f"low by <= {-100 * min(r['sigma_t_bias'] for r in inside):.2f} % (worst: α {worst['alpha']}, "
                f"g {worst['g']})")
    say(f"  largest in-scattered signal: {max(r['inscattered'] for r in rows):.2e} of the open-slot beam")
    return rows


# ------------------------------------------------------------------ the table the inversion corrects with
def traced_log1p_ratio(alphas, sigma_t: float, g: float, thickness_mm: float, n: float, geometry: dict,
                       photons: int, seed: int) -> np.ndarray:
    """L = ln(1 + in-scattered / unscattered) at each of `alphas`, for one (σt, g), from one trace."""
    _, tally, _ = _trace_orders(sigma_t, g, thickness_mm, n, photons, seed, geometry, nee=True)
    unscattered = float(collimated_transmittance(sigma_t, thickness_mm, n, cover_slide_n(geometry)))
    return np.log1p(np.polynomial.polynomial.polyval(np.asarray(alphas, dtype=float), tally) / unscattered)


def build_inscatter_table(n: float, thickness_mm: float, geometry_params: dict, *, photons: int = 30_000,
                          seed: int = 0, shape=(25, 21, 13), progress=None) -> InscatterTable:
    """Trace every (τ, g) column of an in-scattering table once (`_trace_orders`: all α from one trace)."""
    import time

    alphas, taus, gs = InscatterTable.axes(*shape)
    L = np.zeros(shape)
    t0 = time.perf_counter()
    for j, tau in enumerate(taus):
        if tau == 0.0:
            continue  # nothing scatters: L = 0
        for k, g in enumerate(gs):
            L[:, j, k] = traced_log1p_ratio(alphas, tau / thickness_mm, g, thickness_mm, n, geometry_params,
                                            photons, seed + 1000 * j + k)
        if progress:
            progress(j, len(taus))
    provenance = {"builder": "trimeter.forward.transport.inscatter_tracer.build_inscatter_table", "photons": photons,
                  "seed": seed,
                  "seconds": round(time.perf_counter() - t0, 1)}
    return InscatterTable(L, u_max=-math.log1p(-alphas[-1]), tau_max=taus[-1], v_max=-math.log1p(-gs[-1]), n=n,
                          thickness_mm=thickness_mm, geometry_params=geometry_params, provenance=provenance)
