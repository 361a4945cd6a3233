"""Calibrating once, as a plain function: holder check, warm-up, the three references, checks, save.
Service.calibrate (the press-button service, and `trimeter calibrate` through it) wraps it with the LED,
its events and the device's lamps; tests call it directly."""

from __future__ import annotations

from collections.abc import Callable

from trimeter.domain import Calibration, InstrumentInfo
from trimeter.errors import CheckError, TrimeterError
from trimeter.sequences.checks import calibration_problems
from trimeter.sequences.plans import WarmUpResult, holder_check, warm_up
from trimeter.sequences.plans import calibration as calibration_plan
from trimeter.sequences.settings import HostSettings
from trimeter.sequences.steps import Runner


def previous_calibration(settings: HostSettings) -> Calibration | None:
    """The last good calibration on disk (every saved one passed its checks), or None."""
    try:
        return Calibration.load(settings.calibration_path)
    except TrimeterError:
        return None


def calibrate(runner: Runner, settings: HostSettings, *, instrument: InstrumentInfo | None, warm: bool = True,
              force: bool = False, on_warmed_up: Callable[[WarmUpResult], None] = lambda result: None
              ) -> Calibration:
    """Holder check, warm-up, calibration, checks, save (the lamps must be on). CheckError (nothing saved)
    when the holder is not empty, the slots are swapped or the result is implausible. `force` accepts a
    calibration that disagrees with the previous good one (a replaced lamp); the physical bounds still apply."""
    previous = None if force else previous_calibration(settings)
    quick = runner.run(holder_check(white_reference_reflectance=settings.white_reference))
    quick.device = instrument
    if problems := calibration_problems(quick, previous):
        raise CheckError("the holder does not look empty, nothing was calibrated: " + "; ".join(problems))
    if warm:
        on_warmed_up(runner.run(warm_up(threshold=settings.warmup_threshold, interval_s=settings.warmup_interval_s,
                                        timeout_s=settings.warmup_timeout_s, frames=settings.frames)))
    cal = runner.run(calibration_plan(white_reference_reflectance=settings.white_reference, frames=settings.frames))
    cal.device = instrument
    if problems := calibration_problems(cal, previous):
        raise CheckError("calibration refused, the previous one is kept: " + "; ".join(problems))
    cal.save(settings.calibration_path)
    return cal
