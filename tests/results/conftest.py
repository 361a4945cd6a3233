"""The measurement every results test writes: a fake instrument's calibration and capture, and a fit
with an unusable (NaN) bin."""

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from trimeter.device.client import Device
from trimeter.domain.parameters import FitResult
from trimeter.domain import MapIdentity, Measurement, Provenance, Sample, SampleCapture
from trimeter.results import Parameters
from trimeter.sequences import Runner, calibration, reflectances, sample_capture

WL = np.linspace(400, 700, 31)


@pytest.fixture(scope="module")
def measurement():
    fake = FakeInstrument(busy_polls=1)
    optics = FakeOptics(WL, diffuse=np.full(31, 1e6), collimated=np.full(31, 2e6), rho_black=np.full(31, 0.03),
                        rho_white=0.99)
    runner = Runner(Device(fake), FakeSpectrometer(fake, optics), sleep=lambda s: None)
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    optics.sample = (np.full(31, 0.2), np.full(31, 0.5), np.full(31, 0.1))
    raw = runner.run(sample_capture(hdr_decades=1))
    refl = reflectances(cal, raw)
    alpha = np.linspace(0.5, 0.99, 31)
    alpha[3] = np.nan  # an unusable bin must survive every writer
    result = FitResult(alpha=alpha, sigma_t=np.linspace(1, 5, 31), g=np.full(31, 0.4), alpha_std=np.full(31, 0.01),
                       sigma_t_std=np.full(31, 0.1), g_std=np.full(31, 0.05), flags=np.where(np.isnan(alpha), 1, 0),
                       sigma_t_beer=np.linspace(1, 5, 31), method="lut")
    params = Parameters.from_fit(WL, result)
    sample = Sample(0.4, MapIdentity("test-map", 0.4, "sha256:0"))
    return Measurement(cal, [SampleCapture(sample, raw, refl)], params,
                       provenance=Provenance(method="lut", sample_name="test ink"))
