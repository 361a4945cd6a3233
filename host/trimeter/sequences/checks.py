"""What keeps garbage from being reported as a measurement: checks on a calibration before it is saved
or used, and on every shot before it is fitted and written. Each check returns what it saw, in words a
person can act on (empty: nothing wrong); the callers refuse with a CheckError.

Calibration (paper Sec. 4.2: the three references with the holder empty), vectorised over bins:
- physical bounds: the black background's ρ_black is small (black paint: ~0.03 in the visible, rising
  in the NIR) and below the white reference. A sample in the holder raises it to the sample's own
  I_b/I_w ratio; slots swapped put it far above ρ_white. Both lamps light most bins; the dark frames
  (every shutter closed) are dark.
- agreement with the previous good calibration of the same spectrometer and instrument: lamps and
  backgrounds change slowly, while a sample in the holder dims and colours both lamp spectra and raises
  ρ_black. A replaced lamp is accepted explicitly (`trimeter calibrate --force`).
The same checks run on a quick capture before any calibration (`plans.holder_check`), so a sample in
the holder is refused before the warm-up, with what was seen.

Shot (the sample is in every light path, so nothing is sample-independent; what is checked is that
the triple is physically possible), per bin, refused when a problem concerns more than
BAD_BIN_FRACTION of the usable bins:
- I_w under half the map's floor (its lowest I_w over the whole gamut: the sample surface's own
  reflection): no sample reflects less than its surface, so the diffuse panels gave (almost) no light;
- I_b above I_w beyond noise: no passive sample is brighter on black than on white;
- I_c above the calibrated beam: a sample transmits less than the open slot;
- after the fit: no material of the map explains the triple (NOT_CONVERGED).
A genuinely black or opaque sample passes all four (its I_w sits at the floor, I_c near 0 is allowed).

The lamps themselves, which nothing in a shot's spectra can judge (a panel dimmed to 80 % reads as a darker
sample), are watched by the lamp monitor (trimeter.sequences.lamp_monitor): its photodiodes see each lamp
past its shutter, never through the sample; every shot's readings against the calibration's refuse a lamp off
by more than ±3 %, a dead one, or a shutter that did not move. The calibration's own readings must show each
photodiode lit through its open shutter and dark behind the closed one.
"""

from __future__ import annotations


import numpy as np
from numpy.typing import ArrayLike

from trimeter import registers as regs
from trimeter.domain.measurement import BackgroundCoefficients
from trimeter.domain import Calibration, Reflectances
from trimeter.inversion.flags import FitFlag
from trimeter.model.response import background_response
from trimeter.sequences import lamp_monitor

# shared with the device's own calibration press (hardware/registers.toml, enums.standalone_holder)
RHO_BLACK_MAX = regs.StandaloneHolder.RHO_BLACK_MAX_PERMILLE / 1000  # median ρ_black of an empty holder
# median |Δρ_black| against the previous good calibration
RHO_BLACK_AGREEMENT = regs.StandaloneHolder.RHO_BLACK_AGREEMENT_PERMILLE / 1000
LAMP_LEVEL_BOUND = 0.25       # lamp spectrum against the previous one: median ratio within 1 ± this
LAMP_SHAPE_BOUND = 0.15       # … and its 10-90 % spread relative to the median (a coloured sample)
MIN_LIT_FRACTION = regs.StandaloneHolder.MIN_LIT_PERMILLE / 1000  # bins with light from both lamps, at least
DARK_LEVEL_MAX = 0.2          # median dark frame above this fraction of full scale: light leak / bad sensor
FLOOR_FRACTION = 0.5          # I_w under this fraction of the map's floor: the panels gave no light
BLACK_ABOVE_WHITE_TOLERANCE = 0.02   # relative, on top of 3 standard errors
BEAM_MAX = 1.1                # I_c above this (plus 3 standard errors): more beam than calibrated
BAD_BIN_FRACTION = 0.25       # a per-bin problem in more than this fraction of usable bins refuses the shot
GAMUT_BAD_FRACTION = 0.5      # bins the fit could not place in the map


def _median(values: ArrayLike) -> float:
    array = np.asarray(values, dtype=float)
    finite = array[np.isfinite(array)]
    return float(np.median(finite)) if finite.size else float("nan")


def comparable(calibration: Calibration, previous: Calibration | None) -> str | None:
    """Why `previous` cannot serve as the reference for `calibration` (None: it can)."""
    if previous is None:
        return "there is no previous calibration"
    if len(previous.wavelengths_nm) != len(calibration.wavelengths_nm) or not np.allclose(
            previous.wavelengths_nm, calibration.wavelengths_nm, rtol=0, atol=1e-3):
        return "the previous calibration has other wavelengths"
    for key in ("model", "serial"):
        if previous.spectrometer.get(key) != calibration.spectrometer.get(key):
            return "the previous calibration was taken with another spectrometer"
    if previous.device and calibration.device and not previous.device.same_model(calibration.device):
        return "the previous calibration was taken on another instrument"
    return None


def calibration_problems(calibration: Calibration, previous: Calibration | None = None) -> list[str]:
    """Physical bounds, and agreement with `previous` (a good calibration of the same set-up) if given."""
    cal = calibration
    usable = (cal.flags == 0) & np.isfinite(cal.rho_black)
    n = len(cal.flags)
    if usable.sum() < MIN_LIT_FRACTION * n:
        return [f"only {int(usable.sum())} of {n} bins have usable light from both lamps (expected ≥ "
                f"{MIN_LIT_FRACTION:.0%}): a lamp, a shutter or the spectrometer failed"]
    problems = []
    rho = _median(cal.rho_black[usable])
    if rho >= cal.rho_white:
        problems.append(f"ρ_black {rho:.3g} is above the white reference's {cal.rho_white:g}: the black and white "
                        f"slots seem swapped (or the white reference is missing) — check the slider's backgrounds")
    elif rho > RHO_BLACK_MAX:
        problems.append(f"ρ_black {rho:.2f} (expected ≤ {RHO_BLACK_MAX:g}): a sample seems to be in the holder "
                        f"— remove it")
    elif rho < -RHO_BLACK_AGREEMENT:
        problems.append(f"ρ_black {rho:.3f} is negative: the dark frames are brighter than the black background "
                        f"(light reaching the detector with the shutters closed?)")
    full_scale = cal.spectrometer.get("saturation_counts")
    if isinstance(full_scale, (int, float)) and full_scale > 0 and cal.dark_counts > DARK_LEVEL_MAX * full_scale:
        problems.append(f"the dark frames read {cal.dark_counts:.0f} counts ({cal.dark_counts / full_scale:.0%} of "
                        f"full scale, expected ≤ {DARK_LEVEL_MAX:.0%}) with every shutter closed: light leaks in "
                        f"or the spectrometer is faulty")
    problems += lamp_monitor.calibration_problems(cal.lamp_monitor)
    if previous is not None and comparable(cal, previous) is None:
        problems += agreement_problems(cal, previous)
    return problems


def agreement_problems(calibration: Calibration, previous: Calibration) -> list[str]:
    """Lamp spectra (level, shape) and ρ_black against the previous good calibration."""
    both = (calibration.flags == 0) & (previous.flags == 0)
    since = f"the previous good calibration ({previous.created_utc or 'undated'})"
    problems = []
    for what, new, old in (("panels' diffuse light", calibration.diffuse, previous.diffuse),
                           ("collimated beam", calibration.collimated, previous.collimated)):
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = new[both] / old[both]
        ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
        if ratio.size < 3:
            continue
        level = float(np.median(ratio))
        spread = float(np.percentile(ratio, 90) - np.percentile(ratio, 10)) / level
        if abs(level - 1.0) > LAMP_LEVEL_BOUND:
            problems.append(f"the {what} is {level - 1:+.0%} against {since} (bound ±{LAMP_LEVEL_BOUND:.0%}): a "
                            f"sample in the holder, or a changed lamp (then `trimeter calibrate --force` accepts it)")
        elif spread > LAMP_SHAPE_BOUND:
            problems.append(f"the {what} changed the shape of its spectrum against {since} (spread {spread:.0%}, bound "
                            f"{LAMP_SHAPE_BOUND:.0%}): a coloured sample in the holder, or a changed lamp (then "
                            f"`trimeter calibrate --force` accepts it)")
    delta = _median(np.abs(calibration.rho_black - previous.rho_black)[both])
    if delta > RHO_BLACK_AGREEMENT:
        problems.append(f"ρ_black {_median(calibration.rho_black[both]):.3f} against "
                        f"{_median(previous.rho_black[both]):.3f} in {since} (median change {delta:.3f}, bound "
                        f"{RHO_BLACK_AGREEMENT:g}): something is in the holder or on the black background")
    return problems


# ------------------------------------------------------------------------------------------ shots
def surface_floor(amap: BackgroundCoefficients, rho_white: float) -> float:
    """The lowest I_w any material of the map gives against a white background of `rho_white`: the
    light the sample's front surface reflects whatever lies behind it."""
    return float(np.nanmin(background_response(amap.A, amap.B, amap.C, rho_white)))


def usable_bins(refl: Reflectances) -> np.ndarray:
    """Bins with a finite triple and no capture flag: the ones the checks judge."""
    return (refl.flags == 0) & np.isfinite(refl.I_b) & np.isfinite(refl.I_w) & np.isfinite(refl.I_c)


def _std(value: ArrayLike | None) -> np.ndarray | float:
    return 0.0 if value is None else np.nan_to_num(np.asarray(value, dtype=float), nan=0.0)


def shot_problems(refl: Reflectances, amap: BackgroundCoefficients) -> list[str]:
    """Were the lamps as calibrated (lamp monitor), and is this triple physically possible for any sample,
    given the calibration and the map?"""
    lamps = lamp_monitor.shot_problems(refl.lamp_light)
    usable = usable_bins(refl)
    n = int(usable.sum())
    if n == 0:
        return lamps + ["no bin has a usable I_b, I_w, I_c (every bin saturated, non-finite or without reference "
                        "light)"]
    floor = surface_floor(amap, float(np.nanmin(refl.rho_w)))
    sb, sw, sc = _std(refl.I_b_std), _std(refl.I_w_std), _std(refl.I_c_std)
    with np.errstate(invalid="ignore"):
        checks = (
            (refl.I_w + 3 * sw < FLOOR_FRACTION * floor,
             f"I_w is under half the sample surface's own reflection (the map's floor {floor:.3f})",
             "the diffuse panels gave (almost) no light during the capture (a failed panel lamp or a panel "
             "shutter that did not open), or light reached the dark frames (a shutter that did not close)"),
            (refl.I_b - refl.I_w > BLACK_ABOVE_WHITE_TOLERANCE * refl.I_w + 3 * np.hypot(sb, sw),
             "I_b is above I_w (no sample is brighter on black than on white)",
             "the panel light changed between the black and white captures, or the slider stopped at the "
             "wrong slot"),
            (refl.I_c - 3 * sc > BEAM_MAX,
             f"I_c is above the calibrated beam (more than {BEAM_MAX:g})",
             "the collimated beam is brighter than at the calibration, or panel light leaks into the open slot; "
             "calibrate again with the holder empty"),
        )
    problems = lamps
    for bad, seen, cause in checks:
        k = int(np.count_nonzero(bad & usable))
        if k > BAD_BIN_FRACTION * n:
            # The lamp monitor sees each lamp and shutter directly and names it; a guess from the spectra
            # would point elsewhere (a collimated shutter stuck open lights the dark frames, so I_w looks
            # as if the panels were off).
            problems.append(f"{seen} in {k} of {n} usable bins: "
                            f"{'what the lamp monitor found explains it' if lamps else cause}")
    return problems


def fit_problems(flags: ArrayLike, usable: ArrayLike | None = None) -> list[str]:
    """After the fit: bins whose triple no material of the map explains (the fit did not converge)."""
    flags = np.asarray(flags, dtype=np.int64)
    usable = np.ones(flags.shape, bool) if usable is None else np.asarray(usable, bool)
    n = int(usable.sum())
    k = int(np.count_nonzero(((flags & int(FitFlag.NOT_CONVERGED)) != 0) & usable))
    if n and k > GAMUT_BAD_FRACTION * n:
        return [f"in {k} of {n} usable bins no material of the map explains the measured I_b, I_w, I_c (the fit "
                f"did not converge): a lamp or shutter misbehaved during the capture, or the map is not this "
                f"instrument's"]
    return []
