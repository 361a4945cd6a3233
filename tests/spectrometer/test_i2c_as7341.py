"""The AS7341 driver against the fake chip: SMUX routing, integration time/gain registers, polling, errors."""

from __future__ import annotations

import numpy as np
import pytest

from fake_as7341 import FakeAS7341Bus, FakeClock
from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer import Spectrometer
from trimeter.spectrometer.i2c import AS7341, CHANNEL_NM

FLUX = {"F1": 1.0, "F2": 2.0, "F3": 3.0, "F4": 4.0, "F5": 5.0, "F6": 6.0, "F7": 7.0, "F8": 8.0,
        "Clear": 20.0, "NIR": 0.5}  # counts per ms at 1x gain


def make(flux=FLUX, **bus_options):
    clock = FakeClock()
    bus = FakeAS7341Bus(clock, flux, **bus_options)
    return AS7341(bus, gain=1, integration_time_us=50_000, clock=clock.now, sleep=clock.sleep), bus, clock


def test_every_channel_reads_its_own_photodiodes():
    sensor, bus, clock = make()
    assert isinstance(sensor, Spectrometer)
    counts = sensor.intensities()
    t_ms = sensor.integration_time_us / 1e3
    expected = np.array([FLUX[c] for c in ("F1", "F2", "F3", "F4", "F5", "F6", "F7", "F8", "NIR")]) * t_ms
    np.testing.assert_allclose(counts, expected, rtol=1e-3, atol=1)
    assert sensor.last_clear == pytest.approx(FLUX["Clear"] * t_ms, abs=1)
    np.testing.assert_array_equal(sensor.wavelengths_nm(), [415, 445, 480, 515, 555, 590, 630, 680, 910])
    assert bus.errors == []  # the SMUX was only switched with the measurement stopped, after SMUX_CMD=write
    assert clock.now() >= 2 * 0.05  # two full integrations were waited for


def test_integration_time_and_gain_round_trip_through_the_registers():
    sensor, bus, _ = make()
    for us in (1000, 50_000, 182_000, 1_000_000, 20_000_000):
        sensor.integration_time_us = us
        assert abs(sensor.integration_time_us - us) <= 2.78 * (bus.regs[0x81] + 1)
        assert abs(bus._t_int_s() * 1e6 - sensor.integration_time_us) < 1
    sensor.integration_time_us = 182_000
    assert bus.regs[0x81] == 0 and (bus.regs[0xCA] | bus.regs[0xCB] << 8) == round(182_000 / 2.78) - 1
    before = sensor.integration_time_us
    for bad in (0, 10**9, "slow"):
        with pytest.raises(InputError, match="integration_time_us"):
            sensor.integration_time_us = bad
    assert sensor.integration_time_us == before
    sensor.gain = 64
    assert bus.regs[0xAA] & 0x1F == 7 and sensor.gain == 64
    for bad in (3, 64.5, "lots", None):
        with pytest.raises(InputError, match="gain must be one of"):
            sensor.gain = bad
    sensor.gain = "0.5"  # as it comes from a URL query
    assert bus.regs[0xAA] & 0x1F == 0
    sensor.gain = 64
    assert sensor.gain == 64


def test_saturation_is_clipped_flagged_and_reported():
    sensor, bus, _ = make(flux={**FLUX, "F8": 1e6})
    sensor.integration_time_us = 1000  # (ATIME+1)(ASTEP+1) = 360 < 65535: the full scale is the step count
    assert sensor.saturation_counts == 360
    counts = sensor.intensities()
    assert counts[7] == 360 and sensor.last_saturated
    sensor.integration_time_us = 500_000
    assert sensor.saturation_counts == 65535


def test_a_wedged_chip_times_out_instead_of_hanging():
    sensor, bus, clock = make(stuck=True)
    with pytest.raises(DeviceError, match="AVALID"):
        sensor.intensities()
    assert clock.now() < 1.0  # gave up after ~2× the integration time


def test_wrong_chip_or_no_chip_is_a_clear_error():
    clock = FakeClock()
    with pytest.raises(DeviceError, match="not an AS7341"):
        AS7341(FakeAS7341Bus(clock, FLUX, chip_id=0x10), clock=clock.now, sleep=clock.sleep)
    with pytest.raises(DeviceError, match="0x3a.*failed"):
        AS7341(FakeAS7341Bus(clock, FLUX), address=0x3A, clock=clock.now, sleep=clock.sleep)


def test_close_powers_down_and_description_is_declarative():
    sensor, bus, _ = make()
    d = sensor.description
    assert d.model == "AS7341" and d.pixels == 9 and d.dark_pixels == ()
    sensor.close()
    assert bus.regs[0x80] == 0


def test_i2c_urls_are_checked_before_touching_a_bus():
    from trimeter.spectrometer import open_spectrometer

    with pytest.raises(InputError, match="i2c:<bus number>"):
        open_spectrometer("i2c:one")
    with pytest.raises(DeviceError, match="/dev/i2c-99"):
        open_spectrometer("i2c:99")  # no such adapter on this machine (nor on most)


def test_band_weights_built_in_or_measured(tmp_path):
    """The backend's band weights: the built-in model's, or a measured CSV's (channels in the chip's
    order whatever the file's); a bad file is one InputError, raised when the weights are asked for."""
    from trimeter.spectrometer.sensors import as7341_weights

    chip, _, _ = make()
    built_in = chip.band_weights()
    assert built_in.channels == tuple(CHANNEL_NM)
    np.testing.assert_allclose(built_in.diffuse, as7341_weights().diffuse)
    lam = np.arange(350.0, 1001.0, 2.0)
    names = list(CHANNEL_NM)[::-1]
    columns = {"wavelength_nm": lam}
    for name in names:
        bump = np.exp(-0.5 * ((lam - CHANNEL_NM[name]) / 12.0) ** 2)
        columns[f"{name}_diffuse"], columns[f"{name}_collimated"] = bump, 2 * bump
    path = tmp_path / "measured.csv"
    path.write_text(",".join(columns) + "\n" + "\n".join(",".join(f"{v[i]:.9g}" for v in columns.values())
                                                           for i in range(lam.size)) + "\n")
    clock = FakeClock()
    bus = FakeAS7341Bus(clock, FLUX)
    measured = AS7341(bus, gain=1, clock=clock.now, sleep=clock.sleep, weights=str(path)).band_weights()
    assert measured.channels == tuple(CHANNEL_NM)
    np.testing.assert_allclose(measured.centre_nm, list(CHANNEL_NM.values()), atol=0.5)
    path.write_text("wavelength_nm,F1_diffuse\n400,1\n")
    with pytest.raises(InputError, match="needs both <channel>_diffuse and <channel>_collimated"):
        AS7341(bus, gain=1, clock=clock.now, sleep=clock.sleep, weights=str(path)).band_weights()
