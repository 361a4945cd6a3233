"""The mcu: backend on the twin's firmware: the C12880MA captured by the firmware (frames averaged on the
device), its wavelengths from the device's polynomial, dark with the shutters closed, saturation flagged,
refusals; and the sim chip's own model (slit, noise, timing)."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter import registers as regs
from trimeter.device.transport import ModbusExceptionReply
from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer import open_spectrometer
from trimeter.spectrometer.mcu import ADC_FULL_SCALE, McuSpectrometer
from trimeter.spectrometer.sensors import c12880_coefficients, c12880_wavelengths_nm
from trimeter.twin import Twin


@pytest.fixture(scope="module")
def twin():
    with Twin(sensor="c12880ma", seed=3, time_scale=5.0) as t:
        yield t


@pytest.fixture(scope="module")
def spec(twin):
    s = open_spectrometer(twin.spectrometer_url, frames=2)
    d = s.device
    d.command("home")
    d.wait_idle(60)
    yield s
    s.close()


def _at(spec, slot: str, panels: bool, collimated: bool) -> None:
    d = spec.device
    d.goto(slot)
    d.set_lights(panels=panels, collimated=collimated)
    d.wait_idle(20)


def test_description_and_wavelengths_from_the_device(twin, spec):
    assert twin.spectrometer_url.startswith("mcu:")
    desc = spec.description
    assert desc.model == "C12880MA" and desc.pixels == 288 and desc.saturation_counts == ADC_FULL_SCALE
    lam = spec.wavelengths_nm()
    np.testing.assert_allclose(lam, c12880_wavelengths_nm(c12880_coefficients()), rtol=1e-6)
    assert 300 < lam[0] < 340 and 850 < lam[-1] < 900 and np.all(np.diff(lam) > 0)
    # 54 CLK periods at the sim's 500 kHz CLK: the chip's shortest integration
    assert desc.integration_time_us_limits == (108, 1_000_000)


def test_capture_follows_the_light_and_the_integration_time(spec):
    _at(spec, "white", panels=True, collimated=False)
    spec.integration_time_us = 2000
    short = spec.intensities()
    spec.integration_time_us = 4000
    assert spec.integration_time_us == 4000
    long = spec.intensities()
    dark = spec.dark()  # the firmware closes every shutter first
    assert spec.device.read("spectro_dark_valid") == 1
    lit = (short - dark) > 200
    assert lit.sum() > 100
    np.testing.assert_allclose((long - dark)[lit] / (short - dark)[lit], 2.0, rtol=0.1)
    # the datasheet's video offset (0.5 V) through the sim front end (4.8 V over 4200 counts), read noise +
    # dark current
    assert abs(np.median(dark) - 0.5 / (4.8 / 4200)) < 10 and dark.std() < 5
    # the panels' blue pump at 450 nm seen through the 12 nm slit: a peak near it
    lam = spec.wavelengths_nm()
    blue = (lam > 420) & (lam < 480)
    assert 440 < lam[blue][np.argmax((long - dark)[blue])] < 462


def test_saturation_is_flagged_and_reported_at_full_scale(spec):
    _at(spec, "open", panels=False, collimated=True)
    spec.integration_time_us = 50_000
    counts = spec.intensities()
    assert spec.device.read("spectro_status") == regs.SpectroStatus.SATURATED
    assert counts.max() == ADC_FULL_SCALE
    spec.integration_time_us = spec.integration_time_us_limits[0]
    assert spec.intensities().max() < 0.9 * ADC_FULL_SCALE
    assert spec.device.read("spectro_status") == regs.SpectroStatus.DONE


def test_refusals(twin, spec):
    with pytest.raises(InputError, match="integration_time_us"):
        spec.integration_time_us = 50  # below 54 CLK periods
    with pytest.raises(InputError):
        spec.device.write("spectro_integration_us", 5)  # below the register's range: exception 03
    with pytest.raises(InputError):  # a polynomial that turns back: exception 03, nothing changed
        spec.device.write("spectro_wl_b2", -0.02)
    assert spec.device.read("spectro_wl_b2") == pytest.approx(c12880_coefficients()[2], rel=1e-6)
    with pytest.raises(InputError, match="frames"):
        open_spectrometer(twin.spectrometer_url, frames=0)
    with pytest.raises(InputError, match="gain"):
        open_spectrometer(twin.spectrometer_url, gain=3)
    with pytest.raises(ModbusExceptionReply):  # the spectra are read-only files
        spec.device.transport.write_file_records(int(regs.SpectroFile.LIGHT), 0, b"\x00\x01")


def test_missing_eos_is_a_device_error(twin, spec):
    twin.plant.request(cmd="spectro", eos_broken=True)
    try:
        with pytest.raises(DeviceError, match="EOS"):
            spec.intensities()
        assert spec.device.read("spectro_status") == regs.SpectroStatus.ERROR_NO_EOS
    finally:
        twin.plant.request(cmd="spectro", eos_broken=False)
    assert spec.intensities().shape == (288,)


def test_the_units_polynomial_is_what_the_host_uses(twin, spec):
    """A unit whose sheet differs: stored on the device, a new connection reads it."""
    spec.device.write("spectro_wl_a0", 300.0)
    try:
        other = McuSpectrometer("", device=spec.device)
        assert other.wavelengths_nm()[0] == pytest.approx(300.0 + (spec.wavelengths_nm()[0] - 305.54), abs=1e-3)
    finally:
        spec.device.write("spectro_wl_a0", c12880_coefficients()[0])


def test_chip_requests_are_checked(twin):
    with pytest.raises(DeviceError, match="increase"):
        twin.plant.request(cmd="spectro", b1=-3.0)
    with pytest.raises(DeviceError, match="values"):
        twin.plant.request(cmd="spectro_light", component="beam_open", start_nm=300, step_nm=5, values=[1, -2, 3])
    with pytest.raises(DeviceError, match="component"):
        twin.plant.request(cmd="spectro_light", component="sky", start_nm=300, step_nm=5, values=[1, 2])
