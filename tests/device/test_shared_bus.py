"""Several instruments on one port (trimeter.device.bus): each request goes to its member's address under the
bus lock (never two on the wire at once), link counters stay per instrument, and the probe's reply counting tells
one answer from none and from a collision."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from fakes import FakeInstrument
from trimeter import registers as regs
from trimeter.crc import crc16_modbus_bytes
from trimeter.device import Device
from trimeter.device.bus import SharedBus, count_replies, probe_request
from trimeter.device.transport import LinkStats
from trimeter.errors import DeviceError


class FakeLine:
    """An RtuTransport's surface over one FakeInstrument per address; records overlapping requests."""

    def __init__(self, port: str, *, address: int, **options: object) -> None:
        self.address, self.stats, self._slow_reply_s = address, LinkStats(), 0.0
        self.instruments = {a: FakeInstrument() for a in (1, 2, 3)}
        self.in_flight = 0
        self.overlaps = 0
        self.log: list[tuple[int, float]] = []
        self.closed = False

    def _call(self, method: str, *args: object) -> object:
        self.in_flight += 1
        self.overlaps += self.in_flight > 1
        self.stats.requests += 1
        self.log.append((self.address, self._slow_reply_s))
        try:
            time.sleep(0.0005)  # a request takes time on the wire: another thread would get in here
            return getattr(self.instruments[self.address], method)(*args)
        finally:
            self.in_flight -= 1

    def read_bits(self, *args): return self._call("read_bits", *args)      # noqa: E704
    def read_words(self, *args): return self._call("read_words", *args)    # noqa: E704
    def write_bits(self, *args): return self._call("write_bits", *args)    # noqa: E704
    def write_words(self, *args): return self._call("write_words", *args)  # noqa: E704

    def reopen(self) -> None:
        self.stats.reconnects += 1

    def close(self) -> None:
        self.closed = True


def test_each_instrument_is_reached_at_its_address_with_its_own_counters_and_never_two_requests_at_once():
    bus = SharedBus("/dev/bus", transport=FakeLine)
    line = bus._rtu
    devices = {address: Device(bus.member(address)) for address in (1, 2, 3)}
    assert bus.member(2) is devices[2].transport  # one member per address

    def work(address: int) -> None:
        for i in range(20):
            devices[address].write("speed_mm_s", 10.0 + address + i / 100)

    with ThreadPoolExecutor(3) as pool:
        list(pool.map(work, (1, 2, 3)))
    assert line.overlaps == 0
    for address in (1, 2, 3):
        assert devices[address].read("speed_mm_s") == pytest.approx(10.0 + address + 0.19, rel=1e-6)
    requests = [devices[a].transport.stats.requests for a in (1, 2, 3)]
    assert all(r > 20 for r in requests) and sum(requests) == len(line.log)
    assert line.stats.requests == 0  # nothing counted against no one

    with devices[2].transport.slow_reply(1.5):  # a flash erase on one instrument lengthens only its own wait
        devices[2].read("uptime_s")
        devices[1].read("uptime_s")
    assert line.log[-2:] == [(2, 1.5), (1, 0.0)]
    devices[3].transport.reopen()
    assert devices[3].transport.stats.reconnects == 1 and devices[1].transport.stats.reconnects == 0
    devices[1].close()  # an instrument closing leaves the port open for the others
    assert not line.closed
    bus.close()
    assert line.closed


def test_a_member_address_outside_modbus_range_is_refused():
    bus = SharedBus("/dev/bus", transport=FakeLine)
    for address in (0, 248):
        with pytest.raises(DeviceError, match="outside 1..247"):
            bus.member(address)


def test_reply_counting_tells_one_answer_from_none_and_from_a_collision():
    reply = bytes([2, 0x04, 2]) + regs.VENDOR_ID.to_bytes(2, "big")
    frame = reply + crc16_modbus_bytes(reply)
    assert count_replies(b"", 2) == 0
    assert count_replies(frame, 2) == 1
    assert count_replies(frame + frame, 2) == 2       # two instruments at one address, replies whole
    assert count_replies(frame[:4] + frame, 2) == -1  # interleaved: collided bytes
    assert count_replies(bytes([3]) + frame[1:], 2) == -1  # another address answering
    assert probe_request(2)[:2] == bytes([2, 0x04])


def test_the_bus_lock_is_held_for_a_whole_request():
    bus = SharedBus("/dev/bus", transport=FakeLine)
    member = bus.member(1)
    started = threading.Event()

    def hold() -> None:
        with bus.lock:
            started.set()
            time.sleep(0.2)

    thread = threading.Thread(target=hold)
    thread.start()
    started.wait()
    t0 = time.monotonic()
    member.read_words("input_register", 0, 1)
    assert time.monotonic() - t0 > 0.1  # waited for its turn
    thread.join()
