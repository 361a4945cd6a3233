"""The measurement plans (paper Sec. 4.2) as generators of steps (trimeter.sequences.steps).

- `warm_up`: lamps on, white background, spectra every `interval_s` until the relative change between
  two consecutive spectra is under `threshold` — not a fixed wait; a timeout names the drift left.
- `calibration`: the three references *without a sample*: white → diffuse spectrum = white / ρ_white_ref;
  black → ρ_black(λ) = black / diffuse; open slot + collimated LED → collimated spectrum.
- `holder_check`: a quick capture of the three references before a calibration, to refuse a sample in the
  holder (trimeter.sequences.checks) before the warm-up.
- `sample_capture`: the sample against black, white and the collimated beam (HDR across decades for I_c).
Every capture: auto-exposure, `frames` averaged exposures, dark frames at every integration time used
(all shutters closed), rates in counts/s. Bins that saturate at every exposure, or read NaN, become NaN
(and are flagged downstream) — never an exception.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from trimeter.domain import Calibration, Capture, RawSample
from trimeter.spectrometer.base import SpectrometerDescription
from trimeter.errors import CheckError, DeviceError
from trimeter.sequences import lamp_monitor
from trimeter.sequences.steps import (Acquire, Describe, DeviceTime, Expose, LampMonitor, Lights, Move, Progress,
                                      Plan, Status, Wait)

SATURATION_FRACTION = 0.98   # a bin above this fraction of full scale counts as saturated
EXPOSURE_TARGET = 0.7        # auto-exposure aims the brightest bin at this fraction of full scale
NO_LIGHT_FRACTION = 0.003    # brightest bin under this fraction of full scale at the longest exposure: no light


def _lit_bins(description: SpectrometerDescription, n: int) -> np.ndarray:
    lit = np.ones(n, dtype=bool)
    lit[[p for p in description.dark_pixels if 0 <= p < n]] = False
    return lit


def _offset(counts: np.ndarray, description: SpectrometerDescription) -> float:
    """Dark-offset estimate of one frame from the masked pixels, for exposure control only (the rates use
    real dark frames). Without masked pixels: 0, i.e. the offset counts as signal (conservative)."""
    dark = [p for p in description.dark_pixels if 0 <= p < len(counts)]
    value = float(np.nanmedian(counts[dark])) if dark else 0.0
    return value if np.isfinite(value) else 0.0


def auto_expose(start_us: float | None = None, *, target: float = EXPOSURE_TARGET,
                max_iterations: int = 10) -> Plan[tuple[float, float]]:
    """Find the integration time that puts the brightest lit bin at `target` of full scale (its maximum,
    not a percentile: a bin that saturates in every frame is lost, so none may).
    Returns (integration_time_us, peak_fraction) — peak_fraction ≈ 0 means there is no light."""
    description, wavelengths = yield Describe()
    lo, hi = description.integration_time_us_limits
    full = float(description.saturation_counts)
    lit = _lit_bins(description, len(wavelengths))
    t = float(start_us or min(max(10_000, lo), hi))
    peak_fraction = 0.0
    for _ in range(max_iterations):
        t = yield Expose(t)
        counts = yield Acquire()
        offset = _offset(counts, description)
        light = counts[lit]
        light = light[np.isfinite(light)]
        if light.size == 0:
            return t, 0.0
        headroom = max(full - offset, 1.0)
        peak = float(np.max(light)) - offset
        peak_fraction = peak / headroom
        if np.max(light) >= SATURATION_FRACTION * full:
            wanted = t * 0.25  # how far over full scale is unknown
        elif peak <= 0:
            wanted = t * 100
        else:
            wanted = t * target / peak_fraction
        wanted = min(max(wanted, lo), hi)
        if abs(wanted / t - 1) < 0.2 or wanted == t:
            return t, peak_fraction
        t = wanted
    return t, peak_fraction


def capture(slot: str, *, panels: bool = False, collimated: bool = False, frames: int = 2, hdr_decades: int = 0,
            start_us: float | None = None) -> Plan[tuple[dict, float, dict]]:
    """One set-up: move, light, auto-expose, then `frames` exposures at t, 10t, … (HDR decades).
    Returns {integration_time_us: mean counts}, the auto-exposure's peak fraction and the lamp monitor's
    record (read once the shutters settled and again after the last exposure)."""
    yield Move(slot)
    yield Lights(panels=panels, collimated=collimated)
    monitor = [(yield LampMonitor())]
    description, _ = yield Describe()
    t, peak = yield from auto_expose(start_us)
    times = [t]
    hi = description.integration_time_us_limits[1]
    for decade in range(1, hdr_decades + 1):
        longer = min(t * 10 ** decade, hi)
        if longer > times[-1]:
            times.append(longer)
    signals = {}
    for wanted in times:
        actual = yield Expose(wanted)
        signals[actual] = yield Acquire(frames, spread=True)
    monitor.append((yield LampMonitor()))
    return signals, peak, lamp_monitor.record(panels, collimated, monitor)


def dark_frames(times: list[float], *, frames: int = 2) -> Plan[dict]:
    """All shutters closed; one averaged dark frame per integration time used."""
    yield Lights(panels=False, collimated=False)
    darks = {}
    for wanted in sorted(set(times)):
        actual = yield Expose(wanted)
        # `times` are integration times the spectrometer already granted for the signals; a dark
        # at any other time would be subtracted from the wrong exposure
        if not abs(actual - wanted) <= 1e-9 * max(abs(wanted), 1.0):
            raise DeviceError(f"the spectrometer set {actual:g} µs for a dark frame at {wanted:g} µs, an "
                              f"integration time it had granted before; the darks would not match the signals")
        darks[wanted] = yield Acquire(frames, spread=True)
    return darks


def combine(signals: dict, darks: dict, saturation_counts: float, lit: np.ndarray) -> Capture:
    """HDR merge: rate = Σ(S − D) / Σ t over every exposure in which the bin did not saturate; its
    standard error from the frame-to-frame spread of S and D. `signals`/`darks`: t → (mean, sem)."""
    times = sorted(signals)
    signal = np.stack([signals[t][0][lit] for t in times])
    signal_sem = np.stack([signals[t][1][lit] for t in times])
    dark = np.stack([darks[t][0][lit] for t in times])
    dark_sem = np.stack([darks[t][1][lit] for t in times])
    seconds = np.asarray(times, float)[:, None] * 1e-6
    usable = np.isfinite(signal) & np.isfinite(dark) & (signal < SATURATION_FRACTION * saturation_counts)
    net = np.where(usable, signal - dark, 0.0).sum(axis=0)
    variance = np.where(usable, signal_sem ** 2 + dark_sem ** 2, 0.0).sum(axis=0)
    exposure = np.where(usable, seconds, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(exposure > 0, net / exposure, np.nan)
        rate_std = np.where(exposure > 0, np.sqrt(variance) / exposure, np.nan)
    saturated = ~usable.any(axis=0) & np.isfinite(signal).any(axis=0)
    return Capture(rate=rate, saturated=saturated, integration_times_us=np.asarray(times, float),
                   signals=signal, darks=dark, rate_std=rate_std)


def _light_seen(capture: Capture, saturation_counts: float) -> bool:
    """Dark-subtracted brightest bin at the longest exposure: (almost) nothing means no light."""
    net = capture.signals[-1] - capture.darks[-1]
    net = net[np.isfinite(net)]
    return net.size > 0 and float(np.max(net)) >= NO_LIGHT_FRACTION * saturation_counts


def _check_light(capture: Capture, saturation_counts: float, what: str) -> None:
    if not _light_seen(capture, saturation_counts):
        raise DeviceError(f"no light from the {what} at the longest exposure (lamp failure, or a shutter stuck "
                          "closed?); nothing was measured")


def _captures(setups: Sequence[tuple[str, str, bool, bool, int, str | None]], frames: int, progress_from: float,
              progress_to: float, label: str
              ) -> Plan[tuple[dict[str, Capture], np.ndarray, SpectrometerDescription, dict[str, Any]]]:
    description, wavelengths = yield Describe()
    lit = _lit_bins(description, len(wavelengths))
    raw, peaks, monitors = {}, {}, {}
    for i, (key, slot, panels, collimated, hdr, _what) in enumerate(setups):
        yield Progress(progress_from + (progress_to - progress_from) * i / (len(setups) + 1),
                       f"{label}: {key} ({slot} slot)")
        raw[key], peaks[key], monitors[key] = yield from capture(slot, panels=panels, collimated=collimated,
                                                                 frames=frames, hdr_decades=hdr)
    yield Progress(progress_from + (progress_to - progress_from) * len(setups) / (len(setups) + 1),
                   f"{label}: dark frames")
    darks = yield from dark_frames([t for signals in raw.values() for t in signals], frames=frames)
    # every shutter closed, the LEDs still on: each photodiode's closed reading
    monitors["dark"] = lamp_monitor.record(False, False, [(yield LampMonitor())])
    out = {key: combine(raw[key], darks, description.saturation_counts, lit) for key in raw}
    for key in raw:
        out[key].lamp_monitor = monitors[key]
    for key, _, _, _, _, what in setups:
        if what:
            _check_light(out[key], description.saturation_counts, what)
    return out, wavelengths[lit], description, monitors


def calibration(*, white_reference_reflectance: float, frames: int = 2) -> Plan[Calibration]:
    """Paper Sec. 4.2, without a sample: returns a Calibration."""
    if not 0 < white_reference_reflectance <= 1:
        raise DeviceError(f"white reference reflectance must be in (0, 1], got {white_reference_reflectance}")
    yield Status("fast_blink")
    setups = [("white", "white", True, False, 0, "diffuse LED panels"),
              ("black", "black", True, False, 0, None),
              ("collimated", "open", False, True, 0, "collimated LED")]
    captures, wavelengths, description, monitors = yield from _captures(setups, frames, 0.0, 1.0, "calibration")
    device_time = yield DeviceTime()
    yield Progress(1.0, "calibration done")
    return Calibration.from_captures(wavelengths, captures, white_reference_reflectance=white_reference_reflectance,
                                     device_time_s=device_time, spectrometer=description.to_dict(),
                                     lamp_monitor=monitors)


def holder_check(*, white_reference_reflectance: float, frames: int = 1) -> Plan[Calibration]:
    """A quick look at the three references before a calibration (lamps possibly still cold): returns a
    provisional Calibration for checks.calibration_problems. A reference without light is a CheckError
    here, not a lamp failure: a sample or anything else in the holder may be what blocks it."""
    setups = [("white", "white", True, False, 0, None),
              ("black", "black", True, False, 0, None),
              ("collimated", "open", False, True, 0, None)]
    captures, wavelengths, description, monitors = yield from _captures(setups, frames, 0.0, 1.0, "holder check")
    if not _light_seen(captures["white"], description.saturation_counts):
        raise CheckError("no light from the diffuse panels on the white slot: something opaque covers the holder, "
                         "a panel lamp failed or its shutter stuck closed")
    if not _light_seen(captures["collimated"], description.saturation_counts):
        raise CheckError("no light through the open slot: a sample in the holder blocks the collimated beam — "
                         "remove it (if the holder is empty: the collimated LED or its shutter failed)")
    device_time = yield DeviceTime()
    return Calibration.from_captures(wavelengths, captures, white_reference_reflectance=white_reference_reflectance,
                                     device_time_s=device_time, spectrometer=description.to_dict(),
                                     lamp_monitor=monitors)


def sample_capture(*, frames: int = 2, hdr_decades: int = 2, label: str = "sample") -> Plan[RawSample]:
    """The sample against black, white and the collimated beam: returns a RawSample (rates, counts/s)."""
    yield Status("fast_blink")
    setups = [("black", "black", True, False, 0, None),
              ("white", "white", True, False, 0, None),
              ("collimated", "open", False, True, hdr_decades, None)]
    captures, wavelengths, _, monitors = yield from _captures(setups, frames, 0.0, 1.0, label)
    device_time = yield DeviceTime()
    return RawSample(wavelengths_nm=wavelengths, black=captures["black"], white=captures["white"],
                     collimated=captures["collimated"], device_time_s=device_time, lamp_monitor=monitors)


@dataclass(frozen=True)
class WarmUpResult:
    drift: float            # relative change between the last two spectra
    elapsed_s: float        # device seconds the warm-up took
    spectra: int


def warm_up(*, threshold: float = 0.002, interval_s: float = 10.0, timeout_s: float = 900.0,
            frames: int = 2) -> Plan[WarmUpResult]:
    """Lamps on, white background; stop when two spectra `interval_s` apart differ by < `threshold`."""
    yield Status("slow_blink")
    yield Move("white")
    yield Lights(panels=True, collimated=False)
    description, wavelengths = yield Describe()
    t, _ = yield from auto_expose()
    lit = _lit_bins(description, len(wavelengths))
    yield Lights(panels=False, collimated=False)
    yield Expose(t)
    dark = (yield Acquire(frames))[lit]
    yield Lights(panels=True, collimated=False)
    start = yield DeviceTime()
    previous, count, drift = None, 0, float("inf")
    while True:
        yield Expose(t)
        current = (yield Acquire(frames))[lit] - dark
        count += 1
        if count == 1 and not np.nanmax(current, initial=0.0) >= NO_LIGHT_FRACTION * description.saturation_counts:
            raise DeviceError("no light from the diffuse LED panels at the longest exposure (lamp failure, or a "
                              "shutter stuck closed?); nothing was measured")
        now = yield DeviceTime()
        if previous is not None:
            bright = (previous > 0.1 * description.saturation_counts) & (current < SATURATION_FRACTION *
                                                                         description.saturation_counts)
            if bright.sum() < 3:
                raise DeviceError("warm-up: too few well-exposed bins to judge the lamp drift")
            drift = float(abs(np.median(current[bright] / previous[bright]) - 1.0))
            yield Progress(min(0.99, threshold / max(drift, 1e-12)), f"warm-up: drift {drift:.2%} per {interval_s:g} s")
            if drift < threshold:
                return WarmUpResult(drift, now - start, count)
        # not before two spectra: a first one that came after the limit (a slow link) says nothing of the lamps
        if count >= 2 and now - start >= timeout_s:
            raise DeviceError(f"lamps did not stabilise within {timeout_s:g} s (drift {drift:.2%} per "
                              f"{interval_s:g} s, threshold {threshold:.2%}): check the LEDs")
        previous = current
        yield Wait(interval_s)
