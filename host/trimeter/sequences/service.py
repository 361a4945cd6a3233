"""Press-button mode (`trimeter serve`): the instrument on its own, driven by its front button.
This module keeps the button loop, the LED and the reconnect policy; what a press runs is a plain
function (sequences.calibrate.calibrate, sequences.measure.measure) that `trimeter measure`, the web
page and the tests call too.

Calibration missing, older than `calibration_max_age_s`, or the device was reset since: the LED
triple-blinks ("empty the holder and press") as soon as that is seen, and a press then checks that the
holder is empty (a sample or swapped slots are refused with what was seen; the LED keeps asking),
warms up (until the lamps are stable) and calibrates; the calibration is checked (physical bounds,
agreement with the previous good one) before it is saved; then the LED goes steady. A press while the
LED does not ask is never taken for an empty holder: it only starts the asking.
Otherwise a press captures the sample, checks the shot against the calibration and the map (a failed
lamp refuses it: nothing is written), fits and writes the results directory.
Status LED: steady on = ready (press to measure) · slow blink = working · triple blink = empty the
holder and press (to calibrate) · double blink = put the next sample in and press · fast blink = the
last press failed (see the log) · the firmware's own slow blink at power-up = not yet connected.
A device reset or a lost link never ends the service: it reconnects, re-arms, marks the calibration
stale, and a measurement the reset interrupted leaves no result directory. A request a noisy line loses
is tried again under the sequences' RetryPolicy, inside a sequence (the Runner) and outside it alike
(polls, status LED, lamps, the map-table check: `_on_device`), so it does not cost the press.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, TypeVar

from trimeter.device import Device
from trimeter.device.transport import LinkError
from trimeter.device.backup import config_source_warning
from trimeter.domain import Calibration, InstrumentInfo, Sample
from trimeter.domain.measurement import DeviceTableCheck, Estimate
from trimeter.errors import CheckError, DeviceError, TrimeterError
from trimeter.device.table_cache import instrument_table
from trimeter.formats.device_table import DeviceTable
from trimeter.results.spool import recover_partials
from trimeter.sequences import measure as pipeline
from trimeter.sequences.calibrate import calibrate, previous_calibration
from trimeter.sequences.checks import calibration_problems
from trimeter.sequences.settings import HostSettings
from trimeter.sequences.steps import RetryPolicy, Runner, retry_on_link_error
from trimeter.spectrometer.base import Spectrometer

READY, WORKING, FAILED = "on", "slow_blink", "fast_blink"
NEXT_SAMPLE = "double_blink"  # two samples: the first is captured, put the second in and press
EMPTY_HOLDER = "triple_blink"  # a calibration is due: empty the holder and press
T = TypeVar("T")


@dataclass
class Event:
    # connected | press | empty_holder | calibrating | refused | warmed_up | calibrated | next_sample | advice |
    # measured | failed | warning | reset | reconnecting | link_lost | link_restored
    kind: str
    message: str
    data: dict = field(default_factory=dict)


def lamps_on(device: Device) -> None:
    """Both LEDs on at full level with every shutter closed: the warm idle state."""
    device.write("led_panels_level", 1.0)
    device.write("led_collimated_level", 1.0)
    device.set_lights(panels=False, collimated=False)


def calibration_is_stale(calibration: Calibration | None, uptime_s: float, max_age_s: float) -> str | None:
    """Why the calibration can't be used now (None = usable)."""
    if calibration is None:
        return "no calibration yet"
    if uptime_s < calibration.device_time_s:
        return "the device was reset since the calibration"
    if uptime_s - calibration.device_time_s > max_age_s:
        return f"the calibration is {uptime_s - calibration.device_time_s:.0f} s old (max {max_age_s:g} s)"
    return None


POLL_S = 0.05  # the button poll's interval: a press is seen within it


class Service:
    """The press-button loop. `open_device()` / `open_spectrometer()` are factories so it can reconnect."""

    def __init__(self, open_device: Callable[[], Device], open_spectrometer: Callable[[], Spectrometer],
                 settings: HostSettings, *, on_event: Callable[[Event], None] | None = None,
                 on_progress: Callable[[float, str], None] | None = None, label: str | None = None,
                 device_clock: Callable[[], float] | None = None, retry: RetryPolicy = RetryPolicy()) -> None:
        self._open_device = open_device
        self._open_spectrometer = open_spectrometer
        self.settings = settings
        self.on_event = on_event or (lambda e: None)
        self.on_progress = on_progress
        self.label = label
        self.device_clock = device_clock
        self.retry = retry
        self.poll_s = POLL_S  # longer for an instrument sharing its bus (sequences.instruments)
        self.device: Device | None = None
        self.spectrometer: Spectrometer | None = None
        self.calibration: Calibration | None = None
        self._button: int | None = None
        self._uptime = -1
        self.last_result: Path | None = None
        self.last_parameters: Estimate | None = None
        self.last_advice: list[str] = []  # trimeter.inversion.flags.advice on the last measurement's fit
        self.last_timing: dict = {}
        self.last_incomplete: str | None = None  # why the last measurement has fewer samples than asked
        self.last_instrument_table: dict = {}  # the table last read from the device (instrument_table)
        self._status = READY   # what the LED shows between presses (kept across reconnects)
        self.calibration_stale_reason: str | None = None  # set when a reset was seen
        self.calibration_requested: str | None = None  # a calibration asked for by name (the web page)
        self._next_sample_confirmed = threading.Event()  # the web page's stand-in for the double-blink press
        self.calibration = previous_calibration(settings)
        if self.calibration is not None and (problems := calibration_problems(self.calibration)):
            self.calibration_stale_reason = "the saved calibration fails its checks (" + "; ".join(problems) + ")"

    # --------------------------------------------------------------------------- connection
    def connect(self) -> None:
        self.close()
        self.device = self._open_device()
        try:
            self.spectrometer = self._open_spectrometer()  # reopened too: it may have been re-plugged
        except BaseException:
            self.close()
            raise
        button, uptime = self.device.read_many("button_events", "uptime_s").values()
        self._button, self._uptime = button, uptime
        if not self.device.read("led_panel_left_on"):
            # This service keeps the lamps on: off means a reset or power-up, so they are cold.
            self.calibration_stale_reason = self.calibration_stale_reason or \
                "the lamps were off (device reset or power-up) and must warm up again"
        lamps_on(self.device)
        self.device.write("status_pattern", self._status)
        identity = self.device.identity
        firmware = ".".join(map(str, identity.firmware_version)) if identity is not None else "unchecked"
        self._emit("connected", f"connected (firmware {firmware})")
        if warning := config_source_warning(self.device.read("config_source")):
            self._emit("warning", warning)  # slot positions, steps/mm … may be wrong for this instrument
        if self._status != EMPTY_HOLDER and (reason := self.calibration_due(uptime)):
            self._ask_empty_holder(reason)

    def close(self) -> None:
        for name in ("device", "spectrometer"):
            thing = getattr(self, name)
            if thing is not None:
                with contextlib.suppress(Exception):  # closing a link that is already gone
                    thing.close()
                setattr(self, name, None)

    def _emit(self, kind: str, message: str, **data: object) -> None:
        self.on_event(Event(kind, message, data))

    def _on_device(self, what: str, action: Callable[[Device], T]) -> T:
        """`action(device)` under the same RetryPolicy as a sequence's steps: a request the line lost is tried
        again after a backoff and a reopen; a reset or a refusal is not. Every action here sets a state or
        reads one, so it is safe to repeat."""
        device = self.connected_device()
        lost = False

        def attempt() -> T:
            # Told at the first failed try, not after the retries give up (tens of seconds): the status drops
            # the device and queued work expires while the link is being tried again.
            nonlocal lost
            try:
                result = action(device)
            except LinkError as exc:
                if not lost:
                    lost = True
                    self._emit("link_lost", f"the device stopped answering while {what} ({exc}); trying again")
                raise
            if lost:
                self._emit("link_restored", "the device answers again")
            return result

        return retry_on_link_error(attempt, what, self.retry, device.transport, abandoned="gave up on the device link")

    def connected_device(self) -> Device:
        """The open device: a DeviceError, which the loop answers by reconnecting, when there is none."""
        if self.device is None:
            raise DeviceError("the device is not connected")
        return self.device

    def _show(self, pattern: str) -> None:
        self._on_device("setting the status LED", lambda d: d.write("status_pattern", pattern))

    @property
    def pattern(self) -> str:
        """What the LED shows between presses: READY, EMPTY_HOLDER (asking), FAILED; NEXT_SAMPLE while it waits."""
        return self._status

    @property
    def device_uptime_s(self) -> float | None:
        """The device's uptime at the last poll (None before the first)."""
        return None if self._uptime < 0 else float(self._uptime)

    # --------------------------------------------------------------------------------- loop
    def serve(self, stop: Callable[[], bool] = lambda: False, poll_s: float | None = None,
              reconnect_s: float = 0.5, between_polls: Callable[[str | None], None] | None = None) -> None:
        """Run until `stop()` is true. Survives resets, lost links and failed measurements. `poll_s`: the
        button poll's interval (default: self.poll_s).
        `between_polls(outcome of the poll)` runs on this thread after each button poll: work asked for
        elsewhere (the web page's jobs) shares the device with the button this way; a DeviceError it raises
        reconnects like the button's."""
        for note in recover_partials(self.settings.results_path):
            self._emit("warning", note)  # before any press: what interrupted writes left behind
        while not stop():
            try:
                if self.device is None:
                    self.connect()
                outcome = self.poll_once()
                if between_polls is not None:
                    between_polls(outcome)
            except DeviceError as exc:
                self._emit("reconnecting", f"device link problem: {exc}; reconnecting")
                self.close()
                time.sleep(reconnect_s)
                continue
            time.sleep(self.poll_s if poll_s is None else poll_s)
        self.close()

    def poll_once(self) -> str | None:
        """Check the button once; run whatever a press asks for. Returns what was done, if anything."""
        def poll(device: Device) -> tuple[int, int, bool]:
            return (*device.read_many("button_events", "uptime_s").values(), device.read("led_panel_left_on"))

        button, uptime, lamps = self._on_device("polling the button", poll)
        # A reset restarts the counters and darkens the lamps (which this service keeps on); uptime alone
        # misses a reset within a second of the last poll. RTU replies carry no transaction id: a reply to an
        # earlier poll arriving late has the shape of this one's and an older uptime, so a reset is believed
        # only when a second poll says so too.
        if uptime < self._uptime or not lamps:
            button, uptime, lamps = self._on_device("confirming a device reset", poll)
        if uptime < self._uptime or not lamps:
            self._emit("reset", f"device reset detected (uptime {self._uptime} → {uptime} s, lamps "
                                f"{'on' if lamps else 'off'}); lamps back on, calibration marked stale")
            self.calibration_stale_reason = "the device was reset since the calibration"
            # a power cycle re-enumerates the spectrometer too: reopen it before it is needed
            if self.spectrometer is not None:
                with contextlib.suppress(Exception):  # it is gone already
                    self.spectrometer.close()
            self.spectrometer = self._open_spectrometer()
            self._button, self._uptime = button, uptime
            self._on_device("switching the lamps on", lamps_on)
            self._show(self._status)
            self._ask_empty_holder(self.calibration_stale_reason)
            return "reset"
        self._uptime = uptime
        if self._status != EMPTY_HOLDER and button == self._button and (reason := self.calibration_due(uptime)):
            self._ask_empty_holder(reason)  # before anyone presses to measure with a stale calibration
        if button == self._button:
            return None
        self._button = button
        self._emit("press", "button pressed")
        return self.handle_press()

    def calibration_due(self, uptime_s: float) -> str | None:
        """Why a calibration is needed before the next measurement (None: the one held is usable)."""
        return self.calibration_stale_reason or self.calibration_requested or calibration_is_stale(
            self.calibration, uptime_s, self.settings.calibration_max_age_s)

    def ask_to_calibrate(self, reason: str) -> None:
        """A calibration asked for other than by the LED (the web page): the LED asks for an empty holder,
        and the next press (or its stand-in) runs the same holder check as any calibration."""
        self.calibration_requested = reason
        if self._status != EMPTY_HOLDER:
            self._ask_empty_holder(reason)

    def confirm_next_sample(self) -> None:
        """The web page's stand-in for the press that says the next sample is in (thread-safe)."""
        self._next_sample_confirmed.set()

    def _ask_empty_holder(self, reason: str) -> None:
        self._status = EMPTY_HOLDER
        self._show(EMPTY_HOLDER)
        self._emit("empty_holder", f"{reason}: empty the sample holder and press the button to calibrate",
                   reason=reason)

    def handle_press(self, samples: list[tuple[float, str | None]] | None = None, label: str | None = None) -> str:
        """What a press does. `samples` ((thickness, map or None) each) and `label`: a measurement asked for
        by name (the web page) instead of the host config's; it never calibrates: a due calibration only asks."""
        try:
            reason = self.calibration_due(self._on_device("reading the device's uptime", lambda d: d.read("uptime_s")))
            if reason and (self._status != EMPTY_HOLDER or samples is not None):
                # this press was meant to measure, with a sample in: it must not calibrate
                self._ask_empty_holder(reason)
                return "asked"
            self._show(WORKING)
            if reason:
                self._emit("calibrating", f"{reason}: checking that the holder is empty, then warming up and "
                                          f"calibrating")
                try:
                    self.calibrate()
                except CheckError as exc:
                    self._emit("refused", f"{exc}; then press the button again")
                    self._ask_empty_holder(reason)
                    return "refused"
                outcome = "calibrated"
            else:
                self.measure(self.resolve_samples(samples or self.settings.serve_samples),
                             between=self._await_next_sample, label=label)
                outcome = "incomplete" if self.last_incomplete else "measured"
            if outcome == "incomplete" and self.last_incomplete:  # written, but not what was asked for: the LED says so
                self._emit("failed", self.last_incomplete)
            self._status = FAILED if outcome == "incomplete" else READY
            self._show(self._status)
            return outcome
        except DeviceError as exc:
            self._status = FAILED
            self._emit("failed", str(exc))
            self._safe_status(FAILED)
            raise
        except TrimeterError as exc:
            self._status = FAILED
            self._emit("failed", str(exc))
            self._safe_status(FAILED)
            return "failed"

    def _await_next_sample(self, thickness: float, poll_s: float = 0.05) -> None:
        """measure()'s `between` under `serve`: the LED double-blinks until the button is pressed again
        (the next sample is in); that press is consumed here, not taken as a new measurement. No press
        within swap_timeout_s, or a device reset meanwhile, raises: measure() then writes what it has."""
        self._show(NEXT_SAMPLE)
        self._emit("next_sample", f"insert the {thickness:g} mm sample and press the button", thickness_mm=thickness)
        deadline = time.monotonic() + self.settings.swap_timeout_s
        self._next_sample_confirmed.clear()  # only a confirm given while this asks counts
        while True:
            button, uptime = self._on_device("polling the button", lambda d: d.read_many("button_events",
                                                                                         "uptime_s").values())
            if uptime < self._uptime:  # left for poll_once to handle as a reset: lamps, calibration
                raise DeviceError(f"the device was reset while waiting for the {thickness:g} mm sample")
            confirmed = self._next_sample_confirmed.is_set()
            if button != self._button or confirmed:
                self._button = button
                self._next_sample_confirmed.clear()
                self._emit("press", f"{'confirmed on the web page' if confirmed else 'button pressed'}: "
                                    f"measuring the {thickness:g} mm sample")
                self._show(WORKING)
                return
            if time.monotonic() >= deadline:
                raise TrimeterError(f"no press within {self.settings.swap_timeout_s:g} s "
                                    f"for the {thickness:g} mm sample")
            time.sleep(poll_s)

    def _safe_status(self, pattern: str) -> None:
        with contextlib.suppress(TrimeterError):
            self.connected_device().write("status_pattern", pattern)

    # ------------------------------------------------------------------------------ actions
    def _runner(self) -> Runner:
        if self.spectrometer is None:
            raise DeviceError("the spectrometer is not open")
        return Runner(self.connected_device(), self.spectrometer, on_progress=self.on_progress,
                      device_clock=self.device_clock, retry=self.retry)

    def calibrate(self, *, warm: bool = True, force: bool = False) -> Calibration:
        """sequences.calibrate.calibrate on this service's device, with the lamps switched on first; the LED
        and events follow it (see there for the CheckError cases and `force`)."""
        self._on_device("switching the lamps on", lamps_on)
        runner = self._runner()
        identity = self.connected_device().identity
        cal = calibrate(runner, self.settings, instrument=None if identity is None else InstrumentInfo.of(identity),
                        warm=warm, force=force, on_warmed_up=lambda result: self._emit(
                            "warmed_up", f"lamps stable after {result.elapsed_s:.0f} s (drift {result.drift:.2%})",
                            drift=result.drift, elapsed_s=result.elapsed_s))
        self.calibration = cal
        self.calibration_stale_reason = self.calibration_requested = None
        self.last_timing = runner.timing.to_dict()
        self._emit("calibrated", "calibrated: insert the sample and press the button to measure",
                   timing=self.last_timing)
        self._show(READY)
        return cal

    def resolve_samples(self, requests: list[tuple[float, str | None]]) -> list[Sample]:
        """pipeline.resolve_samples with this instrument's own table for a sample without a map: the fit
        then uses what the device carries, so a host without map files measures and the two cannot differ."""
        return pipeline.resolve_samples(requests, instrument_table=self.instrument_table)

    def instrument_table(self) -> DeviceTable:
        """The table in the device's active slot (trimeter.device.table_cache.instrument_table: cached by its
        SHA-256); an event says which, and whether it was read from the device or the cache."""
        t0 = time.monotonic()
        table, slot, cached = self._on_device("reading the device's map table", instrument_table)
        self.last_instrument_table = {"name": table.name, "sha256": table.sha256, "slot": slot, "cached": cached,
                                      "seconds": round(time.monotonic() - t0, 3)}
        self._emit("table", f"map table {table.name} (ℓ = {table.thickness_mm:g} mm, sha256 {table.sha256[:12]}…) "
                            f"from the device's slot {slot}{' (cached)' if cached else ''}",
                   **self.last_instrument_table)
        return table

    def device_table(self, prepared: pipeline.PreparedFit) -> DeviceTableCheck:
        """Is the map table active in the device the very table this host fits the first sample with?

        Not by the slot's CRC-32: a table ends with its own CRC-32, so the CRC-32 over a whole valid
        table is always the CRC residue 0x2144DF1C. Compared instead: length, the 128-byte header (map
        name, source-map SHA-256, grid) and the table's trailing CRC-32 (which covers every other byte)."""
        from trimeter import registers as regs

        device = self.connected_device()
        status = device.map_status()
        active = status["map_active_slot"]
        if active == regs.MapSlot.NONE:
            return DeviceTableCheck(None, False)
        key = active.name.lower()
        slot = {"slot": active.name, "crc32": f"0x{status[f'map_slot_{key}_crc32']:08X}",
                "length": status[f"map_slot_{key}_length"], "version": status[f"map_slot_{key}_version"]}
        table = prepared.fit_table_bytes()
        if table is None:
            return DeviceTableCheck(matches_fit_table=False, **slot)
        same = len(table) == slot["length"] and len(table) > 132
        if same:
            head = device.read_map(active, 128)
            tail_at = (len(table) - 4) & ~1
            tail = device.read_map(active, len(table) - tail_at, offset=tail_at)
            same = head == table[:128] and tail == table[tail_at:]
        return DeviceTableCheck(matches_fit_table=bool(same), map=prepared.samples[0].map.name, **slot)

    def measure(self, samples: list[Sample], *, between: Callable[[float], None] | None = None,
                label: str | None = None) -> Path:
        """sequences.measure.measure with this service's device, calibration and settings; the LED, events
        and last_* follow it. When `between` raises (the next sample never came), what was captured is
        still written, marked incomplete (last_incomplete); a DeviceError is raised again after that."""
        label = label or self.label
        self.last_incomplete = None
        outcome = pipeline.measure(
            self._runner(), self.calibration, samples, self.settings, label=label, between=between,
            device_table=lambda prepared: self._on_device("reading the device's map table",
                                                          lambda d: self.device_table(prepared)),
            on_warning=lambda note: self._emit("warning", note))
        self.last_result, self.last_parameters = outcome.path, outcome.parameters
        self.last_incomplete = outcome.incomplete
        if outcome.spooled is not None:
            raise outcome.spooled
        self.last_timing = outcome.timing
        self.last_advice = outcome.measurement.provenance.advice
        for note in self.last_advice:
            self._emit("advice", note)
        provenance = outcome.measurement.provenance
        table = None if provenance.device_map_table is None else provenance.device_map_table.to_json()
        self._emit("measured", f"results written to {outcome.path}", path=outcome.path,
                   parameters=outcome.parameters, timing=outcome.timing, link=provenance.link, device_map_table=table)
        if isinstance(outcome.stopped, DeviceError):
            raise outcome.stopped
        return outcome.path
