"""The sim backend against the twin's spectrometer server, over a real pty, with an injected light source."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer import Spectrometer, open_spectrometer
from trimeter.twin.optics import SpectrometerModel
from trimeter.twin.specserver import SpectrometerServer


@pytest.fixture
def server():
    model = SpectrometerModel()
    rng = np.random.default_rng(0)
    calls = []

    def expose(it_us):
        calls.append(it_us)
        counts = rng.integers(0, 65536, len(model.wavelengths_nm), dtype=np.uint16)
        server.last_counts = counts
        return counts, 12.5 + len(calls)

    server = SpectrometerServer(model.description(), model.wavelengths_nm, expose)
    server.model, server.calls = model, calls
    yield server
    server.close()


def test_round_trip_description_wavelengths_integration_time_and_counts(server):
    with open_spectrometer(f"sim:{server.port}") as spec:
        assert isinstance(spec, Spectrometer)
        d = spec.description
        assert d.pixels == 1024 and d.dark_pixels == tuple(range(8)) and d.saturation_counts == 65535
        np.testing.assert_allclose(spec.wavelengths_nm(), server.model.wavelengths_nm, atol=1e-4)
        spec.integration_time_us = 2500
        assert spec.integration_time_us == 2500 == server.integration_time_us
        counts = spec.intensities()
        assert counts.dtype == np.float64
        np.testing.assert_array_equal(counts, server.last_counts)  # exact: every uint16 value survives
        assert server.calls == [2500]
        assert spec.sim_time_s() == pytest.approx(13.5)


def test_integration_time_outside_the_limits_is_refused_and_unchanged(server):
    with open_spectrometer(f"sim:{server.port}") as spec:
        lo, hi = spec.integration_time_us_limits
        before = spec.integration_time_us
        for bad in (lo - 1, hi + 1, float("nan"), "fast"):
            with pytest.raises(InputError, match="integration_time_us"):
                spec.integration_time_us = bad
        assert spec.integration_time_us == before == server.integration_time_us


def test_server_answers_garbage_with_err_and_keeps_serving(server):
    assert server.handle("IT 5") .startswith("ERR")  # below the minimum, even without the client's check
    assert server.handle("IT -3").startswith("ERR")
    assert server.handle("FLY").startswith("ERR")
    assert server.handle("").startswith("ERR")
    fd = os.open(server.port, os.O_RDWR | os.O_NOCTTY)
    try:
        os.write(fd, b"\xff\x00garbage\n" + b"x" * 600 + b"\n*IDN?\n")
        deadline, data = time.monotonic() + 3, b""
        os.set_blocking(fd, False)
        while data.count(b"\n") < 3 and time.monotonic() < deadline:
            try:
                data += os.read(fd, 4096)
            except BlockingIOError:
                time.sleep(0.005)
    finally:
        os.close(fd)
    lines = data.split(b"\n")
    assert lines[0].startswith(b"ERR") and lines[1] == b"ERR line too long"
    assert lines[2].startswith(b"OK trimeter-twin-spectrometer")


def test_a_failing_light_source_is_reported_on_the_wire(server):
    def broken(it_us):
        raise RuntimeError("plant gone")

    server._expose = broken
    with open_spectrometer(f"sim:{server.port}") as spec:
        with pytest.raises(DeviceError, match="plant gone"):
            spec.intensities()
        assert spec.integration_time_us > 0  # still answering afterwards


def test_urls_choose_the_backend_and_bad_ones_are_refused():
    with pytest.raises(InputError, match="backend must be one of"):
        open_spectrometer("usb:3")
    with pytest.raises(InputError, match="<backend>:<address>"):
        open_spectrometer("sim")
    with pytest.raises(DeviceError, match="cannot open sim spectrometer"):
        open_spectrometer("sim:/dev/does-not-exist")
    with pytest.raises(InputError, match="option 'speed' is not one of sim's: timeout_s"):
        open_spectrometer("sim:/dev/pts/0?speed=3")
    with pytest.raises(InputError, match="must be key=value"):
        open_spectrometer("sim:/dev/pts/0?timeout_s")


def test_a_late_reply_is_not_taken_for_the_next_answer(server):
    import threading

    release = threading.Event()
    slow_counts = np.full(1024, 7, dtype=np.uint16)

    def slow(it_us):
        release.wait(5)
        return slow_counts, 1.0

    with open_spectrometer(f"sim:{server.port}?timeout_s=0.2") as spec:
        server._expose = slow
        with pytest.raises(DeviceError, match="no reply to 'ACQ'"):
            spec.intensities()
        release.set()  # the ACQ reply now arrives, late
        spec.integration_time_us = 3000  # its own replies, not the stale ACQ payload
        assert spec.integration_time_us == 3000
        server._expose = lambda it_us: (np.full(1024, 9, dtype=np.uint16), 2.0)
        np.testing.assert_array_equal(spec.intensities(), 9)


def test_a_port_closed_by_another_thread_mid_command_is_a_device_error(server):
    """The press-button service's thread can be mid-capture when the rig (or a shutdown) closes the instrument:
    pyserial then fails with a TypeError on the closed descriptor, which must reach the service as the
    DeviceError it handles, not kill its thread."""
    import threading

    release = threading.Event()
    server._expose = lambda it_us: (release.wait(5), (np.zeros(1024, dtype=np.uint16), 1.0))[1]
    spec = open_spectrometer(f"sim:{server.port}?timeout_s=3")
    closer = threading.Timer(0.3, spec.close)
    closer.start()
    try:
        with pytest.raises(DeviceError, match="the port failed during 'ACQ'"):
            spec.intensities()
    finally:
        release.set()
        closer.join()


@pytest.mark.parametrize("field, value", [("wavelength_range_nm", [340.0, 500.0, 850.0]),
                                          ("integration_time_us_limits", [10]),
                                          ("integration_time_us_limits", 10)])
def test_a_description_whose_limits_are_not_pairs_is_refused(field, value):
    model = SpectrometerModel()
    description = {**model.description(), field: value}
    server = SpectrometerServer(description, model.wavelengths_nm, lambda it_us: (np.zeros(1024, np.uint16), 0.0))
    try:
        with pytest.raises(DeviceError, match="bad DESC"):
            open_spectrometer(f"sim:{server.port}")
    finally:
        server.close()


def test_a_port_in_use_is_refused_as_the_instrument_port_is(server):
    with open_spectrometer(f"sim:{server.port}"):
        with pytest.raises(DeviceError, match="in use by another program"):
            open_spectrometer(f"sim:{server.port}")
    with open_spectrometer(f"sim:{server.port}") as again:   # free again once the first has closed it
        assert again.description.pixels == 1024
