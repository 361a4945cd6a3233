"""Scene dicts (no Mitsuba needed): what each observable needs and nothing else; the white-reference
normalisation in closed form."""

import math
import subprocess
import sys

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.forward.nonscattering import _panel_directions
from trimeter.forward.scenes import integrator_for, panel_corners, panel_irradiance, reflectance_scale, scene_dict
from trimeter.geometry import load_geometry


def _types(scene):
    return sorted(v["type"] for v in scene.values() if isinstance(v, dict))


def test_importing_the_forward_package_does_not_import_mitsuba():
    code = ("import sys, trimeter.forward.render, trimeter.forward.scenes, trimeter.forward.validate, "
            "trimeter.forward.transport.inscatter_tracer, trimeter.cli.cmd_forward; print('mitsuba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_ideal_scene_is_slab_background_sky_radiancemeter():
    scene = scene_dict("ideal", 0.9, 2.0, 0.5, 1.5, 0.5, 0.3)
    sensors = [v for v in scene.values() if isinstance(v, dict) and v["type"] == "radiancemeter"]
    assert len(sensors) == 1 and sensors[0]["direction"] == [0.0, 0.0, -1.0]
    assert [v["type"] for v in scene.values() if isinstance(v, dict) and v["type"] == "constant"] == ["constant"]
    assert scene["integrator"] == {"type": "volpath", "max_depth": -1, "rr_depth": 5}
    medium = scene["sample_medium"]
    assert (medium["albedo"], medium["sigma_t"], medium["phase"]) == (0.9, 2.0, {"type": "hg", "g": 0.5})
    assert scene["background"]["bsdf"]["reflectance"]["value"] == 0.3
    # two dielectric faces, four mirror sides of the slab and four of the air gap, one background: nothing else
    assert _types(scene).count("rectangle") == 11
    assert sum(1 for v in scene.values() if isinstance(v, dict) and v.get("bsdf", {}).get("type") == "conductor") == 8
    assert sum(1 for v in scene.values() if isinstance(v, dict) and v.get("bsdf", {}).get("type") == "dielectric") == 2


def test_device_scene_has_four_interfaces_two_panels_and_a_one_pixel_orthographic_sensor():
    scene = scene_dict("device", 0.9, 2.0, 0.5, 1.5, 0.4, 0.02)
    emitters = [v for v in scene.values() if isinstance(v, dict) and "emitter" in v]
    assert len(emitters) == 2
    faces = [k for k in scene if k in ("slide_front", "sample_front", "sample_back", "slide_back")]
    assert len(faces) == 4
    assert scene["sample_front"]["bsdf"] == {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.52}
    assert scene["slide_front"]["bsdf"] == {"type": "dielectric", "int_ior": 1.52, "ext_ior": 1.0}
    assert scene["sensor"]["type"] == "orthographic"
    assert (scene["sensor"]["film"]["width"], scene["sensor"]["film"]["height"]) == (1, 1)
    assert not any(isinstance(v, dict) and v["type"] in ("constant", "envmap") for v in scene.values())
    # index-matched sample and slides: the inner faces vanish instead of becoming eta = 1 dielectrics
    matched = scene_dict("device", 0.9, 2.0, 0.5, 1.52, 0.4, 0.02)
    assert matched["sample_front"]["bsdf"] == {"type": "null"}


def test_panels_are_where_geometry_toml_puts_them():
    p = load_geometry("device")
    for quad in panel_corners(p):
        centre = quad.mean(axis=0)
        assert np.linalg.norm(centre) == pytest.approx(p["panels"]["distance_mm"])
        elevation = math.degrees(math.acos(centre[2] / np.linalg.norm(centre)))
        assert elevation == pytest.approx(p["panels"]["elevation_deg"])
        sides = sorted([np.linalg.norm(quad[1] - quad[0]), np.linalg.norm(quad[3] - quad[0])])
        assert sides == pytest.approx(sorted([p["panels"]["width_mm"], p["panels"]["height_mm"]]))


def test_white_reference_normalisation_closed_form_matches_quadrature():
    p = load_geometry("device")
    point = np.array([0.0, 0.0, -p["background_gap_mm"]])
    _, weights = _panel_directions(p, 400, 200)
    assert panel_irradiance(p, point) == pytest.approx(weights.sum(), rel=1e-4)
    assert reflectance_scale("device") == pytest.approx(math.pi / weights.sum(), rel=1e-4)
    assert reflectance_scale("ideal") == 1.0
    # a single small panel far away: E ≈ A cosθ_panel cosθ_receiver / d²
    far = {**p, "panels": {**p["panels"], "width_mm": 1.0, "height_mm": 1.0, "distance_mm": 1000.0, "count": 1}}
    assert panel_irradiance(far, np.zeros(3)) == pytest.approx(math.cos(math.radians(45)) / 1000.0**2, rel=1e-4)


def test_unknown_geometry_is_an_input_error():
    with pytest.raises(InputError, match="geometry"):
        scene_dict("fridge", 0.5, 1.0, 0.0, 1.5, 0.5, 0.5)


def test_no_roulette_at_high_albedo_and_a_depth_cap_that_bounds_the_truncation():
    for alpha in (0.951, 0.99, 0.999, 0.9999):
        spec = integrator_for(alpha)
        assert spec["rr_depth"] >= 1 << 30
        assert alpha ** (spec["max_depth"] / 16) <= 1e-6
    assert integrator_for(1.0)["max_depth"] == -1
    assert integrator_for(0.5) == {"type": "volpath", "max_depth": -1, "rr_depth": 5}
    assert scene_dict("ideal", 0.999, 1.0, 0.0, 1.5, 0.5, 0.5)["integrator"] == integrator_for(0.999)


@pytest.mark.parametrize("geometry", ["ideal", "device"])
def test_a_translated_scene_moves_every_shape_and_the_sensor_and_nothing_else(geometry):
    from trimeter.forward.scenes import _Transform, top_face_z, translated

    scene = scene_dict(geometry, 0.5, 1.0, 0.5, 1.5, 0.4, 0.5)
    moved = translated(scene, 10.0)
    assert moved.keys() == scene.keys()
    placed = 0
    for key, value in scene.items():
        if not isinstance(value, dict):
            assert moved[key] == value
            continue
        if isinstance(value.get("to_world"), _Transform):
            shift = moved[key]["to_world"].matrix - value["to_world"].matrix
            assert np.allclose(shift[:, :3], 0) and np.allclose(shift[:, 3], [0, 0, 10.0, 0]), key
            placed += 1
        elif value.get("type") == "radiancemeter":
            assert moved[key]["origin"] == [value["origin"][0], value["origin"][1], value["origin"][2] + 10.0]
            placed += 1
        else:
            assert moved[key] == value, key
    assert placed >= 4
    fresh = scene_dict(geometry, 0.5, 1.0, 0.5, 1.5, 0.4, 0.5)["sensor"]                  # not changed in place
    assert (np.array_equal(fresh["to_world"].matrix, scene["sensor"]["to_world"].matrix) if "to_world" in fresh
            else fresh == scene["sensor"])
    assert top_face_z(geometry, 0.4) == (0.0 if geometry == "ideal" else 0.4 + 2 * 0.15)
