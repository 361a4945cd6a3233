"""measure() with a multichannel sensor: band-aware when the sensor has band weights (values at the
channels' centroids, method "bands"), every value flagged PER_CHANNEL_BANDS when it has none."""

import json

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from hil_support import HIL_MAP
from trimeter.device.client import Device
from trimeter.domain import Sample
from trimeter.inversion.flags import FitFlag
from trimeter.formats.appearance import AppearanceMap
from trimeter.inversion.artifacts import load_artifacts
from trimeter.sequences import Runner, calibration
from trimeter.sequences.measure import measure
from trimeter.sequences.settings import HostSettings
from trimeter.spectrometer.base import SpectrometerDescription
from trimeter.spectrometer.i2c import CHANNEL_NM
from trimeter.spectrometer.sensors import as7341_weights

CENTRES = np.array(list(CHANNEL_NM.values()))


class FakeMultichannel(FakeSpectrometer):
    def __init__(self, *args, weights=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._weights = weights

    @property
    def description(self):
        d = super().description
        return SpectrometerDescription(d.model, d.serial, d.pixels, d.wavelength_range_nm, d.integration_time_us_limits,
                                       d.saturation_counts, (), {"channels": list(CHANNEL_NM)})

    def band_weights(self):
        return self._weights


@pytest.fixture(scope="module")
def amap():
    return AppearanceMap.load(HIL_MAP)


@pytest.fixture(scope="module")
def band_readings(amap):
    """Band readings of a smooth magenta-like spectrum (the map's forward model per wavelength)."""
    weights = as7341_weights()
    lam = weights.wavelength_nm
    sigma_a = 0.01 + 2.1 * np.exp(-0.5 * ((lam - 545) / 40) ** 2)
    sigma_s = 3.3 * (lam / 500) ** -0.8
    truth = (sigma_s / (sigma_s + sigma_a), sigma_s + sigma_a, 0.6 - 0.02 * (lam - 500) / 100)
    I = load_artifacts(amap).grid.intensities(*truth, np.full(lam.size, 0.03), np.full(lam.size, 0.99))
    readings = (weights.diffuse @ I[0], weights.diffuse @ I[1], weights.collimated @ I[2])
    return weights, readings, [np.interp(weights.centre_nm, lam, t) for t in truth]


def _measure(tmp_path, monkeypatch, amap, readings, weights):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    fake = FakeInstrument(busy_polls=1)
    n = len(CENTRES)
    optics = FakeOptics(CENTRES, diffuse=np.full(n, 3e6), collimated=np.full(n, 5e6), rho_black=np.full(n, 0.03),
                        rho_white=0.99)
    runner = Runner(Device(fake), FakeMultichannel(fake, optics, weights=weights), sleep=lambda s: None)
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    optics.sample = readings
    settings = HostSettings()
    settings.set("results_dir", str(tmp_path / "results"))
    return measure(runner, cal, [Sample(0.4, amap)], settings)


def test_a_sensor_with_band_weights_is_fitted_band_aware(tmp_path, monkeypatch, amap, band_readings):
    weights, readings, (alpha, sigma_t, _) = band_readings
    outcome = _measure(tmp_path, monkeypatch, amap, readings, weights)
    p = outcome.parameters
    np.testing.assert_allclose(p.wavelengths_nm, weights.centre_nm)
    assert np.max(np.abs(p.alpha - alpha)) < 0.01 and np.max(np.abs(p.sigma_t / sigma_t - 1)) < 0.02
    assert not np.any(p.flags & int(FitFlag.PER_CHANNEL_BANDS))
    assert json.loads((outcome.path / "measurement.json").read_text())["method"] == "bands"


def test_a_sensor_without_band_weights_is_flagged_per_channel(tmp_path, monkeypatch, amap, band_readings):
    _, readings, _ = band_readings
    outcome = _measure(tmp_path, monkeypatch, amap, readings, None)
    p = outcome.parameters
    np.testing.assert_allclose(p.wavelengths_nm, CENTRES)
    assert np.all(p.flags & int(FitFlag.PER_CHANNEL_BANDS))
    assert any("PER_CHANNEL_BANDS" in note for note in outcome.measurement.provenance.advice)


def test_a_refit_takes_the_recorded_sensor(amap):
    from trimeter.sequences.measure import for_recorded_sensor, prepare_fit

    prepared = prepare_fit([Sample(0.4, amap)], "lut")
    assert for_recorded_sensor(prepared, {"model": "fake", "extra": {}}) == prepared
    channels = list(CHANNEL_NM)
    as7341 = for_recorded_sensor(prepared, {"model": "AS7341", "extra": {"channels": channels}})
    assert as7341.bands is not None and as7341.bands.channels == tuple(channels) and as7341.multichannel
    twin = for_recorded_sensor(prepared, {"model": "AS7341-TWIN", "extra": {"channels": channels}})
    assert twin.bands is None and twin.multichannel
