"""The fault-injecting Modbus proxy, alone: a test plays the firmware on the other side of a pty; and the
seeded fates it draws (Fates), driven directly."""

from __future__ import annotations

import os
import time
import tty

import numpy as np
import pytest

from trimeter.crc import crc16_modbus_bytes
from trimeter.errors import InputError
from trimeter.twin.faults import MAX_FRAME, FaultConfig, Fates, ModbusProxy, request_length


class Rig:
    def __init__(self, faults: FaultConfig, seed=0):
        self.faults = faults
        self.requests = []
        self.dev_master, dev_slave = os.openpty()
        tty.setraw(dev_slave)
        self.proxy = ModbusProxy(os.ttyname(dev_slave), lambda: self.faults, seed, on_request=self.requests.append)
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


def _frame(*body: int) -> bytes:
    return bytes(body) + crc16_modbus_bytes(bytes(body))


def _transactions(r, n, gap=0.006):
    """n request/reply exchanges; returns how many replies reached the host within 0.15 s each."""
    got = 0
    for i in range(n):
        os.write(r.host, _frame(1, 3, 0, i % 256, 0, 1))
        assert len(r.read(r.dev_master, 8)) == 8  # the request always reaches the device
        os.write(r.dev_master, _frame(1, 3, 2, 0, i % 256))
        got += len(r.read(r.host, 7, timeout=0.15)) == 7
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
        os.write(r.host, _frame(1, 4, 0, i, 0, 1))
        assert len(r.read(r.dev_master, 8)) == 8
        os.write(r.dev_master, _frame(1, 4, 2, 0, i))
        assert len(r.read(r.host, 7)) == 7
    assert r.requests == [1, 2, 3, 4, 5]


def test_frames_written_together_are_separate_requests_and_a_stray_burst_ends_with_silence(rig):
    r = rig(FaultConfig())
    frames = _frame(1, 3, 0, 1, 0, 1) + _frame(1, 16, 0, 2, 0, 1, 2, 0, 7) + _frame(1, 4, 0, 3, 0, 2)
    os.write(r.host, frames)
    assert r.read(r.dev_master, len(frames)) == frames
    assert r.requests == [1, 2, 3]
    os.write(r.host, b"\x01\xee\x05")  # no function code a master sends: forwarded after the gap, as one request
    assert r.read(r.dev_master, 3) == b"\x01\xee\x05"
    assert r.requests == [1, 2, 3, 4]


def test_request_length_from_the_header():
    assert request_length(b"\x01") is None
    assert request_length(_frame(1, 3, 0, 0, 0, 2)) == 8
    assert request_length(bytes([1, 16, 0, 0, 0, 2])) is None  # its byte count not yet in
    assert request_length(_frame(1, 16, 0, 0, 0, 2, 4, 0, 1, 0, 2)) == 13
    assert request_length(_frame(1, 20, 7, 6, 0, 1, 0, 0, 0, 4)) == 12
    assert request_length(bytes([1, 23, 0, 0, 0, 1, 0, 0, 0, 1, 2])) == 15
    assert request_length(_frame(1, 0x2B, 0x0E, 1, 0)) == 7
    assert request_length(bytes([1, 16, 0, 0, 0, 0, 255])) == MAX_FRAME
    assert request_length(b"\x01\x99\x00") is None


# --- the seeded fates, driven directly -------------------------------------------------------------------

POLL = _frame(1, 4, 0, 9, 0, 1)
SCRIPT = [_frame(1, 3, 0, i % 7, 0, 2) for i in range(200)] + [_frame(1, 6, 0, 1, 0, i) for i in range(100)]


def _fates_of_the_script(seed: int, polls: list[int], faults: FaultConfig) -> list:
    """Each scripted request's fate (reply, its own flips, its reply's flips), with polls[i] status polls
    drawn before the i-th request (their fates are drawn too, so they would shift an unkeyed stream)."""
    fates, seen = Fates(seed), []
    for request, n_polls in zip(SCRIPT, polls, strict=True):
        for _ in range(n_polls):
            poll = fates.draw(POLL, faults)
            poll.flips(len(POLL), faults.corrupt), poll.flips(7, faults.corrupt)
        fate = fates.draw(request, faults)
        seen.append((fate.reply, fate.flips(len(request), faults.corrupt).tobytes(),
                     fate.flips(9, faults.corrupt).tobytes()))
    return seen


def test_a_request_meets_the_same_fate_whatever_polls_came_between():
    faults = FaultConfig(corrupt=0.05, drop=0.1, late=0.05)
    polls = np.random.default_rng(1).integers(0, 4, len(SCRIPT)).tolist()
    quiet = _fates_of_the_script(5, [0] * len(SCRIPT), faults)
    busy = _fates_of_the_script(5, polls, faults)
    assert busy == quiet
    # not trivially so: fates vary, repeated requests meet different fates, another seed others
    assert {reply for reply, _, _ in quiet} == {"forward", "drop", "late"}
    assert len({fate for fate, request in zip(quiet, SCRIPT, strict=True) if request == SCRIPT[0]}) > 1
    assert _fates_of_the_script(6, [0] * len(SCRIPT), faults) != quiet


def test_flips_do_not_depend_on_how_the_bytes_were_read():
    one, two = Fates(3).draw(POLL, FaultConfig()), Fates(3).draw(POLL, FaultConfig())
    whole = one.flips(600, 0.3)
    pieces = np.concatenate([two.flips(n, 0.3) for n in (1, 7, 300, 292)])
    assert np.array_equal(whole, pieces) and whole.any()
    three = Fates(3).draw(POLL, FaultConfig())
    assert not three.flips(100, 0.0).any()  # a clean stretch keeps its place in the stream
    assert np.array_equal(three.flips(500, 0.3), whole[100:])


def test_fates_honour_the_probabilities():
    fates, faults = Fates(11), FaultConfig(corrupt=0.1, drop=0.1, late=0.1)
    drawn = [fates.draw(POLL, faults) for _ in range(10_000)]  # one request 10,000 times: each its own draw
    replies = [fate.reply for fate in drawn]
    assert 0.07 < replies.count("drop") / len(drawn) < 0.13
    assert 0.07 < replies.count("late") / len(drawn) < 0.13
    flips = np.concatenate([fate.flips(8, faults.corrupt) for fate in drawn[:2000]])
    assert 0.07 < np.count_nonzero(flips) / len(flips) < 0.13
    corrupted = flips[flips != 0]
    assert np.all(np.unpackbits(corrupted[:, None], axis=1).sum(1) == 1)  # one bit per corrupted byte
    assert set(corrupted.tolist()) == {1 << bit for bit in range(8)}


def test_a_bad_seed_is_refused():
    for bad in (-1, 1.5, "7", True, None):
        with pytest.raises(InputError, match="seed"):
            Fates(bad)


# --- end to end through the pty proxy ----------------------------------------------------------------------

def _scripted_client(r, polls: list[int]) -> list:
    """The script's first 40 requests with polls[i] status polls before the i-th (the test plays the device):
    what the device received and what reached the host for each scripted request."""
    seen = []
    for request, n_polls in zip(SCRIPT[:40], polls, strict=True):
        for _ in range(n_polls):
            os.write(r.host, POLL)
            r.read(r.dev_master, len(POLL))
            os.write(r.dev_master, _frame(1, 4, 2, 0, 0))
            r.read(r.host, 7, timeout=0.05)
            time.sleep(0.004 * n_polls)  # a different pace as well
        os.write(r.host, request)
        received = r.read(r.dev_master, len(request))
        os.write(r.dev_master, _frame(1, 3, 4, 0, request[3], 0, 1))
        seen.append((received, r.read(r.host, 9, timeout=0.05)))
    return seen


def test_two_runs_with_one_seed_see_the_same_faults_through_the_proxy(rig):
    faults = FaultConfig(corrupt=0.03, drop=0.15)
    quiet = _scripted_client(rig(faults, seed=21), [0] * 40)
    busy = _scripted_client(rig(faults, seed=21), np.random.default_rng(2).integers(0, 3, 40).tolist())
    assert busy == quiet
    assert any(received != request for (received, _), request in zip(quiet, SCRIPT, strict=False))  # corrupted
    assert any(reply == b"" for _, reply in quiet)  # dropped
    assert _scripted_client(rig(faults, seed=22), [0] * 40) != quiet
