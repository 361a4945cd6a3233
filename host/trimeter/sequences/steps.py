"""Steps and the runner: plans (generators) yield steps, the runner carries them out.

A plan never touches a device: it yields `Move("white")`, `Lights(panels=True)`, `Acquire()` … and
receives each step's result back (`spectrum = yield Acquire()`). Tests drive plans with fake devices
(tests/fakes.py) or just check the steps they yield; the Runner executes them against a
trimeter.device.Device and a Spectrometer (the pattern of bluesky plans, without its stack).

The runner also guards the measurement: before every exposure it checks that the device has not been
reset (uptime went backwards, homed lost, light set-up lost), so a reset mid-sequence is a clear
DeviceError instead of a silently dark spectrum.

A step whose request found no valid reply after all of the transport's attempts (a LinkError: a noisy
or briefly lost line) is tried again, after a backoff and a reopen of the port (RetryPolicy), instead of
abandoning the whole sequence. Every step is safe to repeat: it sets a state (a slot, shutters, an
integration time, a status pattern) or reads one, and a Wait resumes from its original start. A reset
(uptime went back) and a refusal (a Modbus exception reply) are not link failures and are never retried.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Generator, TypeVar

import numpy as np

from trimeter.device.client import light_coils
from trimeter.device.transport import LinkError
from trimeter.errors import DeviceError, InputError

if TYPE_CHECKING:
    from trimeter.device.client import Device
    from trimeter.spectrometer.base import Spectrometer

T = TypeVar("T")
LAMP_MONITORS = ("panel_left", "panel_right", "collimated")  # one photodiode per LED channel


@dataclass(frozen=True)
class Move:
    slot: str  # black | white | open


@dataclass(frozen=True)
class Lights:
    """Both LEDs stay on (warm); the shutters select the set-up: diffuse panels and/or collimated beam."""

    panels: bool = False
    collimated: bool = False


@dataclass(frozen=True)
class Expose:
    """Set the integration time (clamped to the spectrometer's limits); returns the time it reports."""

    integration_time_us: float


@dataclass(frozen=True)
class Acquire:
    """Average `frames` exposures; returns raw counts (float64, dark not subtracted). With `spread`,
    returns (mean, standard error of the mean) — NaN errors for a single frame."""

    frames: int = 1
    spread: bool = False


@dataclass(frozen=True)
class Describe:
    """Returns (SpectrometerDescription, wavelengths_nm)."""


@dataclass(frozen=True)
class Wait:
    """Wait this many seconds of *device* time (the firmware's uptime: simulated seconds on the twin)."""

    seconds: float


@dataclass(frozen=True)
class DeviceTime:
    """Returns the device's uptime in seconds."""


@dataclass(frozen=True)
class LampMonitor:
    """Returns the lamp-monitor photodiodes now, in ADC counts: {"panel_left", "panel_right", "collimated"}."""


@dataclass(frozen=True)
class Status:
    pattern: str  # off | on | slow_blink | fast_blink


@dataclass(frozen=True)
class Progress:
    fraction: float
    message: str


# A plan yields steps and is sent each one's answer, whose type depends on the step; it returns a T.
Plan = Generator[object, Any, T]


@dataclass(frozen=True)
class RetryPolicy:
    """How often a step is tried when the link fails it, and how long to back off in between."""

    attempts: int = 5            # tries per step (1: a link failure abandons the sequence at once)
    backoff_s: float = 0.2       # before the 2nd try; doubled before each further one
    max_backoff_s: float = 2.0

    def __post_init__(self) -> None:
        if isinstance(self.attempts, bool) or not isinstance(self.attempts, int) or self.attempts < 1:
            raise InputError(f"step attempts must be an integer ≥ 1, got {self.attempts!r}")
        if not 0.0 <= self.backoff_s <= self.max_backoff_s <= 60.0:
            raise InputError(f"step backoff must satisfy 0 ≤ backoff_s ≤ max_backoff_s ≤ 60 s, got "
                             f"{self.backoff_s!r} / {self.max_backoff_s!r}")

    def backoff(self, failures: int) -> float:
        """Seconds to wait after the `failures`-th failed try."""
        return min(self.max_backoff_s, self.backoff_s * 2 ** (failures - 1))


@dataclass
class Timing:
    """Where a run's wall time went: exposures and waits for the device (physical) vs. everything else."""

    wall_s: float = 0.0
    exposure_s: float = 0.0         # integration time asked of the spectrometer (device seconds)
    motion_wall_s: float = 0.0      # wall time spent waiting for the slider / shutters to settle
    acquire_wall_s: float = 0.0     # wall time of the exposures (incl. readout + transfer)
    wait_wall_s: float = 0.0        # warm-up waits
    motion_device_s: float = 0.0    # device-clock time of moves + shutter/LED settles (needs a device clock)
    wait_device_s: float = 0.0      # device-clock time of warm-up waits
    requests: int = 0               # Modbus requests the run made
    request_wall_s: float = 0.0     # wall time spent inside them
    request_retries: int = 0        # transport-level repeats of a request (garbled, dropped, stale replies)
    step_retries: int = 0           # steps tried again after a link failure
    retry_wall_s: float = 0.0       # wall time the failed step tries, backoffs and reopens cost
    steps: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def retry_on_link_error(action: Callable[[], T], what: str, policy: RetryPolicy, transport: object, *,
                        sleep: Callable[[float], None] = time.sleep, timing: Timing | None = None,
                        abandoned: str = "the sequence was abandoned") -> T:
    """`action()`, tried again while it fails with a LinkError, up to `policy.attempts` tries: after each
    failure a backoff, then `transport.reopen()` (the device's identity is checked again on the next read).
    Any other error — a reset, a refusal, a fault — propagates at once. After the last try, a LinkError
    naming `what` (as the operator would say it) and what was `abandoned`. `timing` counts the retried
    tries and their wall time."""
    failures = 0
    while True:
        t0 = time.monotonic()
        try:
            return action()
        except LinkError as exc:
            failures += 1
            if failures >= policy.attempts:
                if timing is not None:
                    timing.retry_wall_s += time.monotonic() - t0
                raise LinkError(f"{what} failed {failures} times on a bad link; {abandoned} (last: {exc})") from None
            sleep(policy.backoff(failures))
            reopen = getattr(transport, "reopen", None)
            if reopen is not None:
                reopen()
            if timing is not None:
                timing.step_retries += 1
                timing.retry_wall_s += time.monotonic() - t0


class Runner:
    """Executes plans against a Device and a Spectrometer."""

    def __init__(self, device: Device, spectrometer: Spectrometer, *,
                 on_progress: Callable[[float, str], None] | None = None, move_timeout_s: float = 60.0,
                 sleep: Callable[[float], None] = time.sleep, device_clock: Callable[[], float] | None = None,
                 retry: RetryPolicy = RetryPolicy()) -> None:
        """`device_clock`: the device's own time in seconds with sub-second resolution, if there is one
        (the twin's simulated clock); it splits physical time (motion, settling) from host overhead."""
        self.device = device
        self.spectrometer = spectrometer
        self.on_progress = on_progress
        self.move_timeout_s = move_timeout_s
        self._sleep = sleep
        self._device_clock = device_clock
        self.timing = Timing()
        self._lights: tuple[bool, bool] | None = None
        self._slot: str | None = None
        self._uptime: int | None = None
        self._homed_seen = False
        self.retry = retry
        self._wait_start: int | None = None  # a Wait's start, kept across its retries

    def run(self, plan: Plan[T]) -> T:
        started = time.monotonic()
        stats = getattr(self.device.transport, "stats", None)
        requests0, busy0, retries0 = (stats.requests, stats.busy_s, stats.retries) if stats else (0, 0.0, 0)
        reply = None
        try:
            while True:
                try:
                    step = plan.send(reply)
                except StopIteration as stop:
                    return stop.value
                t0 = time.monotonic()
                reply = self.retrying(functools.partial(self.execute, step), _describe(step))
                name = type(step).__name__
                self.timing.steps[name] = self.timing.steps.get(name, 0.0) + time.monotonic() - t0
        finally:
            self.timing.wall_s += time.monotonic() - started
            if stats:
                self.timing.requests += stats.requests - requests0
                self.timing.request_wall_s += stats.busy_s - busy0
                self.timing.request_retries += stats.retries - retries0

    def retrying(self, action: Callable[[], T], what: str) -> T:
        """`action()` under the RetryPolicy (retry_on_link_error), counted in this run's timing; also for
        what a sequence's owner does on the device outside a plan, so it shares the policy."""
        self._wait_start = None
        return retry_on_link_error(action, what, self.retry, self.device.transport, sleep=self._sleep,
                                   timing=self.timing)

    # ------------------------------------------------------------------------------- guarding
    def _check_not_reset(self) -> None:
        uptime, homed = self.device.read_many("uptime_s", "homed").values()
        if self._uptime is not None and uptime < self._uptime:
            raise DeviceError(f"the device was reset during the sequence (uptime went from {self._uptime} s to "
                              f"{uptime} s); the measurement was abandoned")
        if self._homed_seen and not homed:
            raise DeviceError("the device lost its homing during the sequence (reset?); the measurement was abandoned")
        self._uptime = uptime
        self._homed_seen = self._homed_seen or bool(homed)

    def _check_setup(self) -> None:
        self._check_not_reset()
        if self._lights is not None:
            want = light_coils(panels=self._lights[0], collimated=self._lights[1])
            if [bool(c) for c in self.device.transport.read_bits("coil", 0, len(want))] != want:
                raise DeviceError("the device lost its light set-up during the sequence (reset?); "
                                  "the measurement was abandoned")

    # ------------------------------------------------------------------------------- execute
    def execute(self, step: object) -> Any:
        if isinstance(step, (Move, Lights, Wait)) and self._device_clock is not None:
            d0 = self._device_clock()
            result = self._execute(step)
            spent = self._device_clock() - d0
            if isinstance(step, Wait):
                self.timing.wait_device_s += spent
            else:
                self.timing.motion_device_s += spent
            return result
        return self._execute(step)

    def _execute(self, step: object) -> Any:
        dev, spec = self.device, self.spectrometer
        if isinstance(step, Move):
            t0 = time.monotonic()
            self._check_not_reset()
            dev.goto(step.slot, timeout_s=self.move_timeout_s)  # homes on first use after power-up
            self._check_not_reset()
            self._slot = step.slot
            self.timing.motion_wall_s += time.monotonic() - t0
            return None
        if isinstance(step, Lights):
            t0 = time.monotonic()
            dev.set_lights(panels=step.panels, collimated=step.collimated)
            dev.wait_idle(self.move_timeout_s)
            self._lights = (step.panels, step.collimated)
            self.timing.motion_wall_s += time.monotonic() - t0
            return None
        if isinstance(step, Expose):
            lo, hi = spec.integration_time_us_limits
            spec.integration_time_us = int(min(max(round(step.integration_time_us), lo), hi))
            return spec.integration_time_us
        if isinstance(step, Acquire):
            self._check_setup()
            t0 = time.monotonic()
            frames = [np.asarray(spec.intensities(), dtype=np.float64) for _ in range(max(1, step.frames))]
            self.timing.acquire_wall_s += time.monotonic() - t0
            self.timing.exposure_s += spec.integration_time_us * 1e-6 * len(frames)
            self._check_not_reset()
            mean = np.mean(frames, axis=0)
            if not step.spread:
                return mean
            if len(frames) < 2:
                return mean, np.full_like(mean, np.nan)
            return mean, np.std(frames, axis=0, ddof=1) / np.sqrt(len(frames))
        if isinstance(step, Describe):
            return spec.description, np.asarray(spec.wavelengths_nm(), dtype=np.float64)
        if isinstance(step, DeviceTime):
            return float(dev.read("uptime_s"))
        if isinstance(step, Wait):
            t0 = time.monotonic()
            if self._wait_start is None:
                self._wait_start = dev.read("uptime_s")
            while (now := dev.read("uptime_s")) - self._wait_start < step.seconds:
                if now < self._wait_start:
                    break  # a reset: _check_not_reset says so
                self._sleep(0.02)
            self._check_not_reset()
            self._wait_start = None
            self.timing.wait_wall_s += time.monotonic() - t0
            return None
        if isinstance(step, Status):
            dev.write("status_pattern", step.pattern)
            return None
        if isinstance(step, LampMonitor):
            readings = dev.read_many(*(f"lamp_monitor_{lamp}" for lamp in LAMP_MONITORS))
            return {lamp: int(readings[f"lamp_monitor_{lamp}"]) for lamp in LAMP_MONITORS}
        if isinstance(step, Progress):
            if self.on_progress:
                self.on_progress(step.fraction, step.message)
            return None
        raise TypeError(f"unknown step {step!r}")




def _describe(step: object) -> str:
    """A step as the operator would say it, for errors."""
    if isinstance(step, Move):
        return f"moving to the {step.slot} slot"
    if isinstance(step, Lights):
        return "setting the shutters"
    if isinstance(step, Acquire):
        return "an exposure"
    if isinstance(step, Wait):
        return f"a {step.seconds:g} s wait"
    if isinstance(step, Status):
        return "setting the status LED"
    return f"the {type(step).__name__} step"
