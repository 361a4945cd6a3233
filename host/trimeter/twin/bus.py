"""Several twins on one simulated RS-485 bus: one pty for the host, every instrument at its own address.

```
host ──pty (the bus)── BusHub ──┬── ModbusProxy of twin 1 (its faults) ── trimeter-fw-sim --address 1
                                ├── ModbusProxy of twin 2 ──────────────── trimeter-fw-sim --address 2
                                └── …
```

The hub models a 4-wire (full-duplex) RS-485 bus: every byte the host sends reaches every instrument,
and what an instrument sends reaches only the host (the instruments do not hear each other). Each
firmware answers only frames with its own address and stays silent otherwise, so on a healthy bus one
reply comes back per request; a fault injected on one twin's proxy (drop, corrupt, late, a stuck slider)
stays on that twin's branch of the bus. Two twins given one address both answer: the collision a host
must refuse (trimeter.device.bus.probe_address tells it).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty
from pathlib import Path
from typing import Any

from trimeter.errors import InputError
from trimeter.twin._pty import open_raw_pty, read_some, write_all
from trimeter.twin.faults import FaultConfig
from trimeter.twin.twin import Twin

MAX_INSTRUMENTS = 32  # one RS-485 unit load each: what a standard transceiver drives without repeaters


class BusHub:
    """The bus pty ⇄ each branch port (a twin's proxy pty); see the module docstring for who hears what."""

    def __init__(self, branches: list[str]) -> None:
        self._master, self._slave, self.port = open_raw_pty()
        self._branches: list[int] = []
        for path in branches:
            fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            with contextlib.suppress(Exception):
                tty.setraw(fd)
            self._branches.append(fd)
        self.counters = {"bytes_to_instruments": 0, "bytes_to_host": 0}
        self._wake_r, wake_w = os.pipe()
        self._wake_w: int | None = wake_w  # None once closed
        self._thread = threading.Thread(target=self._run, name="twin-bus-hub", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        alive = set(self._branches)
        while True:
            ready, _, _ = select.select([self._master, self._wake_r, *alive], [], [])
            if self._wake_r in ready:
                return
            if self._master in ready and (data := read_some(self._master)):
                self.counters["bytes_to_instruments"] += len(data)
                for fd in alive:
                    write_all(fd, data, timeout_s=0.2)
            for fd in [fd for fd in ready if fd in alive]:
                data = read_some(fd)
                if data is None:
                    alive.discard(fd)  # that twin is gone: the host hears silence at its address
                elif data:
                    self.counters["bytes_to_host"] += len(data)
                    write_all(self._master, data, timeout_s=0.2)

    def close(self) -> None:
        if self._wake_w is None:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w, *self._branches):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_w = None


def check_addresses(addresses: list[int]) -> list[int]:
    """The instruments' addresses as given, or InputError: each within 1..247; at most MAX_INSTRUMENTS.
    Duplicates are allowed here on purpose (a collision to test the host against)."""
    if not 1 <= len(addresses) <= MAX_INSTRUMENTS:
        raise InputError(f"a bus holds 1..{MAX_INSTRUMENTS} instruments, got {len(addresses)}")
    for address in addresses:
        if isinstance(address, bool) or not isinstance(address, int) or not 1 <= address <= 247:
            raise InputError(f"instrument address must be within 1..247, got {address!r}")
    return list(addresses)


class TwinBus:
    """N twins on one bus. `addresses` default 1..N; `faults[i]` is twin i's (None: healthy); every other
    keyword goes to each Twin (its state in `state_dir`/instrument-ADDRESS when a state_dir is given).
    Use as a context manager."""

    def __init__(self, count: int | None = None, *, addresses: list[int] | None = None,
                 faults: list[FaultConfig | None] | None = None, state_dir: str | Path | None = None,
                 seed: int | None = None, **twin_kwargs: Any) -> None:
        if addresses is None:
            if isinstance(count, bool) or not isinstance(count, int):
                raise InputError(f"the number of instruments must be an integer, got {count!r}")
            addresses = list(range(1, count + 1)) if count >= 1 else []
        self.addresses = check_addresses(addresses)
        faults = list(faults) if faults is not None else [None] * len(self.addresses)
        if len(faults) != len(self.addresses):
            raise InputError(f"faults: {len(faults)} given for {len(self.addresses)} instruments")
        self.twins: list[Twin] = []
        for i, (address, fault) in enumerate(zip(self.addresses, faults, strict=True)):
            twin_state = None if state_dir is None else Path(state_dir) / f"instrument-{i + 1}"
            self.twins.append(Twin(address=address, faults=fault, state_dir=twin_state,
                                   seed=None if seed is None else seed + i, **twin_kwargs))
        self.hub: BusHub | None = None
        self.modbus_port: str | None = None

    def __enter__(self) -> "TwinBus":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> "TwinBus":
        try:
            for twin in self.twins:
                twin.start()
            self.hub = BusHub([str(twin.modbus_port) for twin in self.twins])
            self.modbus_port = self.hub.port
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        if self.hub is not None:
            self.hub.close()
            self.hub = None
        for twin in reversed(self.twins):
            twin.close()

    @property
    def running(self) -> bool:
        return self.hub is not None and all(twin.running for twin in self.twins)

    def twin(self, address: int) -> Twin:
        """The (first) twin at `address`."""
        for twin in self.twins:
            if twin.address == address:
                return twin
        raise InputError(f"no instrument at address {address} on this bus ({', '.join(map(str, self.addresses))})")

    def ports(self) -> dict:
        """What `trimeter sim --instruments N --json` prints."""
        return {"modbus_port": self.modbus_port,
                "instruments": [{"address": t.address, "spectrometer_url": t.spectrometer_url,
                                 "control_path": t.control_path} for t in self.twins]}
