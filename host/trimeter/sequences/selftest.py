"""`trimeter selftest`: is a freshly built instrument wired and working? Each check drives one part
(homing, the slots, every shutter and LED, the spectrometer's dark level and exposure range), judges
what the device and the spectrometer report, and says what to fix when it fails.

    report = run_selftest(device, spectrometer)      # device: trimeter.device.Device
    report.passed; [c.to_dict() for c in report.checks]

Checks run in order and share what earlier ones found: a slot the slider never reached is not used
for an optical check (that check says so and is skipped, never silently passed). A failing or
crashing check does not stop the rest. Shutters and LEDs have no feedback of their own, so the
spectrometer is the judge: an LED must raise the signal by a clear margin when it switches on, and
its shutter must block that light when it closes.
"""

from __future__ import annotations

import time
import tomllib
from dataclasses import dataclass, field
from enum import IntEnum
from functools import lru_cache
from typing import TYPE_CHECKING, Callable

import numpy as np

from trimeter import registers as regs
from trimeter.errors import TrimeterError
from trimeter.paths import HARDWARE_DIR
from trimeter.sequences import lamp_monitor
from trimeter.sequences.plans import EXPOSURE_TARGET, NO_LIGHT_FRACTION, SATURATION_FRACTION, auto_expose
from trimeter.sequences.steps import Acquire, Expose, Plan, Runner
from trimeter.spectrometer.base import Spectrometer

if TYPE_CHECKING:
    from trimeter.device.client import Device, Value
    from trimeter.domain import Calibration

PASS, FAIL, SKIP = "pass", "fail", "skip"
# What a check finds: its status, a message saying what to fix, and the figures it judged by.
Outcome = tuple[str, str, dict]

FRAMES = 2                       # exposures averaged per spectrum
MIN_RISE_FRACTION = 0.05         # a working light raises the brightest bins by ≥ this much of full scale
MAX_SHUTTER_LEAK = 0.05          # a closed shutter lets through at most this share of its light
MIN_PANEL_BALANCE = 0.5          # the weaker diffuse panel gives at least this share of the stronger one's light
MIN_WHITE_OVER_BLACK = 2.0       # white background / black background, summed over the lit pixels
MAX_DARK_OFFSET_FRACTION = 0.25  # dark offset above this share of full scale eats the dynamic range
MAX_DARK_LIGHT_FRACTION = 0.01   # lights off: lit pixels at most this far (of full scale) above the masked ones
DARK_CHECK_US = 1_000_000        # long enough for stray light and dark current to show
NO_LIGHT_EXPOSURE_US = 1_000_000  # without light, LEDs are judged at this exposure rather than the longest
SLOT_TOLERANCE_MM = 0.1          # the firmware stops on the slot's step; more off means a move was cut short
MOVE_MARGIN_S = 2.0              # on top of twice the time a move or homing should take

PANELS = ("panel_left", "panel_right")
LIGHTS = PANELS + ("collimated",)
_LABEL = {"panel_left": "left panel", "panel_right": "right panel", "collimated": "collimated"}
_SETUP_LABEL = {"panels": "diffuse panels", "collimated": "collimated LED"}
_LEVEL = {"panel_left": "led_panels_level", "panel_right": "led_panels_level", "collimated": "led_collimated_level"}


@lru_cache(maxsize=1)
def _pinout() -> dict:
    try:
        with open(HARDWARE_DIR / "pinout.toml", "rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError):
        return {}


def pins(*signals: str) -> str:
    """'stepper_step PB0, …' from hardware/pinout.toml (the signal name alone where it is not declared)."""
    table = _pinout()
    out = []
    for signal in signals:
        pin = table.get(signal, {})
        out.append(f"{signal} P{pin['port']}{pin['pin']}" if "port" in pin and "pin" in pin else signal)
    return ", ".join(out)


STEPPER_PINS = ("stepper_step", "stepper_dir", "stepper_enable", "stepper_diag")


@dataclass
class CheckResult:
    name: str
    status: str          # pass | fail | skip
    message: str         # what was seen; on fail, what to fix; on skip, why it could not be judged
    figures: dict = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {"name": self.name, "status": self.status, "message": self.message,
                "figures": {k: _plain(v) for k, v in self.figures.items()}, "seconds": round(self.seconds, 3)}


def _plain(value: object) -> object:
    if isinstance(value, IntEnum):
        return value.name.lower()
    if isinstance(value, (np.floating, float)):
        return round(float(value), 6)
    if isinstance(value, np.integer):
        return int(value)
    return value


@dataclass
class SelfTestReport:
    checks: list[CheckResult]
    device: dict
    spectrometer: dict

    @property
    def passed(self) -> bool:
        return not any(c.status == FAIL for c in self.checks)

    def to_dict(self) -> dict:
        return {"passed": self.passed, "device": self.device, "spectrometer": self.spectrometer,
                "checks": [c.to_dict() for c in self.checks]}


def _outcome(status: str, message: str, **figures: object) -> Outcome:
    return status, message, figures


def _enum_name(code: object) -> str:
    return code.name.lower() if isinstance(code, IntEnum) else str(code)


def _spectrum_plan(integration_time_us: float, frames: int) -> Plan[tuple[int, np.ndarray]]:
    actual = yield Expose(integration_time_us)
    counts = yield Acquire(frames)
    return actual, counts


class _Bench:
    """The device and spectrometer under test, and what the checks so far have found."""

    def __init__(self, device: Device, spectrometer: Spectrometer, *, frames: int,
                 device_clock: Callable[[], float] | None, clock: Callable[[], float],
                 sleep: Callable[[float], None]) -> None:
        self.device, self.spectrometer, self.frames = device, spectrometer, frames
        self.device_clock, self.clock, self.sleep = device_clock, clock, sleep
        self.description = spectrometer.description
        n = len(np.asarray(spectrometer.wavelengths_nm()))
        self.lit = np.ones(n, dtype=bool)
        self.lit[[p for p in self.description.dark_pixels if 0 <= p < n]] = False
        self.masked = ~self.lit
        self.full = float(self.description.saturation_counts)
        self.config = {**device.config(), **device.read_many(*sorted(set(_LEVEL.values())))}
        self.homed = False
        self.reached: set[str] = set()
        self.exposure_us: dict[str, float] = {}    # per light set-up: "panels", "collimated"
        self.light_seen: dict[str, bool] = {}
        self._sources: dict[str, dict] = {}
        self._darks: dict[float, np.ndarray] = {}
        self.calibration: Calibration | None = None

    # ------------------------------------------------------------------------------- device
    def now(self) -> float:
        return self.device_clock() if self.device_clock is not None else self.clock()

    def wait_idle(self, timeout_s: float) -> tuple[bool, Value]:
        """Poll until not busy: returns (finished, fault code or None)."""
        deadline = self.clock() + timeout_s
        while True:
            busy, fault = self.device.read_many("busy", "fault").values()
            if fault:
                return True, self.device.read("fault_code")
            if not busy:
                return True, None
            if self.clock() >= deadline:
                return False, None
            self.sleep(0.01)

    def clear_fault(self) -> None:
        if self.device.read("fault"):
            self.device.command("clear_fault")

    def move_timeout_s(self) -> float:
        c = self.config
        travel_mm = max(c["slot_black_mm"], c["slot_white_mm"], c["slot_open_mm"])
        expected = (travel_mm / c["speed_mm_s"] + c["speed_mm_s"] / c["accel_mm_s2"]
                    + c["motion_settle_ms"] / 1000.0)
        return 2 * expected + MOVE_MARGIN_S

    def homing_timeout_s(self) -> float:
        c = self.config
        expected = (c["homing_timeout_ms"] / 1000.0 + c["homing_backoff_mm"] / c["homing_speed_mm_s"]
                    + c["motion_settle_ms"] / 1000.0)
        return 2 * expected + MOVE_MARGIN_S

    def lights(self, on: tuple[str, ...] = (), open_: tuple[str, ...] = ()) -> None:
        """LEDs `on` and shutters `open_` (names from LIGHTS), everything else off/closed: one request over
        every coil, so the set-up changes at once."""
        wanted = {**{f"led_{light}_on": light in on for light in LIGHTS},
                  **{f"shutter_{light}_open": light in open_ for light in LIGHTS}}
        if set(wanted) != set(regs.COILS):  # a coil this code does not know must not be switched blindly
            raise AssertionError("the register map's coils are no longer exactly the light coils")
        coils = [False] * regs.SPANS["coil"]
        for name, value in wanted.items():
            coils[regs.COILS[name].address] = value
        self.device.transport.write_bits(0, coils)
        finished, fault = self.wait_idle(self.move_timeout_s())
        if fault is not None:
            raise _CheckFailed(f"the device latched a {_enum_name(fault)} fault while switching lights")
        if not finished:
            raise _CheckFailed("the device stayed busy after switching lights and shutters (a shutter servo or "
                               "LED settle that never ends): check shutter_settle_ms and led_settle_ms")

    # -------------------------------------------------------------------------- spectrometer
    def spectrum(self, integration_time_us: float) -> np.ndarray:
        _, counts = Runner(self.device, self.spectrometer).run(_spectrum_plan(integration_time_us, self.frames))
        return np.asarray(counts, dtype=float)

    def auto_expose(self, start_us: float | None = None) -> tuple[float, float]:
        return Runner(self.device, self.spectrometer).run(auto_expose(start_us))

    def dark(self, integration_time_us: float) -> np.ndarray:
        if integration_time_us not in self._darks:
            self.lights()
            self._darks[integration_time_us] = self.spectrum(integration_time_us)
        return self._darks[integration_time_us]

    def peak(self, counts: np.ndarray) -> float:
        """The brightest lit bins (95th percentile, so one hot pixel does not count) as a fraction of full scale."""
        values = counts[self.lit]
        values = values[np.isfinite(values)]
        return float(np.percentile(values, 95)) / self.full if values.size else 0.0

    def source(self, light: str) -> dict:
        """The light's LED on / off (its shutter open) and on with its shutter closed, at its set-up's exposure."""
        if light not in self._sources:
            t = self.exposure_us["collimated" if light == "collimated" else "panels"]
            self.lights(on=(light,), open_=(light,))
            on = self.spectrum(t)
            self.lights(on=(), open_=(light,))
            off = self.spectrum(t)
            self.lights(on=(light,), open_=())
            closed = self.spectrum(t)
            self.lights()
            self._sources[light] = {"rise": self.peak(on - off), "leak": self.peak(closed - off),
                                    "integration_time_us": t}
        return self._sources[light]


Check = Callable[[_Bench], Outcome]


class _CheckFailed(Exception):
    """A check found a problem partway (its message says what to fix)."""


# ------------------------------------------------------------------------------------ checks
def check_device(bench: _Bench) -> Outcome:
    dev = bench.device
    identity = getattr(dev, "identity", None)
    version = ".".join(map(str, identity.firmware_version)) if identity else "?"
    source, fault, code = dev.read("config_source"), dev.read("fault"), dev.read("fault_code")
    notes = []
    if fault:
        dev.command("clear_fault")
        notes.append(f"a {_enum_name(code)} fault was latched at the start (cleared)")
    figures = {"firmware": version, "config_source": source, "fault_at_start": _enum_name(code) if fault else None}
    if source in (regs.ConfigSource.OTHER_REGISTER_MAP, regs.ConfigSource.REFUSED):
        return _outcome(FAIL, f"the saved configuration was ignored at boot ({_enum_name(source)}), so the defaults "
                              "run: restore a backup (`trimeter config import FILE --save`) or set the slots and "
                              "servo widths again and `trimeter config save`", **figures)
    message = f"firmware {version}, register map 0x{regs.REGMAP_HASH:08X}, configuration: {_enum_name(source)}"
    return _outcome(PASS, "; ".join([message, *notes]), **figures)


def check_homing(bench: _Bench) -> Outcome:
    dev, config = bench.device, bench.config
    bench.clear_fault()
    timeout_s = bench.homing_timeout_s()
    start = bench.now()
    dev.command("home")
    finished, fault = bench.wait_idle(timeout_s)
    elapsed = bench.now() - start
    figures = {"homing_s": elapsed, "timeout_s": timeout_s}
    if fault == regs.Fault.STALL:
        bench.clear_fault()
        return _outcome(FAIL, "the slider did not move while homing (stall): check the stepper motor and driver "
                              f"wiring ({pins(*STEPPER_PINS)}), the motor supply, and that the carriage runs freely",
                        **figures, fault="stall")
    if fault == regs.Fault.HOMING_TIMEOUT:
        bench.clear_fault()
        return _outcome(FAIL, f"the endstop did not trigger within homing_timeout_ms = {config['homing_timeout_ms']} "
                              f"ms: check the endstop switch and its wiring ({pins('endstop')}), that the motor turns "
                              f"towards it (homing_direction = {config['homing_direction']}), and homing_speed_mm_s",
                        **figures, fault="homing_timeout")
    if fault is not None:
        bench.clear_fault()
        return _outcome(FAIL, f"homing ended in a {_enum_name(fault)} fault: check the endstop ({pins('endstop')}) "
                              f"and the stepper wiring ({pins(*STEPPER_PINS)})", **figures, fault=_enum_name(fault))
    if not finished:
        dev.command("stop")
        return _outcome(FAIL, f"homing did not finish within {timeout_s:.1f} s: check the stepper wiring "
                              f"({pins(*STEPPER_PINS)}) and the endstop ({pins('endstop')})", **figures)
    homed, endstop, steps = dev.read_many("homed", "endstop", "position_steps").values()
    position_mm = steps / config["steps_per_mm"]
    figures.update(position_mm=position_mm)
    if not homed:
        return _outcome(FAIL, "homing finished without the homed flag: the firmware refused or abandoned it (read "
                              "`trimeter config get state` / the firmware log)", **figures)
    if endstop:
        return _outcome(FAIL, f"the endstop still reads active after the {config['homing_backoff_mm']:g} mm back-off: "
                              f"a switch stuck closed or wired active-high ({pins('endstop')})", **figures)
    bench.homed = True
    return _outcome(PASS, f"homed in {elapsed:.2f} s; endstop released after the back-off, slider at "
                          f"{position_mm:.2f} mm", **figures)


def _check_slot(slot: str) -> Check:
    def check(bench: _Bench) -> Outcome:
        dev, config = bench.device, bench.config
        target_mm = config[f"slot_{slot}_mm"]
        if not bench.homed:
            return _outcome(FAIL, f"the slider cannot go to the {slot} slot: it is not homed (fix homing first)",
                            target_mm=target_mm)
        timeout_s = bench.move_timeout_s()
        start = bench.now()
        dev.command("goto_slot", slot)
        finished, fault = bench.wait_idle(timeout_s)
        elapsed = bench.now() - start
        figures = {"move_s": elapsed, "target_mm": target_mm}
        if fault is not None:
            bench.clear_fault()
            bench.homed = bool(dev.read("homed"))
            return _outcome(FAIL, f"the slider stopped on the way to the {slot} slot with a {_enum_name(fault)} "
                                  f"fault: check the stepper wiring ({pins(*STEPPER_PINS)}), that nothing blocks the "
                                  "carriage, and speed_mm_s / accel_mm_s2 for the motor's torque", **figures,
                            fault=_enum_name(fault))
        if not finished:
            dev.command("stop")
            return _outcome(FAIL, f"the slider did not reach the {slot} slot within {timeout_s:.1f} s: check the "
                                  f"stepper wiring ({pins(*STEPPER_PINS)}) and the endstop ({pins('endstop')})",
                            **figures)
        at, steps = dev.read_many("position_slot", "position_steps").values()
        position_mm = steps / config["steps_per_mm"]
        figures.update(position_mm=position_mm, position_slot=at)
        if at != regs.Slot[slot.upper()] or abs(position_mm - target_mm) > SLOT_TOLERANCE_MM:
            return _outcome(FAIL, f"after the move to the {slot} slot the device reports slot "
                                  f"{_enum_name(at)} at {position_mm:.2f} mm, expected slot_{slot}_mm = "
                                  f"{target_mm:g} mm: a move was cut short (stop?) or the slot positions overlap",
                            **figures)
        bench.reached.add(slot)
        return _outcome(PASS, f"reached in {elapsed:.2f} s, at {position_mm:.2f} mm (slot_{slot}_mm {target_mm:g})",
                        **figures)
    return check


def check_dark_level(bench: _Bench) -> Outcome:
    lo, hi = bench.description.integration_time_us_limits
    long_us = float(min(max(DARK_CHECK_US, lo), hi))
    shortest = bench.dark(float(lo))
    longest = bench.dark(long_us)
    saturated = int(np.sum(longest >= SATURATION_FRACTION * bench.full))
    figures = {"integration_time_us": long_us, "saturated_bins": saturated}
    if saturated:
        return _outcome(FAIL, f"with every light off, {saturated} bins saturate at {long_us / 1e3:g} ms: light gets in "
                              "(close the lid, check the enclosure for leaks) or the spectrometer is faulty", **figures)
    if not bench.masked.any():
        offset = float(np.median(shortest[bench.lit])) / bench.full
        figures.update(offset_fraction=offset)
        if offset > MAX_DARK_OFFSET_FRACTION:
            return _outcome(FAIL, f"dark level {offset:.1%} of full scale at the shortest exposure leaves too little "
                                  "dynamic range: check the spectrometer's settings (gain, electrical dark)", **figures)
        return _outcome(PASS, f"dark level {offset:.1%} of full scale, nothing saturated; this spectrometer has no "
                              "masked pixels, so stray light with the lights off is NOT judged", **figures)
    offset = float(np.median(shortest[bench.masked])) / bench.full
    above = float(np.median(longest[bench.lit]) - np.median(longest[bench.masked])) / bench.full
    figures.update(offset_fraction=offset, lit_above_masked_fraction=above)
    if offset > MAX_DARK_OFFSET_FRACTION:
        return _outcome(FAIL, f"dark offset {offset:.1%} of full scale (masked pixels, shortest exposure) leaves too "
                              "little dynamic range: check the spectrometer's settings (gain, electrical dark)",
                        **figures)
    if above > MAX_DARK_LIGHT_FRACTION:
        return _outcome(FAIL, f"with every light off the lit pixels read {above:.1%} of full scale above the masked "
                              f"ones at {long_us / 1e3:g} ms: stray light reaches the spectrometer (close the lid, "
                              "check the enclosure), or an LED does not switch off", **figures)
    return _outcome(PASS, f"dark offset {offset:.1%} of full scale; lights off, the lit pixels stay within "
                          f"{abs(above):.2%} of the masked ones at {long_us / 1e3:g} ms; nothing saturated", **figures)


def _check_exposure(setup: str) -> Check:
    """Auto-exposure with all lights of a set-up on: it must converge, and nothing may saturate at its result."""
    lights = PANELS if setup == "panels" else ("collimated",)
    where = "white" if setup == "panels" else "open"
    level_name = "led_panels_level" if setup == "panels" else "led_collimated_level"

    def check(bench: _Bench) -> Outcome:
        if setup == "collimated" and where not in bench.reached:
            return _outcome(SKIP, "not judged: the collimated beam is seen only through the open slot, which the "
                                  "slider did not reach (see slot open)")
        lo, hi = bench.description.integration_time_us_limits
        bench.lights(on=lights, open_=lights)
        t, peak = bench.auto_expose()
        counts = bench.spectrum(t)
        saturated = int(np.sum(counts[bench.lit] >= SATURATION_FRACTION * bench.full))
        figures = {"integration_time_us": t, "peak_fraction": peak, "saturated_bins": saturated,
                   "at_slot": where if where in bench.reached else None}
        bench.lights()
        bench.light_seen[setup] = peak >= NO_LIGHT_FRACTION
        if not bench.light_seen[setup]:
            bench.exposure_us[setup] = float(min(t, max(NO_LIGHT_EXPOSURE_US, lo)))
            return _outcome(SKIP, f"not judged: no light at all from the {_SETUP_LABEL[setup]}, even at "
                                  f"{t / 1e3:.4g} ms (see the LED checks)", **figures)
        bench.exposure_us[setup] = float(t)
        if saturated and t <= lo:
            return _outcome(FAIL, f"the {_SETUP_LABEL[setup]} saturate {saturated} bins even at the spectrometer's "
                                  f"shortest exposure ({lo} µs): lower {level_name} (now "
                                  f"{bench.config[level_name]:g} of full drive)", **figures)
        if saturated:
            return _outcome(FAIL, f"{saturated} bins saturate at the integration time auto-exposure chose "
                                  f"({t / 1e3:.4g} ms): the light flickers between exposures (led_pwm_hz too close to "
                                  "the exposure rate?) or the spectrometer reports it wrongly", **figures)
        if t >= hi and peak < 0.5 * EXPOSURE_TARGET:
            return _outcome(FAIL, f"the {_SETUP_LABEL[setup]} light is too dim: at the longest exposure "
                                  f"({hi / 1e6:g} s) the brightest bins reach only {peak:.0%} of full scale: raise "
                                  f"{level_name} (now {bench.config[level_name]:g} of full drive), check the LED "
                                  "current and the optical path", **figures)
        if not 0.5 * EXPOSURE_TARGET <= peak < SATURATION_FRACTION:
            return _outcome(FAIL, f"auto-exposure did not converge (brightest bins at {peak:.0%} of full scale after "
                                  f"its last step, target {EXPOSURE_TARGET:.0%}): the light is unstable (loose LED "
                                  "connector, failing driver) or the spectrometer's counts do not scale with time",
                            **figures)
        return _outcome(PASS, f"auto-exposure: {t / 1e3:.4g} ms puts the brightest bin at {peak:.0%} of full scale; "
                              "nothing saturates", **figures)
    return check


def _check_name(kind: str, light: str) -> str:
    return f"{kind} {light.replace('_', ' ')}"


def _light_not_judged(bench: _Bench, light: str) -> Outcome | None:
    """Why `light` can't be judged with what the earlier checks reached (None: it can)."""
    if light == "collimated" and "open" not in bench.reached:
        return _outcome(SKIP, "not judged: the collimated beam is seen only through the open slot, which the "
                              "slider did not reach (see slot open)")
    setup = "collimated" if light == "collimated" else "panels"
    if setup not in bench.exposure_us:
        return _outcome(SKIP, f"not judged: no integration time was found for the {setup} light "
                              f"(see exposure {setup})")
    return None


def _check_led(light: str) -> Check:
    def check(bench: _Bench) -> Outcome:
        if skipped := _light_not_judged(bench, light):
            return skipped
        found = bench.source(light)
        rise = found["rise"]
        figures = {"rise_fraction": rise, "integration_time_us": found["integration_time_us"]}
        level = _LEVEL[light]
        if rise < MIN_RISE_FRACTION:
            return _outcome(FAIL, f"the {_LABEL[light]} LED does not light the spectrometer (signal rises by "
                                  f"{rise:.1%} of full scale when it switches on, needs {MIN_RISE_FRACTION:.0%}): "
                                  f"check the LED and its driver ({pins('led_' + light)}), {level} (now "
                                  f"{bench.config[level]:g} of full drive), and that its shutter opens "
                                  f"({pins('servo_' + light)})", **figures)
        if light in PANELS:
            other = PANELS[1 - PANELS.index(light)]
            other_rise = bench.source(other)["rise"]
            figures.update(balance=rise / other_rise if other_rise > 0 else float("inf"))
            if other_rise >= MIN_RISE_FRACTION and rise < MIN_PANEL_BALANCE * other_rise:
                return _outcome(FAIL, f"the {_LABEL[light]} gives only {rise / other_rise:.0%} of the "
                                      f"{_LABEL[other]}'s light: check its LED current and driver "
                                      f"({pins('led_' + light)}) and that its shutter opens fully "
                                      f"({pins('servo_' + light)}, servo_{light}_open_us)", **figures)
        return _outcome(PASS, f"switching the LED on raises the signal by {rise:.0%} of full scale", **figures)
    return check


def _check_shutter(light: str) -> Check:
    def check(bench: _Bench) -> Outcome:
        if skipped := _light_not_judged(bench, light):
            return skipped
        found = bench.source(light)
        figures = {"rise_fraction": found["rise"], "leak_fraction": found["leak"]}
        if found["rise"] < MIN_RISE_FRACTION:
            return _outcome(SKIP, f"not judged: no light from the {_LABEL[light]} LED to block (see "
                                  f"{_check_name('LED', light)}); a shutter stuck closed looks the same", **figures)
        leak = max(found["leak"] / found["rise"], 0.0)  # noise can make a perfect blade read slightly negative
        figures.update(transmitted_when_closed=leak)
        closed_us = bench.config[f"servo_{light}_closed_us"]
        if leak > MAX_SHUTTER_LEAK:
            return _outcome(FAIL, f"closed, the {_LABEL[light]} shutter still lets {leak:.0%} of the light through: "
                                  f"check its servo ({pins('servo_' + light)}) and servo_{light}_closed_us (now "
                                  f"{closed_us:g} µs), and that the blade is not bent or loose", **figures)
        return _outcome(PASS, f"closed, it blocks {1 - leak:.1%} of the light; open, it lets it through", **figures)
    return check


def check_backgrounds(bench: _Bench) -> Outcome:
    """White vs black under the panels: the slider really moved between them and the backgrounds are in place."""
    missing = [s for s in ("white", "black") if s not in bench.reached]
    if missing:
        return _outcome(SKIP, f"not judged: the slider did not reach the {' and '.join(missing)} slot "
                              f"(see slot {missing[0]})")
    if not bench.light_seen.get("panels"):
        return _outcome(SKIP, "not judged: no light from the panels to compare the backgrounds with (see exposure "
                              "panels and the LED checks)")
    t = bench.exposure_us["panels"]
    dark = bench.dark(t)
    signals, peaks = {}, {}
    for slot in ("black", "white"):
        bench.device.command("goto_slot", slot)
        finished, fault = bench.wait_idle(bench.move_timeout_s())
        if fault is not None or not finished:
            bench.clear_fault()
            return _outcome(FAIL, f"the slider did not return to the {slot} slot (see the slot checks): "
                                  f"check the stepper wiring ({pins(*STEPPER_PINS)})")
        bench.lights(on=PANELS, open_=PANELS)
        net = bench.spectrum(t) - dark
        signals[slot] = float(np.nansum(net[bench.lit]))
        peaks[slot] = bench.peak(net)
    bench.lights()
    ratio = max(signals["white"], 0.0) / max(signals["black"], 1.0)  # a perfectly black background reads ~0
    figures = {"white_over_black": ratio}
    if peaks["white"] < MIN_RISE_FRACTION and peaks["black"] < MIN_RISE_FRACTION:
        return _outcome(FAIL, f"under the panels neither background gives light (white {peaks['white']:.1%}, black "
                              f"{peaks['black']:.1%} of full scale) although the panels lit the spectrometer before: "
                              "the light path is blocked at the slots, or the panels went off", **figures)
    if ratio < 1 / MIN_WHITE_OVER_BLACK:
        return _outcome(FAIL, f"the black background is brighter than the white one (white/black {ratio:.2f}): the "
                              "backgrounds are swapped (or slot_black_mm / slot_white_mm are)", **figures)
    if ratio < MIN_WHITE_OVER_BLACK:
        return _outcome(FAIL, f"white is only {ratio:.2f}× brighter than black (needs {MIN_WHITE_OVER_BLACK:g}×): the "
                              "slider may not move although the firmware counts steps (check the belt/coupling), "
                              "or a background is missing or dirty", **figures)
    return _outcome(PASS, f"under the panels, white is {ratio:.1f}× brighter than black", **figures)


LAMP_LEVEL_BOUND = 0.2   # a lamp's light off its calibrated level by more than this fails (an aged or overdriven LED)


def check_lamps_against_calibration(bench: _Bench) -> Outcome:
    """Each lamp's light on its lamp-monitor photodiode (LEDs on, only its shutter open) as a fraction of what
    the last calibration recorded: a lamp far from it makes every measurement against that calibration wrong."""
    calibration = bench.calibration
    if calibration is None:
        return _outcome(SKIP, "not judged: this host has no calibration to compare the lamps with (calibrate, then "
                              "run the selftest again)")
    references = lamp_monitor.references(calibration.lamp_monitor or {})
    if set(references) != set(LIGHTS):
        return _outcome(SKIP, "not judged: the last calibration holds no lamp-monitor readings of every lamp "
                              "(calibrate again)")
    figures: dict[str, object] = {}
    wrong = []
    for light in LIGHTS:
        bench.lights(on=LIGHTS, open_=(light,))
        reading = float(bench.device.read(f"lamp_monitor_{light}"))
        dark, lit = references[light]
        level = (reading - dark) / max(lit - dark, 1.0)
        figures[f"{light}_level"] = level
        if abs(level - 1.0) > LAMP_LEVEL_BOUND:
            wrong.append(f"the {_LABEL[light]} gives {level:.0%} of its calibrated light")
    bench.lights()
    figures["calibration_utc"] = calibration.created_utc
    if wrong:
        return _outcome(FAIL, "; ".join(wrong) + f" (bound ±{LAMP_LEVEL_BOUND:.0%}, calibration of "
                              f"{calibration.created_utc}): check the LED currents and levels, then calibrate again",
                        **figures)
    return _outcome(PASS, f"every lamp within ±{LAMP_LEVEL_BOUND:.0%} of its light at the calibration of "
                          f"{calibration.created_utc}", **figures)


CHECKS: tuple[tuple[str, Check], ...] = (
    ("device", check_device),
    ("homing", check_homing),
    ("slot white", _check_slot("white")),
    ("dark level", check_dark_level),
    ("exposure panels", _check_exposure("panels")),
    ("LED panel left", _check_led("panel_left")),
    ("LED panel right", _check_led("panel_right")),
    ("shutter panel left", _check_shutter("panel_left")),
    ("shutter panel right", _check_shutter("panel_right")),
    ("slot black", _check_slot("black")),
    ("backgrounds", check_backgrounds),
    ("slot open", _check_slot("open")),
    ("exposure collimated", _check_exposure("collimated")),
    ("LED collimated", _check_led("collimated")),
    ("shutter collimated", _check_shutter("collimated")),
    ("lamps vs calibration", check_lamps_against_calibration),
)


def run_selftest(device: Device, spectrometer: Spectrometer, *, frames: int = FRAMES,
                 device_clock: Callable[[], float] | None = None, calibration: Calibration | None = None,
                 on_result: Callable[[CheckResult, int, int], None] | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep
                 ) -> SelfTestReport:
    """Run every check in CHECKS against an open Device and Spectrometer; never raises for what it finds.

    `device_clock`: the device's own seconds (the twin's simulated clock) for the times reported;
    without it, wall time. `calibration`: the host's last, which the lamps are checked against (None: that
    check says there is none). `on_result(result, index, total)` is called as each check finishes."""
    bench = _Bench(device, spectrometer, frames=frames, device_clock=device_clock, clock=clock, sleep=sleep)
    bench.calibration = calibration
    pattern = device.read("status_pattern")
    device.write("status_pattern", "fast_blink")
    results = []
    uptime = device.read("uptime_s")
    try:
        for index, (name, check) in enumerate(CHECKS):
            started = clock()
            try:
                status, message, figures = check(bench)
            except _CheckFailed as exc:
                status, message, figures = FAIL, str(exc), {}
            except (TrimeterError, OSError) as exc:
                status, message, figures = FAIL, f"could not finish: {exc}", {}
            now_uptime = _uptime_or_none(device)
            if now_uptime is not None and now_uptime < uptime:
                status, message = FAIL, (f"the device reset during this check (uptime {uptime} → {now_uptime} s): "
                                         "check its supply (a brown-out when the motor or LEDs switch on?); "
                                         f"{message}")
                bench.homed = False
                bench.reached.clear()
            uptime = now_uptime if now_uptime is not None else uptime
            result = CheckResult(name, status, message, figures, clock() - started)
            results.append(result)
            if on_result is not None:
                on_result(result, index, len(CHECKS))
    finally:
        _leave_safe(device, pattern)
    identity = getattr(device, "identity", None)
    device_info = {"firmware": ".".join(map(str, identity.firmware_version)) if identity else None,
                   "regmap_hash": f"0x{regs.REGMAP_HASH:08X}"}
    d = bench.description
    spectrometer_info = {"model": d.model, "serial": d.serial, "pixels": d.pixels,
                         "wavelength_range_nm": [round(float(x), 2) for x in d.wavelength_range_nm],
                         "integration_time_us_limits": list(d.integration_time_us_limits),
                         "saturation_counts": d.saturation_counts, "masked_pixels": len(d.dark_pixels)}
    return SelfTestReport(results, device_info, spectrometer_info)


def _uptime_or_none(device: Device) -> int | None:
    try:
        return device.read("uptime_s")
    except TrimeterError:
        return None


def _leave_safe(device: Device, pattern: object) -> None:
    """Lights off and shutters closed, the status LED as it was; best effort (the device may be gone)."""
    try:
        for name in regs.COILS:
            device.write(name, False)
        device.write("status_pattern", pattern)
    except TrimeterError:
        pass
