"""Plans driven by fakes (tests/fakes.py): the optics are set to known I_b, I_w, I_c and ρ_black, so
the paper's calibration + ratio maths must give them back exactly (noise-free), across four decades of
I_c (HDR), with bad bins flagged instead of raising, and a reset or a dead lamp reported clearly."""

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from trimeter.device.client import Device
from trimeter.errors import DeviceError
from trimeter.domain import CaptureFlag
from trimeter.sequences import Runner, calibration, reflectances, sample_capture, warm_up
from trimeter.sequences.plans import dark_frames
from trimeter.sequences.steps import Acquire, Expose, Lights, Move

N = 64
WL = np.linspace(400, 700, N)


def rig(noise=0.0, **optics):
    fake = FakeInstrument(busy_polls=1)
    defaults = dict(diffuse=2e6 * (1 + 0.5 * np.sin(WL / 40)), collimated=5e6 * np.exp(-((WL - 550) / 120) ** 2),
                    rho_black=0.02 + 0.1 * (WL > 650), rho_white=0.99)
    defaults.update(optics)
    opt = FakeOptics(WL, **defaults)
    spec = FakeSpectrometer(fake, opt, noise=noise)
    return fake, opt, spec, Runner(Device(fake), spec, sleep=lambda s: None)


def known_sample():
    i_b = 0.05 + 0.3 * (WL - 400) / 300
    i_w = i_b + 0.4
    i_c = 10 ** np.linspace(-4.5, -0.3, N)  # four decades: needs the HDR exposures
    return i_b, i_w, i_c


def test_calibration_and_capture_recover_known_reflectances_exactly():
    fake, opt, spec, runner = rig()
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    np.testing.assert_allclose(cal.rho_black, opt.rho_black, rtol=1e-9)
    np.testing.assert_allclose(cal.diffuse, opt.diffuse, rtol=1e-9)
    np.testing.assert_allclose(cal.collimated, opt.collimated, rtol=1e-9)
    opt.sample = known_sample()
    refl = reflectances(cal, runner.run(sample_capture(hdr_decades=3)))
    for got, want in zip((refl.I_b, refl.I_w, refl.I_c), opt.sample, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9)
    assert (refl.flags == 0).all() and (refl.rho_w == 0.99).all()


def test_hdr_is_what_resolves_the_dim_collimated_bins():
    errors = {}
    for decades in (0, 3):
        fake, opt, spec, runner = rig(noise=2.0)
        spec.quantize = True  # a 16-bit ADC with read noise
        cal = runner.run(calibration(white_reference_reflectance=0.99))
        opt.sample = known_sample()
        raw = runner.run(sample_capture(hdr_decades=decades))
        assert len(raw.collimated.integration_times_us) == decades + 1
        refl = reflectances(cal, raw)
        dim = opt.sample[2] < 1e-3
        errors[decades] = np.nanmax(np.abs(refl.I_c[dim] / opt.sample[2][dim] - 1))
    assert errors[3] < 0.02 < errors[0], errors


def test_saturated_and_nan_bins_are_flagged_not_fatal():
    fake, opt, spec, runner = rig()
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    opt.sample = known_sample()
    real = spec.intensities

    def broken():
        counts = real()
        counts[5] = np.nan
        counts[9] = spec.saturation_counts  # a hot pixel: saturated in every frame
        return counts

    spec.intensities = broken
    refl = reflectances(cal, runner.run(sample_capture()))
    assert refl.flags[5] & CaptureFlag.NONFINITE and refl.flags[9] & CaptureFlag.SATURATED
    assert np.isnan(refl.I_b[[5, 9]]).all()
    ok = np.setdiff1d(np.arange(N), [5, 9])
    np.testing.assert_allclose(refl.I_w[ok], opt.sample[1][ok], rtol=1e-9)


def test_plan_yields_the_three_references_in_order_without_hardware():
    steps = []
    plan = calibration(white_reference_reflectance=0.99)
    fake, opt, spec, runner = rig()
    reply = None
    try:
        while True:
            step = plan.send(reply)
            steps.append(step)
            reply = runner.execute(step)
    except StopIteration:
        pass
    moves = [s.slot for s in steps if isinstance(s, Move)]
    assert moves == ["white", "black", "open"]
    lights = [(s.panels, s.collimated) for s in steps if isinstance(s, Lights)]
    assert lights == [(True, False), (True, False), (False, True), (False, False)]  # last: dark frames
    assert sum(isinstance(s, Acquire) for s in steps) >= 6


def test_reset_mid_sequence_is_a_clear_error():
    fake, opt, spec, runner = rig()
    runner.run(calibration(white_reference_reflectance=0.99))
    opt.sample = known_sample()
    count = {"n": 0}

    def reset_once(device):
        count["n"] += 1
        if count["n"] == 40:
            device.reset()

    fake.on_request = reset_once
    with pytest.raises(DeviceError, match="reset during the sequence|lost its homing|lost its light"):
        runner.run(sample_capture())


def test_dead_lamp_is_reported_not_measured():
    fake, opt, spec, runner = rig(diffuse=np.zeros(N))
    with pytest.raises(DeviceError, match="no light from the diffuse LED panels"):
        runner.run(calibration(white_reference_reflectance=0.99))


def test_warm_up_stops_when_drift_is_under_threshold_not_after_a_fixed_time():
    fake, opt, spec, runner = rig()
    opt.brightness = lambda t: 1 - 0.04 * (1 - np.exp(-t / 90))
    result = runner.run(warm_up(threshold=0.002, interval_s=10))
    # relative change per 10 s ≈ 0.04·(1−e^(−10/90))·e^(−t/90) < 0.002 from t ≈ 70 s on
    assert 55 <= result.elapsed_s <= 100 and result.drift < 0.002
    fake2, opt2, spec2, runner2 = rig()
    opt2.brightness = lambda t: 1 - 0.5 * t / 1000  # never settles
    with pytest.raises(DeviceError, match="did not stabilise within 60 s"):
        runner2.run(warm_up(threshold=0.002, interval_s=10, timeout_s=60))


def test_a_warm_up_whose_first_spectrum_came_after_its_limit_still_judges_the_drift():
    # a link slow enough (retries on a noisy line) that the limit passed by the first spectrum: one spectrum
    # says nothing of the lamps, so a second is taken and the drift judged, never reported as infinite
    fake, opt, spec, runner = rig()
    result = runner.run(warm_up(threshold=0.002, interval_s=10, timeout_s=1e-6))
    assert result.spectra == 2 and result.drift < 0.002
    fake2, opt2, spec2, runner2 = rig()
    opt2.brightness = lambda t: 1 - 0.5 * t / 1000
    with pytest.raises(DeviceError, match=r"did not stabilise within 1e-06 s \(drift 0\.\d+%"):
        runner2.run(warm_up(threshold=0.002, interval_s=10, timeout_s=1e-6))


def test_a_dark_at_another_integration_time_than_its_signal_is_an_error():
    """Darks are taken at the times the spectrometer granted the signals; if it then sets another
    time for a dark, subtracting it would pair the wrong exposures: a clear error instead."""
    plan = dark_frames([1000.0, 20000.0])
    assert isinstance(next(plan), Lights)
    step = plan.send(None)
    assert isinstance(step, Expose) and step.integration_time_us == 1000.0
    assert isinstance(plan.send(1000.0), Acquire)  # granted as asked: on to its frames
    step = plan.send((np.zeros(N), np.zeros(N)))
    assert isinstance(step, Expose) and step.integration_time_us == 20000.0
    with pytest.raises(DeviceError, match="darks would not match the signals"):
        plan.send(20480.0)
