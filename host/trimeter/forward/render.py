"""Direct renders of the diffuse observables, and the whole forward model (I_b, I_w rendered, I_c analytic).

These are the reference the map builder's fast tracer is validated against, so they are the plain
thing: Mitsuba's `volpath` (max_depth −1) for the one-pixel sensor's rays, averaged in float64
(render_pixel), one render per material and background.

Std-error: the samples are split into `BATCHES` independent renders with distinct seeds; the
std-error is the spread of the batch means / √BATCHES — it counts every source of variance, including
Russian roulette and rare long paths. Seeds are deterministic: batch b of seed s uses s·BATCHES + b.

Scenes are loaded once per (variant, geometry, n, ℓ) and the material and background are updated in
place (mi.traverse): a new scene would otherwise re-JIT the whole kernel (~0.5 s) for each material.

Russian roulette: none above α = 0.95, where it made the estimate heavy-tailed; see
trimeter.forward.scenes.integrator_for. The integrator is passed per render (scenes are cached).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from trimeter.model.collimated import collimated_transmittance
from trimeter.errors import InputError
from trimeter.forward.mitsuba_env import mitsuba
from trimeter.forward.phase import PHASES, register_phases
from trimeter.forward.scenes import (PARAM_KEYS, _Transform, integrator_for, reflectance_scale, resolve_geometry,
                                     scene_dict, top_face_z, translated)
from trimeter.geometry import cover_slide_n
from trimeter.validation import require_material, require_number, require_reflectance, require_sample

BATCHES = 16
DEFAULT_SPP = 262144


_integrators: dict[tuple, object] = {}


def _integrator(mi, alpha: float):
    spec = integrator_for(alpha)
    key = (mi.variant(), spec["max_depth"], spec["rr_depth"])
    if key not in _integrators:
        _integrators[key] = mi.load_dict(spec)
    return _integrators[key], spec


@dataclass
class _Loaded:
    scene: object
    params: Any  # mitsuba.SceneParameters: mitsuba is imported lazily, so it is not named here
    scale: float


_cache: dict[tuple, _Loaded] = {}


def to_mitsuba(obj, mi):
    """Replace the scene module's plain 4×4 matrices by Mitsuba transforms, recursively."""
    if isinstance(obj, _Transform):
        return mi.ScalarTransform4f(obj.matrix.tolist())
    if isinstance(obj, dict):
        return {k: to_mitsuba(v, mi) for k, v in obj.items()}
    return obj


def _loaded(geometry, n: float, thickness_mm: float, z_offset: float = 0.0, phase: str = "hg") -> _Loaded:
    mi = mitsuba()
    name, params = resolve_geometry(geometry)
    key = (mi.variant(), name, json.dumps(params, sort_keys=True), n, thickness_mm, z_offset, phase)
    if key not in _cache:
        if phase not in PHASES:
            raise InputError(f"phase must be one of {', '.join(PHASES)}, got {phase!r}")
        register_phases(mi)
        # Load with representative (non-zero) values; every render overwrites them.
        scene = scene_dict(params, 0.5, 1.0, 0.5, n, thickness_mm, 0.5, phase=phase)
        scene = mi.load_dict(to_mitsuba(translated(scene, z_offset) if z_offset else scene, mi))
        if len(_cache) >= 2:   # a few live scenes at a time keep JIT memory bounded
            _cache.clear()
        _cache[key] = _Loaded(scene, mi.traverse(scene), reflectance_scale(params))
    return _cache[key]


def render_diffuse(geometry, alpha: float, sigma_t: float, g: float, n: float, thickness_mm: float,
                   rho: float, spp: int = DEFAULT_SPP, seed: int = 0, z_offset: float = 0.0) -> tuple[float, float]:
    """Reflectance factor I and its Monte Carlo std-error for one material on a Lambertian background
    of reflectance ρ, rendered with volpath. σt in 1/mm, ℓ in mm; `geometry` a preset name or dict;
    `z_offset` [mm]: the scene moved along its normal (render_diffuse_offset_free)."""
    means = render_diffuse_batches(geometry, alpha, sigma_t, g, n, thickness_mm, rho, spp, seed, z_offset)
    return float(means.mean()), float(means.std(ddof=1) / math.sqrt(BATCHES))


def render_diffuse_batches(geometry, alpha: float, sigma_t: float, g: float, n: float, thickness_mm: float,
                           rho: float, spp: int = DEFAULT_SPP, seed: int = 0, z_offset: float = 0.0,
                           phase: str = "hg") -> np.ndarray:
    """render_diffuse's BATCHES batch means (reflectance factors), for comparisons whose renders share
    seeds: their batch-wise differences give the difference's own std-error, smaller than either's.
    `phase`: the medium's phase function (trimeter.forward.phase: hg, or hg_depolarising)."""
    alpha, sigma_t, g = require_material(alpha, sigma_t, g)
    n, thickness_mm = require_sample(n, thickness_mm)
    rho = require_reflectance("rho", rho)
    spp = int(require_number("spp", spp, lo=BATCHES))
    seed = int(require_number("seed", seed, lo=0))
    mi = mitsuba()
    loaded = _loaded(geometry, n, thickness_mm, float(z_offset), phase)
    p = loaded.params
    for name, value in (("alpha", alpha), ("sigma_t", sigma_t), ("g", g), ("rho", rho)):
        p[PARAM_KEYS[name]] = value
    p.update()
    integrator, _ = _integrator(mi, alpha)
    return render_pixel(loaded.scene, integrator, spp, seed) * loaded.scale


# Rays per launch of render_pixel (memory: volpath's state is a few hundred bytes per ray).
LANES = 1 << 20


def render_pixel(scene, integrator, spp: int, seed: int, batches: int = BATCHES) -> np.ndarray:
    """The mean radiance seen by the scene's one-pixel sensor, in `batches` independent batches of
    spp/batches rays (their means, float64): rays from the sensor, `integrator.sample` for each, the
    mean taken in float64. Not mi.render: its film sums a pixel's samples in float32, whose rounding at
    the sample counts a check needs is far larger than the noise (figures: the git history of maps/README.md).
    Batch b, launch j is seeded from (seed, b, j)."""
    mi = mitsuba()
    sensor = scene.sensors()[0]
    per_batch = math.ceil(spp / batches)
    means = np.empty(batches)
    for b in range(batches):
        total = 0.0
        for j, start in enumerate(range(0, per_batch, LANES)):
            lanes = min(LANES, per_batch - start)
            sampler = mi.load_dict({"type": "independent"})
            sampler.seed(((seed * batches + b) * 4096 + j) & 0xFFFFFFFF, lanes)
            ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), sampler.next_2d(), sampler.next_2d())
            radiance, _, _ = integrator.sample(scene, sampler, ray, None, True)    # the sensors are in air
            value = radiance * weight
            if mi.is_polarized:  # a Mueller matrix per ray: the unpolarised detector reads its intensity element
                value = mi.unpolarized_spectrum(value)
            total += float(np.asarray(value, dtype=np.float64).sum())
        means[b] = total / per_batch
    return means


# Mitsuba spawns every ray off a surface at ε = RayEpsilon·(1 + max|p|) in float32 (p in scene units, mm
# here), a fraction of a µm at the sample, where a dense sample's light scatters within tens of µm of the
# surface. Rays spawned past that layer skip its scattering, so volpath comes out low, the more so the more
# light is single-scattered just under the surface (figures: the git history of maps/README.md). The loss
# is linear in ε, so a second render with the scene moved away from the origin by OFFSET_SHIFT_MM
# (ε ∝ 1 + top + shift) extrapolates it to ε = 0; at a quarter of the samples its noise adds
# ~(1 + top)/shift × 2 of the first render's to the result.
OFFSET_SHIFT_MM = 10.0


def render_diffuse_offset_free(geometry, alpha: float, sigma_t: float, g: float, n: float, thickness_mm: float,
                               rho: float, spp: int = DEFAULT_SPP, seed: int = 0) -> tuple[float, float, float]:
    """render_diffuse extrapolated to no ray offset: (I, its std-error, I as rendered). Two renders, the
    scene as declared (`spp`) and moved by OFFSET_SHIFT_MM (spp/4, other seeds), and
    I = I₀ + (I₀ − I_shift)·(1 + top)/shift, with top the stack's top face (its hits set max|p|)."""
    I0, s0 = render_diffuse(geometry, alpha, sigma_t, g, n, thickness_mm, rho, spp, seed)
    I1, s1 = render_diffuse(geometry, alpha, sigma_t, g, n, thickness_mm, rho, max(spp // 4, BATCHES),
                            seed + 1_000_003, z_offset=OFFSET_SHIFT_MM)
    k = (1 + top_face_z(geometry, thickness_mm)) / OFFSET_SHIFT_MM
    return I0 + k * (I0 - I1), math.hypot((1 + k) * s0, k * s1), I0


def forward(geometry, alpha: float, sigma_t: float, g: float, thickness_mm: float, n: float,
            rho_b: float, rho_w: float, spp: int = DEFAULT_SPP, seed: int = 0) -> dict:
    """The forward model: {I_b, I_w, I_c, stderr: {I_b, I_w}, provenance}. I_b and I_w are rendered
    with the same seeds (so their difference has less noise than either); I_c is analytic."""
    alpha, sigma_t, g = require_material(alpha, sigma_t, g)
    n, thickness_mm = require_sample(n, thickness_mm)
    rho_b, rho_w = require_reflectance("rho_b", rho_b), require_reflectance("rho_w", rho_w)
    name, params = resolve_geometry(geometry)
    start = time.perf_counter()
    I_b, s_b = render_diffuse(params, alpha, sigma_t, g, n, thickness_mm, rho_b, spp, seed)
    I_w, s_w = render_diffuse(params, alpha, sigma_t, g, n, thickness_mm, rho_w, spp, seed)
    I_c = float(collimated_transmittance(sigma_t, thickness_mm, n, cover_slide_n(params)))
    mi = mitsuba()
    return {"I_b": I_b, "I_w": I_w, "I_c": I_c, "stderr": {"I_b": s_b, "I_w": s_w},
            "provenance": {"geometry": name, "engine": "volpath", "integrator": integrator_for(alpha),
                           "variant": mi.variant(),
                           "mitsuba_version": mi.__version__, "spp": BATCHES * math.ceil(spp / BATCHES),
                           "seed": seed, "seconds": round(time.perf_counter() - start, 3)}}
