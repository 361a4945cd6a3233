"""The fault-injecting Modbus proxy, alone: a test plays the firmware on the other side of a pty."""

from __future__ import annotations

import os
import time
import tty

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.twin.faults import FaultConfig, ModbusProxy


class Rig:
    def __init__(self, faults: FaultConfig, seed=0):
        self.faults = faults
        self.requests = []
        self.dev_master, dev_slave = os.openpty()
        tty.setraw(dev_slave)
        self.proxy = ModbusProxy(os.ttyname(dev_slave), lambda: self.faults, np.random.default_rng(seed),
                                 on_request=self.requests.append)
        os.close(dev_slave)  # the proxy opened its own handle
        self.host = os.open(self.proxy.port, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.host)

    @staticmethod
    def read(fd, n, timeout=3.0):
        os.set_blocking(fd, False)
        data, deadline = b"", time.monotonic() + timeout
        while len(data) < n and time.monotonic() < deadline:
            try:
                data += os.read(fd, n - len(data))
            except BlockingIOError:
                time.sleep(0.001)
        return data

    def close(self):
        self.proxy.close()
        os.close(self.host)
        os.close(self.dev_master)


@pytest.fixture
def rig():
    rigs = []
    yield lambda faults, seed=0: rigs.append(Rig(faults, seed)) or rigs[-1]
    for r in rigs:
        r.close()


def test_corruption_rate_is_what_was_asked(rig):
    r = rig(FaultConfig(corrupt=0.05))
    sent = np.random.default_rng(9).integers(0, 256, 20_000, dtype=np.uint8).tobytes()
    received = b""
    for i in range(0, len(sent), 1000):  # in chunks the pty buffer takes whole
        os.write(r.host, sent[i:i + 1000])
        received += r.read(r.dev_master, 1000)
    assert len(received) == len(sent)
    diff = np.frombuffer(sent, np.uint8) ^ np.frombuffer(received, np.uint8)
    flipped = diff != 0
    rate = flipped.mean()
    assert abs(rate - 0.05) < 4 * np.sqrt(0.05 * 0.95 / len(sent)), rate
    assert np.all(np.unpackbits(diff[flipped][:, None], axis=1).sum(1) == 1)  # one bit per corrupted byte
    assert r.proxy.counters["bytes_corrupted"] == flipped.sum()


def test_clean_link_forwards_both_ways_unchanged(rig):
    r = rig(FaultConfig())
    os.write(r.host, b"\x01\x03\x00\x00\x00\x02\xc4\x0b")
    assert r.read(r.dev_master, 8) == b"\x01\x03\x00\x00\x00\x02\xc4\x0b"
    os.write(r.dev_master, b"\x01\x03\x04\x00\x01\x00\x02\x2a\x32")
    assert r.read(r.host, 9) == b"\x01\x03\x04\x00\x01\x00\x02\x2a\x32"
    assert r.requests == [1]


def _transactions(r, n, gap=0.006):
    """n request/reply exchanges; returns how many replies reached the host within 0.15 s each."""
    got = 0
    for i in range(n):
        os.write(r.host, bytes([1, 3, 0, i % 256]))
        assert len(r.read(r.dev_master, 4)) == 4  # the request always reaches the device
        os.write(r.dev_master, bytes([1, 3, 2, i % 256]))
        got += len(r.read(r.host, 4, timeout=0.15)) == 4
        time.sleep(gap)
    return got


def test_dropped_replies_at_the_configured_rate(rig):
    r = rig(FaultConfig(drop=0.3), seed=4)
    got = _transactions(r, 60)
    dropped = r.proxy.counters["replies_dropped"]
    assert got + dropped == 60 and r.proxy.counters["requests"] == 60
    assert 8 <= dropped <= 30  # 18 expected; binomial 4σ ≈ ±14


def test_late_replies_arrive_after_the_delay(rig):
    r = rig(FaultConfig(late=1.0, late_delay_s=0.3))
    os.write(r.host, b"\x01\x03\x00\x07")
    r.read(r.dev_master, 4)
    t0 = time.monotonic()
    os.write(r.dev_master, b"\x01\x03\x02\x07")
    assert r.read(r.host, 4, timeout=0.2) == b""
    assert r.read(r.host, 4, timeout=1.0) == b"\x01\x03\x02\x07"
    assert 0.25 < time.monotonic() - t0 < 0.6


def test_reset_at_fires_on_the_nth_request_and_faults_can_change_live(rig):
    r = rig(FaultConfig(reset_at=3))
    _transactions(r, 4)
    assert r.requests == [1, 2, 3, 4]
    r.faults = r.faults.replace(drop=1.0)
    assert _transactions(r, 3) == 0


def test_fault_config_parsing_and_validation():
    f = FaultConfig.parse("corrupt=0.01,drop=0.02,late=0.01,reset_at=40,stuck_slider,lamp_failure")
    assert (f.corrupt, f.drop, f.late, f.reset_at, f.stuck_slider, f.lamp_failure) == \
        (0.01, 0.02, 0.01, 40, True, "panels")
    assert FaultConfig.parse("lamp_failure=collimated").lamp_failure == "collimated"
    assert FaultConfig.parse("") == FaultConfig()
    for bad, field in (("corrupt=2", "corrupt"), ("drop=x", "drop"), ("reset_at=0", "reset_at"),
                       ("lamp_failure=sun", "lamp_failure"), ("gremlins=1", "gremlins")):
        with pytest.raises(InputError, match=field):
            FaultConfig.parse(bad)


def test_a_request_right_after_a_reply_counts_as_new(rig):
    r = rig(FaultConfig())
    for i in range(5):  # no pause between a reply and the next request
        os.write(r.host, bytes([1, 4, 0, i]))
        assert len(r.read(r.dev_master, 4)) == 4
        os.write(r.dev_master, bytes([1, 4, 2, i]))
        assert len(r.read(r.host, 4)) == 4
    assert r.requests == [1, 2, 3, 4, 5]
