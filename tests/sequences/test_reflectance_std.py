"""The reflectances' stds: per-bin frame spreads pooled over neighbouring bins, and a lamp's drift since
the calibration corrected by the lamp monitor with what it leaves as a std term."""

import numpy as np

from trimeter.domain import Calibration, Capture, RawSample
from trimeter.sequences import lamp_monitor
from trimeter.sequences.reflectance import (LAMP_SPECTRAL_REL, STD_POOL_BINS, lamp_correction, pooled_relative_std,
                                            reflectances)

N = 400


def test_pooling_turns_two_frame_spreads_into_a_steady_std():
    """Two frames per bin: a bin's own std scatters by ~60 % around the truth, the pooled one by a few %;
    NaN bins stay NaN and do not pull their neighbours."""
    rng = np.random.default_rng(0)
    true = np.linspace(0.004, 0.008, N)  # the noise level drifts slowly over the spectrum
    frames = true[:, None] * np.sqrt(2) * rng.standard_normal((N, 2))
    own = frames.std(axis=1, ddof=1) / np.sqrt(2)  # the standard error from two frames
    own[50] = np.nan
    pooled = pooled_relative_std(own)
    assert np.isnan(pooled[50]) and np.all(np.isfinite(np.delete(pooled, 50)))
    inner = slice(STD_POOL_BINS, N - STD_POOL_BINS)
    assert np.nanstd(own[inner] / true[inner]) > 0.4
    assert np.nanstd(pooled[inner] / true[inner]) < 0.25
    assert abs(np.nanmedian(pooled[inner] / true[inner]) - 1) < 0.1


def _light(setup, readings, panels, collimated):
    calibration = {name: lamp_monitor.record(p, c, [{"panel_left": 60 + 3100 * p, "panel_right": 60 + 3100 * p,
                                                     "collimated": 60 + 3000 * c}] * 2)
                   for name, p, c in (("white", True, False), ("collimated", False, True), ("dark", False, False))}
    shot = {setup: lamp_monitor.record(panels, collimated, readings)}
    return lamp_monitor.relative_light(calibration, shot)


def test_the_lamp_correction_is_the_open_lamps_mean_fraction_with_its_residual():
    readings = [{"panel_left": 60 + 3100 * 0.99, "panel_right": 60 + 3100 * 0.98, "collimated": 60},
                {"panel_left": 60 + 3100 * 0.98, "panel_right": 60 + 3100 * 0.97, "collimated": 60}]
    fraction, rel = lamp_correction(_light("black", readings, True, False), "black")
    assert abs(fraction - 0.98) < 1e-3  # the panels' mean; the closed collimated LED's reading is not used
    assert abs(rel - np.hypot(0.01 / 0.98, LAMP_SPECTRAL_REL * 0.02)) < 1e-3
    assert lamp_correction(None, "black") == (1.0, 0.0)
    assert lamp_correction({"error": "no references"}, "black") == (1.0, 0.0)
    assert lamp_correction(_light("white", readings, True, False), "black") == (1.0, 0.0)


def _capture(rate, rel_std):
    return Capture(rate=rate, saturated=np.zeros(N, bool), integration_times_us=np.array([1000.0]),
                   signals=rate[None], darks=np.zeros((1, N)), rate_std=rate * rel_std)


def test_a_dimmed_lamp_is_divided_out_of_the_shot_and_widens_its_std():
    """The panels gave 2 % less light during the sample's shots than at calibration: I_b, I_w come out
    as they would have under the calibrated light, and their stds grow by the correction's residual."""
    wl = np.linspace(400, 750, N)
    diffuse, coll = np.full(N, 1e5), np.full(N, 2e5)
    ones = np.full(N, 0.005)
    cal = Calibration(wl, diffuse, coll, np.full(N, 0.02), 0.99, np.zeros(N, np.int32), diffuse_rel_std=ones,
                      collimated_rel_std=ones,
                      lamp_monitor={"white": lamp_monitor.record(True, False, [{"panel_left": 3160, "panel_right": 3160,
                                                                                "collimated": 60}]),
                                    "collimated": lamp_monitor.record(False, True, [{"panel_left": 60,
                                                                                     "panel_right": 60,
                                                                                     "collimated": 3060}])})
    dim = {"panel_left": 60 + 3100 * 0.98, "panel_right": 60 + 3100 * 0.98, "collimated": 60}
    full = {"panel_left": 60, "panel_right": 60, "collimated": 3060}
    monitor = {"black": lamp_monitor.record(True, False, [dim, dim]),
               "white": lamp_monitor.record(True, False, [dim, dim]),
               "collimated": lamp_monitor.record(False, True, [full, full])}
    true_b, true_w, true_c = 0.1, 0.6, 0.3
    sample = RawSample(wl, _capture(true_b * 0.98 * diffuse, ones), _capture(true_w * 0.98 * diffuse, ones),
                       _capture(true_c * coll, ones), lamp_monitor=monitor)
    r = reflectances(cal, sample)
    np.testing.assert_allclose(r.I_b, true_b, rtol=1e-9)
    np.testing.assert_allclose(r.I_w, true_w, rtol=1e-9)
    np.testing.assert_allclose(r.I_c, true_c, rtol=1e-9)
    np.testing.assert_allclose(r.I_w_std / r.I_w, np.hypot(0.005 * np.sqrt(2), LAMP_SPECTRAL_REL * 0.02), rtol=1e-6)
    np.testing.assert_allclose(r.I_c_std / r.I_c, 0.005 * np.sqrt(2), rtol=1e-6)  # its lamp did not move
    without = reflectances(cal, RawSample(wl, sample.black, sample.white, sample.collimated))
    np.testing.assert_allclose(without.I_w, true_w * 0.98, rtol=1e-9)  # no monitor readings: nothing to correct
