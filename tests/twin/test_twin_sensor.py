"""The twin's AS7341 (trimeter.twin.sensor): nine channel counts of the twin's light with gain, shot
and read noise and the ADC's full scale; its band weights are what its readings are weighted means of;
the sim backend gets them over BANDS? (a spectrometer has none)."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer import open_spectrometer
from trimeter.twin.optics import Optics
from trimeter.twin.sensor import ADC_MAX_COUNTS, As7341Model
from trimeter.twin.specserver import SpectrometerServer

PLANT_WHITE = {"time_s": 0.0, "slot": "white", "leds": {"panels": 1.0, "collimated": 0.0},
               "shutters": {"panel_left": {"open": True}, "panel_right": {"open": True}}}


@pytest.fixture(scope="module")
def optics():
    return Optics(sensor="as7341")


def test_counts_gain_noise_and_saturation(optics):
    sensor = optics.sensor
    assert isinstance(sensor, As7341Model) and len(sensor.wavelengths_nm) == 9
    rate = optics.rate(PLANT_WHITE)
    lo = sensor.integration_time_us_limits[0]
    rng = np.random.default_rng(0)
    counts = sensor.expose(rate, lo, rng)
    assert counts.dtype == np.uint16 and counts.shape == (9,) and np.all(counts > 0)
    frames = np.stack([sensor.expose(rate, lo, rng).astype(float) for _ in range(40)])
    spread = frames.std(axis=0)
    assert np.all(spread > 1.0)  # shot and read noise
    sensor.gain = 128.0
    doubled = np.stack([sensor.expose(rate, lo, rng).astype(float) for _ in range(40)]).mean(axis=0)
    sensor.gain = 64.0
    np.testing.assert_allclose(doubled - 4, 2 * (frames.mean(axis=0) - 4), rtol=0.05)
    assert np.all(sensor.expose(rate * 1e4, lo, rng) == ADC_MAX_COUNTS)  # clipped at full scale


def test_band_weights_are_what_the_readings_average(optics):
    """A noise-free channel ratio (sample over white, as the calibration takes it) is the band weights'
    weighted mean of the per-pixel ratio."""
    sensor = optics.sensor
    weights = sensor.band_weights()
    optics.remove_sample()
    optics.panels.heat = 1.0  # warm, as the weights take the lamps
    white = sensor._response @ optics.rate(PLANT_WHITE) / optics.rho_white[0]  # the white reference is flat
    s = optics.insert_sample("magenta-ink", 0.4)
    black = sensor._response @ optics.rate({**PLANT_WHITE, "slot": "black"})
    np.testing.assert_allclose(black / white, weights.diffuse @ s.I_b, rtol=1e-6)
    optics.remove_sample()
    optics.panels.heat = 0.0


def test_unknown_sensor_is_refused():
    with pytest.raises(InputError, match="sensor must be one of"):
        Optics(sensor="webcam")


def test_bands_over_the_line_protocol(optics):
    sensor = optics.sensor
    server = SpectrometerServer(sensor.description(), sensor.wavelengths_nm,
                                lambda it_us: (np.zeros(9, np.uint16), 0.0), bands=sensor.band_weights())
    try:
        with open_spectrometer(f"sim:{server.port}") as spec:
            assert spec.description.extra["channels"][0] == "F1"
            got = spec.band_weights()
            assert got.channels == sensor.band_weights().channels
            np.testing.assert_allclose(got.diffuse, sensor.band_weights().diffuse, rtol=1e-9)
    finally:
        server.close()
    plain = Optics().sensor
    server = SpectrometerServer(plain.description(), plain.wavelengths_nm,
                                lambda it_us: (np.zeros(1024, np.uint16), 0.0))
    try:
        assert server.handle("BANDS?").startswith("ERR")
        with open_spectrometer(f"sim:{server.port}") as spec:
            assert spec.band_weights() is None
    finally:
        server.close()


def test_a_bad_bands_reply_is_a_device_error(optics):
    sensor = optics.sensor
    server = SpectrometerServer(sensor.description(), sensor.wavelengths_nm,
                                lambda it_us: (np.zeros(9, np.uint16), 0.0), bands=sensor.band_weights())
    server._bands = '{"wavelength_nm": [1, 2]}'
    try:
        with open_spectrometer(f"sim:{server.port}") as spec, pytest.raises(DeviceError, match="bad BANDS"):
            spec.band_weights()
    finally:
        server.close()


def test_a_twin_with_an_as7341_reads_nine_channels_and_hands_out_its_weights(ideal_map):
    from trimeter.twin import Twin

    with Twin(time_scale=100, appearance_map=ideal_map, sensor="as7341") as twin:
        with open_spectrometer(twin.spectrometer_url) as spec:
            assert spec.description.model == "AS7341-TWIN" and spec.description.pixels == 9
            assert spec.description.dark_pixels == ()
            spec.integration_time_us = spec.integration_time_us_limits[0]
            counts = spec.intensities()
            assert counts.shape == (9,) and np.all(counts <= spec.saturation_counts)
            weights = spec.band_weights()
            assert weights is not None and weights.channels[-1] == "NIR"
    with pytest.raises(InputError, match="sensor must be one of"):
        Twin(appearance_map=ideal_map, sensor="webcam").start()
