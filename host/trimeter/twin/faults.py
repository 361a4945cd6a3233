"""Fault injection: the configuration and the Modbus proxy that corrupts, drops and delays bytes.

The proxy sits between the host's pty and the firmware's pty. A *request* is a burst of host bytes
after ≥ REQUEST_GAP_S of silence or after the device's last reply; each request's reply gets one
fate (forward, drop, late), decided when the request arrives. Byte corruption (one random bit
flipped) applies to every byte, both ways.
"""

from __future__ import annotations

import contextlib
import dataclasses
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


class ModbusProxy:
    """host pty ⇄ firmware pty, with the faults of `faults()` (read on every request, so they can change)."""

    def __init__(self, device_path: str, faults: Callable[[], FaultConfig], rng: np.random.Generator,
                 on_request: Callable[[int], None] | None = None) -> None:
        self._faults, self._rng, self._on_request = faults, rng, on_request
        self._master, self._slave, self.port = open_raw_pty()
        self._device = os.open(device_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        with contextlib.suppress(Exception):  # not a tty (a test may hand in a pipe-like device): raw mode is moot
            tty.setraw(self._device)
        self.counters = {"requests": 0, "bytes_forwarded": 0, "bytes_corrupted": 0,
                         "replies_dropped": 0, "replies_late": 0}
        self._fate = "forward"
        self._last_host_byte = -1e9
        self._held: list[tuple[float, bytes]] = []
        self._late_release = 0.0
        self._replied = False
        self._wake_r, wake_w = os.pipe()
        self._wake_w: int | None = wake_w  # None once closed
        self._thread = threading.Thread(target=self._run, name="twin-modbus-proxy", daemon=True)
        self._thread.start()

    def _corrupt(self, data: bytes, p: float) -> bytes:
        if p <= 0.0 or not data:
            return data
        hit = self._rng.random(len(data)) < p
        if not hit.any():
            return data
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        arr[hit] ^= (1 << self._rng.integers(0, 8, int(hit.sum()))).astype(np.uint8)
        self.counters["bytes_corrupted"] += int(hit.sum())
        return arr.tobytes()

    def _from_host(self, data: bytes) -> None:
        faults, now = self._faults(), time.monotonic()
        # A new request: after a silence, or as soon as the device has answered the previous one (at high
        # time scales a host may send its next request within the gap).
        if now - self._last_host_byte >= REQUEST_GAP_S or self._replied:
            self._replied = False
            self.counters["requests"] += 1
            if self._on_request is not None:
                self._on_request(self.counters["requests"])
            u = self._rng.random()
            self._fate = "drop" if u < faults.drop else "late" if u < faults.drop + faults.late else "forward"
            self.counters["replies_dropped" if self._fate == "drop" else "replies_late"] += self._fate != "forward"
            self._late_release = now + faults.late_delay_s
        self._last_host_byte = now
        self.counters["bytes_forwarded"] += len(data)
        write_all(self._device, self._corrupt(data, faults.corrupt), timeout_s=0.5)

    def _from_device(self, data: bytes) -> None:
        faults = self._faults()
        self._replied = True
        if self._fate == "drop":
            return
        data = self._corrupt(data, faults.corrupt)
        self.counters["bytes_forwarded"] += len(data)
        if self._fate == "late":
            # Held back whole; later replies with a normal fate overtake it, as on a real bus.
            self._held.append((self._late_release, data))
            self._held.sort(key=lambda item: item[0])
        else:
            write_all(self._master, data, timeout_s=0.2)

    def _run(self) -> None:
        device_alive = True
        while True:
            timeout = max(0.0, self._held[0][0] - time.monotonic()) if self._held else None
            fds = [self._master, self._wake_r] + ([self._device] if device_alive else [])
            ready, _, _ = select.select(fds, [], [], timeout)
            if self._wake_r in ready:
                return
            if self._master in ready:
                data = read_some(self._master)
                if data and device_alive:
                    self._from_host(data)
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
