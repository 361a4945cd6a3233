"""Several instruments on one serial port (an RS-485 bus, each at its own Modbus address).

One `SharedBus` per port holds the one open port (an RtuTransport) and the bus lock; each instrument talks
through a `BusMember`, a Transport for its address. The lock is held for one whole request — its retries and
its drain after a failure included — so two requests never overlap on the wire and a late or garbled reply is
drained before another instrument is asked anything; between requests the instruments take turns, so their
jobs run side by side (what takes a measurement its time is exposures and settling, not the bus).
Each member keeps its own link counters, so a noisy branch shows against its own instrument only.

`probe_address` tells whether exactly one device answers at an address: two instruments configured alike
both answer (their replies collide on a real bus; on the twin's bus both arrive whole), which no retry
fixes — the host refuses that bus with one error instead of reading one instrument's replies as another's.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any, Callable

from trimeter import registers as regs
from trimeter.crc import crc16_modbus, crc16_modbus_bytes
from trimeter.device.transport import LinkStats, RtuTransport, record_words
from trimeter.errors import DeviceError

# The register every instrument answers with the same shape (the identity's first word).
_PROBE_REGISTER = regs.BY_NAME["vendor_id"]
PROBE_ROUNDS = 3  # a collision shows every round; a line error seldom twice in a row


class SharedBus:
    """One serial port and its lock, shared by the instruments on it (see the module docstring)."""

    def __init__(self, port: str, *, baudrate: int = 19200, timeout_s: float = 0.15, attempts: int = 6,
                 reconnect_timeout_s: float = 10.0, local_echo: bool = False,
                 transport: Callable[..., Any] = RtuTransport) -> None:
        self.port = port
        self.lock = threading.RLock()
        self._rtu = transport(port, address=1, baudrate=baudrate, timeout_s=timeout_s, attempts=attempts,
                              reconnect_timeout_s=reconnect_timeout_s, local_echo=local_echo)
        self._idle_stats = self._rtu.stats
        self.members: dict[int, BusMember] = {}

    def member(self, address: int) -> BusMember:
        """The Transport for the instrument at `address` (one per address: a second ask gets the same)."""
        if not 1 <= address <= 247:
            raise DeviceError(f"Modbus address {address} is outside 1..247")
        with self.lock:
            if address not in self.members:
                self.members[address] = BusMember(self, address)
            return self.members[address]

    @contextlib.contextmanager
    def turn(self, member: BusMember) -> Iterator[Any]:
        """The port, addressed to `member`, for one request (the bus lock held)."""
        asked = time.monotonic()
        with self.lock:
            member.stats.bus_wait_s += time.monotonic() - asked
            rtu = self._rtu
            rtu.address, rtu.stats = member.address, member.stats
            saved = rtu._slow_reply_s
            rtu._slow_reply_s = member.slow_reply_s
            try:
                yield rtu
            finally:
                rtu._slow_reply_s = saved
                rtu.stats = self._idle_stats

    def close(self) -> None:
        with self.lock:
            self._rtu.close()


class BusMember:
    """A Transport (trimeter.device.transport.Transport) for one address of a SharedBus."""

    def __init__(self, bus: SharedBus, address: int) -> None:
        self.bus, self.address = bus, address
        self.port = bus.port
        self.stats = LinkStats()
        self.slow_reply_s = 0.0

    @contextlib.contextmanager
    def slow_reply(self, seconds: float) -> Iterator[None]:
        saved, self.slow_reply_s = self.slow_reply_s, seconds
        try:
            yield
        finally:
            self.slow_reply_s = saved

    def reopen(self) -> None:
        """Reopen the bus's port (every instrument on it shares it); counted against this instrument."""
        with self.bus.turn(self) as rtu:
            rtu.reopen()

    def read_bits(self, table: str, address: int, count: int) -> list[bool]:
        with self.bus.turn(self) as rtu:
            return rtu.read_bits(table, address, count)

    def read_words(self, table: str, address: int, count: int) -> list[int]:
        with self.bus.turn(self) as rtu:
            return rtu.read_words(table, address, count)

    def write_bits(self, address: int, values: list[bool]) -> None:
        with self.bus.turn(self) as rtu:
            rtu.write_bits(address, values)

    def write_words(self, address: int, values: list[int]) -> None:
        with self.bus.turn(self) as rtu:
            rtu.write_words(address, values)

    @property
    def record_words(self) -> int:
        """The bus's file-record size now: one wire, one line quality for every instrument on it."""
        return record_words(self.bus._rtu)

    def read_file_records(self, file_number: int, record_number: int, count: int) -> bytes:
        with self.bus.turn(self) as rtu:
            return rtu.read_file_records(file_number, record_number, count)

    def write_file_records(self, file_number: int, record_number: int, data: bytes) -> None:
        with self.bus.turn(self) as rtu:
            rtu.write_file_records(file_number, record_number, data)

    def close(self) -> None:
        """Nothing: the port is the bus's (SharedBus.close), and the other instruments still use it."""


def probe_request(address: int) -> bytes:
    frame = struct.pack(">BBHH", address, 0x04, _PROBE_REGISTER.address, 1)
    return frame + crc16_modbus_bytes(frame)


def count_replies(data: bytes, address: int) -> int:
    """How many whole, well-formed replies to probe_request(address) `data` holds back to back; -1 when the
    bytes are not just such replies (collided or garbled)."""
    size = 7  # address, function, byte count, one register, CRC
    if not data:
        return 0
    if len(data) % size:
        return -1
    frames = [data[i:i + size] for i in range(0, len(data), size)]
    if all(f[0] == address and f[1] == 0x04 and f[2] == 2 and crc16_modbus(f) == 0 for f in frames):
        return len(frames)
    return -1


def probe_address(bus: SharedBus, address: int, *, listen_s: float | None = None) -> None:
    """DeviceError unless exactly one device answers at `address` on the bus: none answering names the address,
    several (or replies that collide, every round) names the collision."""
    with bus.lock:
        listen = listen_s if listen_s is not None else bus._rtu.request_timeout_s(8, 7) + 0.05
        results = []
        for round_ in range(PROBE_ROUNDS):
            # each round after a silent or garbled one listens twice as long: a busy device may answer late
            results.append(count_replies(bus._rtu.listen_after(probe_request(address), listen * 2 ** round_),
                                         address))
            if results[-1] == 1:
                return
        if all(n == 0 for n in results):
            raise DeviceError(f"no instrument answers at Modbus address {address} on {bus.port}")
        raise DeviceError(f"address collision on the bus {bus.port}: more than one device answers at Modbus "
                          f"address {address} (or its replies are garbled every time); give each instrument its own "
                          f"address: `trimeter config set modbus_address N --port PORT --address OLD` with it alone "
                          f"on the bus, `trimeter config save`, then restart it")
