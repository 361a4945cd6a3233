"""Direct renders of the diffuse observables, and the whole forward model (I_b, I_w rendered, I_c analytic).

These are the reference the map builder's fast tracer is validated against, so they are the plain
thing: Mitsuba's `volpath` (max_depth −1) into one pixel, one render per material and background.

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
from trimeter.forward.mitsuba_env import mitsuba
from trimeter.forward.scenes import (PARAM_KEYS, _Transform, integrator_for, reflectance_scale, resolve_geometry,
                                     scene_dict)
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


def _loaded(geometry, n: float, thickness_mm: float) -> _Loaded:
    mi = mitsuba()
    name, params = resolve_geometry(geometry)
    key = (mi.variant(), name, json.dumps(params, sort_keys=True), n, thickness_mm)
    if key not in _cache:
        # Load with representative (non-zero) values; every render overwrites them.
        scene = mi.load_dict(to_mitsuba(scene_dict(params, 0.5, 1.0, 0.5, n, thickness_mm, 0.5), mi))
        _cache.clear()   # one live scene at a time keeps JIT memory bounded
        _cache[key] = _Loaded(scene, mi.traverse(scene), reflectance_scale(params))
    return _cache[key]


def render_diffuse(geometry, alpha: float, sigma_t: float, g: float, n: float, thickness_mm: float,
                   rho: float, spp: int = DEFAULT_SPP, seed: int = 0) -> tuple[float, float]:
    """Reflectance factor I and its Monte Carlo std-error for one material on a Lambertian background
    of reflectance ρ, rendered with volpath. σt in 1/mm, ℓ in mm; `geometry` a preset name or dict."""
    alpha, sigma_t, g = require_material(alpha, sigma_t, g)
    n, thickness_mm = require_sample(n, thickness_mm)
    rho = require_reflectance("rho", rho)
    spp = int(require_number("spp", spp, lo=BATCHES))
    seed = int(require_number("seed", seed, lo=0))
    mi = mitsuba()
    loaded = _loaded(geometry, n, thickness_mm)
    p = loaded.params
    for name, value in (("alpha", alpha), ("sigma_t", sigma_t), ("g", g), ("rho", rho)):
        p[PARAM_KEYS[name]] = value
    p.update()
    integrator, _ = _integrator(mi, alpha)
    per_batch = math.ceil(spp / BATCHES)
    means = np.array([float(np.asarray(mi.render(loaded.scene, integrator=integrator, spp=per_batch,
                                                 seed=seed * BATCHES + b)).ravel()[0])
                      for b in range(BATCHES)]) * loaded.scale
    return float(means.mean()), float(means.std(ddof=1) / math.sqrt(BATCHES))


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
