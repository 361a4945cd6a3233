"""Results directories to build materials from: a fake instrument's calibration and capture (tests/fakes),
with the fitted parameters chosen per test, written by the results writer as `trimeter measure` does."""

from __future__ import annotations

import numpy as np
from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from trimeter.device.client import Device
from trimeter.domain import MapIdentity, Measurement, Provenance, Sample, SampleCapture
from trimeter.domain.parameters import FitResult
from trimeter.results import Parameters
from trimeter.results.writer import write_measurement
from trimeter.sequences import Runner, calibration, reflectances, sample_capture

WL = np.linspace(420, 680, 27)


def capture(sample=None, wavelengths=WL):
    """(calibration, raw, reflectances) of the fake instrument with per-bin (I_b, I_w, I_c) `sample`."""
    n = len(wavelengths)
    fake = FakeInstrument(busy_polls=1)
    optics = FakeOptics(wavelengths, diffuse=np.full(n, 1e6), collimated=np.full(n, 2e6),
                        rho_black=np.full(n, 0.03), rho_white=0.99)
    runner = Runner(Device(fake), FakeSpectrometer(fake, optics), sleep=lambda s: None)
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    optics.sample = sample or (np.full(n, 0.2), np.full(n, 0.5), np.full(n, 0.1))
    raw = runner.run(sample_capture(hdr_decades=1))
    return cal, raw, reflectances(cal, raw)


def fit_result(alpha, sigma_t, g, std=(0.01, 0.1, 0.05), n=WL.size, flags=None) -> FitResult:
    full = [np.broadcast_to(np.asarray(v, float), (n,)).copy() for v in (alpha, sigma_t, g)]
    stds = [np.broadcast_to(np.asarray(s, float), (n,)).copy() for s in std]
    return FitResult(*full, *stds, flags=np.zeros(n, np.int64) if flags is None else flags,
                     sigma_t_beer=full[1].copy(), method="lut")


def write_member(root, result: FitResult, *, thickness=0.4, map_name="device-n1.5-l0.4", sample=None,
                 label="ink") -> str:
    cal, raw, refl = capture(sample)
    params = Parameters.from_fit(WL, result)
    identity = Sample(thickness, MapIdentity(map_name, thickness, "sha256:0"))
    m = Measurement(cal, [SampleCapture(identity, raw, refl)], params,
                    provenance=Provenance(method="lut", sample_name=label, label=label))
    return str(write_measurement(root, m, label=label, figure=False, medium=False))
