"""The seabreeze backend: optional (clear error without python-seabreeze), and its wrapper logic against a
stand-in for python-seabreeze's `Spectrometer` (the real one needs a USB device)."""

import importlib.util
import sys
import types

import numpy as np
import pytest

from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer import Spectrometer, open_spectrometer


@pytest.mark.skipif(importlib.util.find_spec("seabreeze") is not None, reason="python-seabreeze is installed")
def test_missing_seabreeze_is_a_clear_error():
    with pytest.raises(DeviceError, match=r"pip install 'trimeter\[seabreeze\]'"):
        open_spectrometer("seabreeze:")


class StandInSpectrometer:
    """The subset of seabreeze.spectrometers.Spectrometer the backend uses (python-seabreeze 2.x API)."""

    opened: list = []
    model, serial_number, max_intensity = "FLAME-S", "FLMS12345", 65535.0
    integration_time_micros_limits = (1000, 65_000_000)

    def __init__(self, serial):
        self.serial_number, self.set_calls, self.closed = serial, [], False
        self.f = types.SimpleNamespace(spectrometer=types.SimpleNamespace(
            get_electric_dark_pixel_indices=lambda: [2, 3, 4]))
        StandInSpectrometer.opened.append(self)

    @classmethod
    def from_first_available(cls):
        return cls("FLMS12345")

    @classmethod
    def from_serial_number(cls, serial):
        if serial != "FLMS12345":
            raise RuntimeError(f"No device attached with serial number '{serial}'.")
        return cls(serial)

    def wavelengths(self):
        return np.linspace(340, 1030, 2048)

    def intensities(self, correct_dark_counts=False, correct_nonlinearity=False):
        assert not correct_dark_counts and not correct_nonlinearity  # raw counts: trimeter corrects itself
        return np.full(2048, 1234.0)

    def integration_time_micros(self, us):
        self.set_calls.append(us)

    def close(self):
        self.closed = True


@pytest.fixture
def stand_in(monkeypatch):
    package = types.ModuleType("seabreeze")
    module = types.ModuleType("seabreeze.spectrometers")
    module.Spectrometer, module.list_devices = StandInSpectrometer, lambda: ["<FLAME-S:USB:FLMS12345>"]
    monkeypatch.setitem(sys.modules, "seabreeze", package)
    monkeypatch.setitem(sys.modules, "seabreeze.spectrometers", module)
    StandInSpectrometer.opened = []
    return StandInSpectrometer


def test_wrapper_reports_what_it_set_and_validates_limits(stand_in):
    with open_spectrometer("seabreeze:") as spec:
        assert isinstance(spec, Spectrometer)
        device = stand_in.opened[-1]
        spec.integration_time_us = 25_000
        assert spec.integration_time_us == 25_000 and device.set_calls[-1] == 25_000
        with pytest.raises(InputError, match="integration_time_us"):
            spec.integration_time_us = 10
        assert spec.integration_time_us == 25_000 and device.set_calls[-1] == 25_000
        d = spec.description
        assert (d.pixels, d.dark_pixels, d.saturation_counts, d.integration_time_us_limits) == (
            2048, (2, 3, 4), 65535.0, (1000, 65_000_000))
        assert spec.intensities().shape == (2048,)
    assert device.closed


def test_unknown_serial_lists_what_is_attached(stand_in):
    with pytest.raises(DeviceError, match="found: <FLAME-S:USB:FLMS12345>"):
        open_spectrometer("seabreeze:NOPE")
