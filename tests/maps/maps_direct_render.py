"""Direct volpath renders for the map tests (a helper module, not a test file)."""

import math


from trimeter.geometry import load_geometry


def render_black_panels(geometry, alpha, sigma_t, g, n, ell, rho, spp, seed=0):
    """A volpath direct render of trimeter.forward.scenes' scene with the LED panels' surface forced
    black (their reflectance must be 0: the white-reference normalisation E assumes panels of radiance
    exactly 1; grey panels added +1.7 % at σt = 0.5, α = 0, ρ = 0.9 before forward/ fixed it in 29faea0).
    Kept explicit so that these tests don't depend on that default."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_pixel, to_mitsuba
    from trimeter.forward.scenes import reflectance_scale, scene_dict

    mi = mitsuba()
    params = load_geometry(geometry)
    d = scene_dict(params, alpha, sigma_t, g, n, ell, rho, spp=spp)
    for key, shape in d.items():
        if key.startswith("panel") and isinstance(shape, dict):
            shape["bsdf"] = {"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}}
    scene = mi.load_dict(to_mitsuba(d, mi))
    batches = 8
    values = render_pixel(scene, scene.integrator(), spp, seed, batches) * reflectance_scale(params)
    return float(values.mean()), float(values.std(ddof=1) / math.sqrt(batches))
