"""Optics sanity: what the simulated spectrometer sees for each plant state, noise, saturation, drift."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.twin.optics import Optics, background_reflectance, material_names, material_spectra


def plant(slot="white", panels=1.0, collimated=0.0, panel_open=True, beam_open=False, time_s=0.0):
    return {"time_s": time_s, "slot": slot, "leds": {"panels": panels, "collimated": collimated},
            "shutters": {"panel_left": {"open": panel_open}, "panel_right": {"open": panel_open},
                         "collimated": {"open": beam_open}}}


@pytest.fixture
def optics(ideal_map):
    return Optics(ideal_map)


def test_no_sample_white_slot_counts_follow_the_diffuse_spectrum(optics):
    rng = np.random.default_rng(1)
    model = optics.spectrometer
    it_us = 50_000
    frames = np.stack([model.expose(optics.rate(plant("white")), it_us, rng) for _ in range(20)]).astype(float)
    dark_rate = optics.rate(plant("white", panels=0.0))
    dark = np.stack([model.expose(dark_rate, it_us, rng) for _ in range(20)]).astype(float)
    signal = frames.mean(0) - dark.mean(0)
    expected = optics.panels.spectrum() * optics.rho_white * it_us * 1e-6
    lit = expected > 2000  # well above read and shot noise
    assert lit.sum() > 300
    assert not (frames >= model.saturation_counts).any()
    np.testing.assert_allclose(signal[lit] / expected[lit], 1.0, atol=0.02)
    # The white reference is the geometry's 0.99: white / diffuse spectrum is flat at that value.
    np.testing.assert_allclose(optics.rho_white, 0.99)


def test_dark_frame_and_masked_pixels(optics):
    rng = np.random.default_rng(2)
    model = optics.spectrometer
    p = model.params
    closed = plant("white", panel_open=False)
    frame = model.expose(optics.rate(closed), 1_000_000, rng).astype(float)
    expected_dark = p["dark_offset_counts"] + p["dark_current_counts_per_s"] * 1.0
    assert abs(frame.mean() - expected_dark) < 3
    assert frame.std() < 4 * np.hypot(p["read_noise_counts"], np.sqrt(expected_dark / p["electrons_per_count"]))
    lit = model.expose(optics.rate(plant("white")), 100_000, rng).astype(float)
    masked = list(model.dark_pixels)
    assert len(masked) >= 4 and lit[masked].max() < expected_dark + 40  # covered pixels never see light


def test_saturation_clips_at_the_adc_limit(optics):
    rng = np.random.default_rng(3)
    model = optics.spectrometer
    frame = model.expose(optics.rate(plant("open", panels=0.0, collimated=1.0, beam_open=True)), 1_000_000, rng)
    assert frame.dtype == np.uint16
    assert frame.max() == model.saturation_counts
    assert (frame == model.saturation_counts).sum() > 100


def test_sample_observables_per_slot(optics):
    s = optics.insert_sample("cyan-ink", 0.4)
    diffuse = optics.panels.spectrum()
    np.testing.assert_allclose(optics.rate(plant("black")), diffuse * s.I_b)
    np.testing.assert_allclose(optics.rate(plant("white")), diffuse * s.I_w)
    np.testing.assert_allclose(optics.rate(plant(None)), diffuse * s.I_b)  # between slots: the black slider body
    beam = optics.collimated.spectrum()
    np.testing.assert_allclose(optics.rate(plant("open", panels=0.0, collimated=1.0, beam_open=True)), beam * s.I_c)
    assert np.all(s.I_w > s.I_b) and np.all((s.I_c > 0) & (s.I_c < 1))
    # Cyan absorbs red: less light comes back at 650 nm than at 480 nm.
    lam = optics.wavelengths_nm
    assert s.I_w[np.argmin(abs(lam - 650))] < 0.6 * s.I_w[np.argmin(abs(lam - 480))]
    one_panel = plant("white")
    one_panel["shutters"]["panel_right"]["open"] = False
    np.testing.assert_allclose(optics.rate(one_panel), 0.5 * diffuse * s.I_w)
    optics.remove_sample()
    np.testing.assert_allclose(optics.rate(plant("black")), diffuse * optics.rho_black)


def test_lamp_failure_darkens_only_the_failed_source(optics):
    beam_and_panels = plant("open", panels=1.0, collimated=1.0, beam_open=True)
    assert optics.rate(beam_and_panels, lamp_failure="panels").max() > 0  # the collimated LED still shines
    assert optics.rate(plant("white"), lamp_failure="panels").max() == 0
    assert optics.rate(beam_and_panels, lamp_failure="both").max() == 0


def test_led_warm_up_settles_exponentially(optics):
    led = optics.panels
    cold = led.spectrum().sum()
    outputs = []
    for t in np.arange(0.0, 900.0, 30.0):
        led.advance(t, 1.0)
        outputs.append(led.spectrum().sum())
    outputs = np.array(outputs)
    assert np.all(np.diff(outputs) < 0)  # dims monotonically while warming
    drop = 1 - outputs[-1] / cold
    assert 0.03 < drop < 0.05  # settles near the declared 4 % droop
    # after 10 time constants the drift per minute is negligible; after one it is not
    assert abs(outputs[-1] - outputs[-3]) / outputs[-1] < 1e-4 < abs(outputs[3] - outputs[1]) / outputs[1]
    led.advance(2000.0, 0.0)
    led.advance(4000.0, 0.0)
    assert led.heat < 1e-6  # cools down when switched off


def test_ptfe_white_option(ideal_map):
    ptfe = Optics(ideal_map, white="ptfe")
    assert ptfe.rho_white.min() < 0.975 < 0.985 < ptfe.rho_white.max() < 1.0  # dips in the near UV
    with pytest.raises(InputError, match="background must be one of"):
        Optics(ideal_map, white="snow")


def test_backgrounds_black_rises_above_650nm():
    lam = np.array([450.0, 550.0, 640.0, 750.0, 900.0])
    rho = background_reflectance("black", lam)
    assert rho[:3].max() < 0.05 and rho[3] > 0.1 and rho[4] > rho[3]
    ptfe = background_reflectance("ptfe", lam)
    assert np.all((ptfe > 0.97) & (ptfe < 1.0))


def test_catalogue_has_cmykw_inks_and_milk_with_plausible_spectra():
    names = material_names()
    for name in ("cyan-ink", "magenta-ink", "yellow-ink", "black-ink", "white-ink", "milk"):
        assert name in names
    lam = np.linspace(345, 1000, 500)
    for name in names:
        s = material_spectra(name, lam)
        assert np.all((s["alpha"] > 0) & (s["alpha"] < 1)) and np.all(s["sigma_t"] > 0)
        assert np.max(np.abs(np.diff(s["alpha"]))) < 0.02  # smooth: no jumps between neighbouring pixels


def test_bad_samples_are_refused_clearly(optics, ideal_map, tmp_path):
    with pytest.raises(InputError, match="sample must be one of"):
        optics.insert_sample("unobtainium", 0.4)
    with pytest.raises(InputError, match="thickness_mm=0.7"):
        optics.insert_sample("milk", 0.7)
    with pytest.raises(InputError, match="thickness_mm must be positive"):
        optics.insert_sample("milk", float("nan"))
    narrow = type(ideal_map)(recipe=ideal_map.recipe, alpha=ideal_map.alpha, sigma_t=ideal_map.sigma_t[:3],
                             g=ideal_map.g, A=ideal_map.A[:, :3], B=ideal_map.B[:, :3], C=ideal_map.C[:, :3],
                             std_b=ideal_map.std_b[:, :3], std_w=ideal_map.std_w[:, :3])
    with pytest.raises(InputError, match="sigma_t spans"):
        Optics(narrow).insert_sample("cyan-ink", 0.4)
    assert optics.sample is None  # a refused insertion changes nothing


def test_every_material_fits_every_device_map_recipe():
    """The twin refuses a sample outside its map; so the catalogue must fit the shipped maps' grids."""
    import tomllib

    from trimeter.paths import MAPS_DIR

    recipes = [tomllib.loads(p.read_text()) for p in sorted((MAPS_DIR / "recipes").glob("*.toml"))]
    recipes = [r for r in recipes if r.get("geometry") == "device" and "grid" in r]
    if not recipes:
        pytest.skip("no device map recipes in maps/recipes")
    lam = np.linspace(345, 1000, 300)
    for recipe in recipes:
        grid = recipe["grid"]
        for name in material_names():
            s = material_spectra(name, lam)
            assert s["alpha"].max() <= grid["alpha"]["max"], (recipe["name"], name)
            assert grid["sigma_t"]["min"] <= s["sigma_t"].min() and s["sigma_t"].max() <= grid["sigma_t"]["max"]
            assert grid["g"]["min"] <= s["g"].min() and s["g"].max() <= grid["g"]["max"], (recipe["name"], name)


def test_map_choice_by_thickness_device_geometry_first(ideal_map):
    import dataclasses

    device = dataclasses.replace(ideal_map, recipe={**ideal_map.recipe, "geometry": "device", "name": "dev"}, path=None)
    thicker = dataclasses.replace(ideal_map, recipe={**ideal_map.recipe, "thickness_mm": 0.8, "name": "thick"},
                                  path=None)
    optics = Optics([ideal_map, device, thicker])
    assert optics.insert_sample("milk", 0.4).map_name == "dev"
    assert optics.insert_sample("milk", 0.8).map_name == "thick"
