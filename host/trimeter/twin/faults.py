"""Fault injection: the configuration and the Modbus proxy that corrupts, drops and delays bytes.

The proxy sits between the host's pty and the firmware's pty. A *request* is one RTU frame from the host
(its length read from the function code) or, for bytes that do not parse as one, a burst ended by
≥ REQUEST_GAP_S of silence (at most MAX_FRAME bytes); it is forwarded once complete. Each request meets a
fate: its reply is forwarded, dropped or late, and some of its bytes and of its reply's bytes have one
random bit flipped (probability `corrupt` per byte). The fate is drawn from a generator keyed on the seed,
a digest of the request's bytes and how many times those exact bytes came before (`Fates`), so with one
seed a request meets the same fate on its n-th appearance however many other requests (status polls,
retries) the wall clock let in between. Device bytes are counted as the reply of the request they follow
(before any request: of the empty request), so spontaneous bytes are keyed the same way. `reset_at`
counts every request, polls included: it moves with their number.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import select
import threading
import time
import tty
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from trimeter.errors import InputError
from trimeter.twin._pty import open_raw_pty, read_some, write_all

REQUEST_GAP_S = 0.003
MAX_FRAME = 256  # bytes: the longest RTU frame; a longer unparsed burst is cut here
LAMP_FAILURES = ("panels", "collimated", "both")
SHUTTERS = ("panel_left", "panel_right", "collimated")
LAMP_CHANNELS = SHUTTERS   # one LED channel behind each shutter
DIMMABLE = {"panels": ("panel_left", "panel_right"), "panel_left": ("panel_left",),
            "panel_right": ("panel_right",), "collimated": ("collimated",), "both": LAMP_CHANNELS}


@dataclass(frozen=True)
class FaultConfig:
    corrupt: float = 0.0
    drop: float = 0.0
    late: float = 0.0
    late_delay_s: float = 1.0
    reset_at: int | None = None
    stuck_slider: bool = False
    lamp_failure: str | None = None
    stuck_shutter_open: str | None = None   # a shutter whose blade lets light through whatever it is told
    endstop_broken: bool = False
    lamp_dimmed: str | None = None          # "LAMP:FACTOR": that lamp emits FACTOR × nominal (an aged LED)

    def __post_init__(self) -> None:
        for name in ("corrupt", "drop", "late"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0.0 <= value <= 1.0:
                raise InputError(f"fault {name} must be a probability in 0..1, got {value!r}")
        if not isinstance(self.late_delay_s, (int, float)) or not 0.0 <= self.late_delay_s <= 60.0:
            raise InputError(f"fault late_delay_s must be within 0..60 s, got {self.late_delay_s!r}")
        if self.reset_at is not None and (isinstance(self.reset_at, bool) or not isinstance(self.reset_at, int)
                                          or self.reset_at < 1):
            raise InputError(f"fault reset_at must be a request number ≥ 1, got {self.reset_at!r}")
        if not isinstance(self.stuck_slider, bool):
            raise InputError(f"fault stuck_slider must be true/false, got {self.stuck_slider!r}")
        if self.lamp_failure is not None and self.lamp_failure not in LAMP_FAILURES:
            raise InputError(f"fault lamp_failure must be one of {', '.join(LAMP_FAILURES)}, got {self.lamp_failure!r}")
        if self.stuck_shutter_open is not None and self.stuck_shutter_open not in SHUTTERS:
            raise InputError(f"fault stuck_shutter_open must be one of {', '.join(SHUTTERS)}, got "
                             f"{self.stuck_shutter_open!r}")
        if not isinstance(self.endstop_broken, bool):
            raise InputError(f"fault endstop_broken must be true/false, got {self.endstop_broken!r}")
        if self.lamp_dimmed is not None:
            self.lamp_emission()  # validates

    def lamp_emission(self) -> dict[str, float]:
        """Each LED channel's emission relative to nominal under lamp_dimmed and lamp_failure (1: healthy)."""
        emission = dict.fromkeys(LAMP_CHANNELS, 1.0)
        if self.lamp_dimmed is not None:
            target, _, factor = str(self.lamp_dimmed).partition(":")
            try:
                value = float(factor)
            except ValueError:
                value = float("nan")
            if target not in DIMMABLE or not 0.0 <= value <= 2.0:
                raise InputError(f"fault lamp_dimmed must be LAMP:FACTOR with LAMP one of {', '.join(DIMMABLE)} and "
                                 f"FACTOR within 0..2, got {self.lamp_dimmed!r}")
            for channel in DIMMABLE[target]:
                emission[channel] = value
        if self.lamp_failure is not None:
            for channel in DIMMABLE[self.lamp_failure]:
                emission[channel] = 0.0
        return emission

    def replace(self, **changes: Any) -> FaultConfig:
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise InputError(f"unknown fault {sorted(unknown)[0]!r} (known: "
                             f"{', '.join(f.name for f in dataclasses.fields(self))})")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def parse(cls, text: str) -> "FaultConfig":
        """`corrupt=0.01,drop=0.02,late=0.01,reset_at=STEP,stuck_slider,lamp_failure[=panels],
        stuck_shutter_open=SHUTTER,endstop_broken,lamp_dimmed=panels:0.8`."""
        changes: dict = {}
        for item in filter(None, (s.strip() for s in (text or "").split(","))):
            key, eq, value = item.partition("=")
            key = key.strip().replace("-", "_")
            try:
                if key in ("corrupt", "drop", "late", "late_delay_s"):
                    changes[key] = float(value)
                elif key == "reset_at":
                    changes[key] = int(value)
                elif key in ("stuck_slider", "endstop_broken"):
                    changes[key] = (not eq) or value.lower() in ("1", "true", "yes", "on")
                elif key == "lamp_failure":
                    changes[key] = value if eq else "panels"
                else:
                    changes[key] = value  # replace() names the unknown fault
            except ValueError:
                raise InputError(f"fault {key} has a malformed value {value!r}") from None
        return cls().replace(**changes)


def as_optics_see_it(plant_state: dict, faults: FaultConfig) -> dict:
    """The plant state with the faults the firmware cannot know about applied (a shutter stuck open)."""
    if faults.stuck_shutter_open is None:
        return plant_state
    shutters = dict(plant_state.get("shutters", {}))
    shutters[faults.stuck_shutter_open] = {**shutters.get(faults.stuck_shutter_open, {}), "open": True}
    return {**plant_state, "shutters": shutters}


def as_lamps_emit(plant_state: dict, faults: FaultConfig) -> dict:
    """The plant state with each LED level scaled by its lamp's dimming (lamp_dimmed): a dimmed lamp driven
    at level L lights the sample like a healthy one at L × factor (its heat still follows the drive)."""
    if faults.lamp_dimmed is None:
        return plant_state
    emission = faults.lamp_emission()
    leds = {k: float(v) for k, v in plant_state.get("leds", {}).items()}
    for channel in LAMP_CHANNELS:
        if channel in leds:
            leds[channel] *= emission[channel]
    if "panel_left" in leds and "panel_right" in leds:
        leds["panels"] = 0.5 * (leds["panel_left"] + leds["panel_right"])
    return {**plant_state, "leds": leds}


# A request frame's length from its header, for the function codes a Modbus master sends: fixed, or
# (offset of its byte count, bytes besides the counted ones).
_FIXED_LENGTH = {1: 8, 2: 8, 3: 8, 4: 8, 5: 8, 6: 8, 7: 4, 8: 8, 11: 4, 12: 4, 17: 4}
_COUNTED_LENGTH = {15: (6, 9), 16: (6, 9), 20: (2, 5), 21: (2, 5), 23: (10, 13)}
_READ_DEVICE_ID = (0x2B, 0x0E, 7)   # encapsulated interface, MEI type "read device identification": 7 bytes


def request_length(buffer: bytes) -> int | None:
    """The length of the RTU request frame `buffer` starts with, as its header gives it (capped at MAX_FRAME);
    None while the header is incomplete or its function code is not one this proxy knows."""
    if len(buffer) < 2:
        return None
    code = buffer[1]
    if code in _FIXED_LENGTH:
        return _FIXED_LENGTH[code]
    if code in _COUNTED_LENGTH:
        at, extra = _COUNTED_LENGTH[code]
        return min(buffer[at] + extra, MAX_FRAME) if len(buffer) > at else None
    if code == _READ_DEVICE_ID[0] and len(buffer) > 2 and buffer[2] == _READ_DEVICE_ID[1]:
        return _READ_DEVICE_ID[2]
    return None


class Fate:
    """One request's fate: what happens to its reply (`reply`: forward, drop, late) and the bit flips of its
    bytes, the request's first and then its reply's, as `flips` hands them out in order. Its generator,
    keyed by Fates, is made only when a fault has a chance (a clean link costs a digest per request)."""

    def __init__(self, key: list[int], faults: FaultConfig) -> None:
        self._key = key
        self._rng: np.random.Generator | None = None
        self._skipped = 0   # bytes handed out while corrupt was 0, whose uniforms are not drawn yet
        self.reply = "forward"
        if faults.drop + faults.late > 0.0:
            u = self._generator().random()
            self.reply = "drop" if u < faults.drop else "late" if u < faults.drop + faults.late else "forward"

    def _generator(self) -> np.random.Generator:
        if self._rng is None:
            self._rng = np.random.default_rng(self._key)
            self._rng.random()  # the reply's draw comes first, whether or not it was needed
        return self._rng

    def flips(self, n: int, p: float) -> np.ndarray:
        """XOR masks for the next n bytes: one random bit set with probability p each. Each byte takes the next
        uniform u of the stream, which says both whether (u < p) and which bit (u / p in eighths); so the masks
        do not depend on how the bytes arrived in reads, nor on a stretch with p = 0 before them."""
        if p <= 0.0:
            self._skipped += n
            return np.zeros(n, dtype=np.uint8)
        u = self._generator().random(self._skipped + n)[self._skipped:]
        self._skipped = 0
        bit = np.minimum(u / p * 8.0, 7.0).astype(np.uint8)
        return np.where(u < p, np.left_shift(1, bit), 0).astype(np.uint8)


class Fates:
    """Draws each request's Fate from a generator keyed on (seed, a digest of the request's bytes, how many
    times those bytes were drawn for before): the n-th appearance of a request meets the same fate whatever
    else came in between. Holds one counter per distinct request."""

    def __init__(self, seed: int) -> None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"fault seed must be a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        self._seen: dict[int, int] = {}

    def draw(self, request: bytes, faults: FaultConfig) -> Fate:
        digest = int.from_bytes(hashlib.blake2b(request, digest_size=8).digest(), "little")
        occurrence = self._seen.get(digest, 0)
        self._seen[digest] = occurrence + 1
        return Fate([self.seed, digest, occurrence], faults)


class ModbusProxy:
    """host pty ⇄ firmware pty, with the faults of `faults()` (read on every request, so they can change)
    and the fates `seed` gives (see the module docstring)."""

    def __init__(self, device_path: str, faults: Callable[[], FaultConfig], seed: int,
                 on_request: Callable[[int], None] | None = None) -> None:
        self._fates = Fates(seed)
        self._faults, self._on_request = faults, on_request
        self._master, self._slave, self.port = open_raw_pty()
        self._device = os.open(device_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        with contextlib.suppress(Exception):  # not a tty (a test may hand in a pipe-like device): raw mode is moot
            tty.setraw(self._device)
        self.counters = {"requests": 0, "bytes_forwarded": 0, "bytes_corrupted": 0,
                         "replies_dropped": 0, "replies_late": 0}
        self._fate = self._fates.draw(b"", FaultConfig())  # device bytes before any request: forwarded
        self._pending = b""  # host bytes of a request not yet complete
        self._last_host_byte = -1e9
        self._held: list[tuple[float, bytes]] = []
        self._late_release = 0.0
        self._wake_r, wake_w = os.pipe()
        self._wake_w: int | None = wake_w  # None once closed
        self._thread = threading.Thread(target=self._run, name="twin-modbus-proxy", daemon=True)
        self._thread.start()

    def _corrupt(self, data: bytes, p: float) -> bytes:
        mask = self._fate.flips(len(data), p)
        hits = int(np.count_nonzero(mask))
        if not hits:
            return data
        self.counters["bytes_corrupted"] += hits
        return (np.frombuffer(data, dtype=np.uint8) ^ mask).tobytes()

    def _from_host(self, data: bytes) -> None:
        self._last_host_byte = time.monotonic()
        self._pending += data
        while self._pending:
            length = request_length(self._pending)
            if length is None and len(self._pending) >= MAX_FRAME:
                length = MAX_FRAME
            if length is None or len(self._pending) < length:
                return  # the rest of the frame, or the silence that ends the burst, is still to come
            request, self._pending = self._pending[:length], self._pending[length:]
            self._forward_request(request)

    def _forward_request(self, request: bytes) -> None:
        faults = self._faults()
        self.counters["requests"] += 1
        if self._on_request is not None:
            self._on_request(self.counters["requests"])
        self._fate = self._fates.draw(request, faults)
        self.counters["replies_dropped" if self._fate.reply == "drop" else "replies_late"] += \
            self._fate.reply != "forward"
        self._late_release = time.monotonic() + faults.late_delay_s
        self.counters["bytes_forwarded"] += len(request)
        write_all(self._device, self._corrupt(request, faults.corrupt), timeout_s=0.5)

    def _from_device(self, data: bytes) -> None:
        if self._fate.reply == "drop":
            return
        data = self._corrupt(data, self._faults().corrupt)
        self.counters["bytes_forwarded"] += len(data)
        if self._fate.reply == "late":
            # Held back whole; later replies with a normal fate overtake it, as on a real bus.
            self._held.append((self._late_release, data))
            self._held.sort(key=lambda item: item[0])
        else:
            write_all(self._master, data, timeout_s=0.2)

    def _run(self) -> None:
        device_alive = True
        while True:
            deadlines = ([self._held[0][0]] if self._held else []) + \
                ([self._last_host_byte + REQUEST_GAP_S] if self._pending else [])
            timeout = max(0.0, min(deadlines) - time.monotonic()) if deadlines else None
            fds = [self._master, self._wake_r] + ([self._device] if device_alive else [])
            ready, _, _ = select.select(fds, [], [], timeout)
            if self._wake_r in ready:
                return
            if self._master in ready:
                data = read_some(self._master)
                if data and device_alive:
                    self._from_host(data)
            if self._pending and time.monotonic() - self._last_host_byte >= REQUEST_GAP_S:
                request, self._pending = self._pending, b""  # a burst that is no frame, ended by silence
                self._forward_request(request)
            if device_alive and self._device in ready:
                data = read_some(self._device)
                if data is None:
                    device_alive = False  # the firmware went away; the host sees silence (timeouts)
                elif data:
                    self._from_device(data)
            while self._held and self._held[0][0] <= time.monotonic():
                write_all(self._master, self._held.pop(0)[1], timeout_s=0.2)

    def close(self) -> None:
        if self._wake_w is None:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        for fd in (self._master, self._slave, self._device, self._wake_r, self._wake_w):
            os.close(fd)
        self._wake_w = None
