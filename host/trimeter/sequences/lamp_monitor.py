"""The lamp monitor: what its photodiodes say about the light of a capture, against the calibration.

One photodiode per LED channel (left panel, right panel, collimated LED) looks at its lamp's emitting face
from just past the lamp's shutter and never through the sample (hardware/README.md), so it reads

    dark offset                      shutter closed (the LEDs stay on throughout a sequence)
    dark offset + the lamp's light   shutter open

Every capture (plans.capture) records the readings right after its shutters settled and again after its
last exposure, with which shutters were open; the dark frames (every shutter closed) record one more set.
The calibration's records give each photodiode its two references — `dark` (median of its shutter-closed
readings) and `lit` (median of its shutter-open readings) — and every reading of a shot becomes its light
as a fraction of the calibrated one, (reading − dark) / (lit − dark):

- shutter open, fraction under DEAD_FRACTION: the lamp is dead or its shutter did not open;
- shutter open, fraction off 1 by more than DRIFT_BOUND: the lamp dimmed or drifted since the calibration
  (the sample sees the same change, and nothing in its spectra can tell: a refused shot, with the figure);
- shutter closed, fraction over LEAK_FRACTION: the shutter did not close (its lamp's light reaches the
  sample in a set-up where it must not).
"""

from __future__ import annotations

import numpy as np

LAMPS = ("panel_left", "panel_right", "collimated")
LAMP_NAMES = {"panel_left": "left diffuse panel", "panel_right": "right diffuse panel",
              "collimated": "collimated LED"}
DRIFT_BOUND = 0.03      # relative light against the calibration: a shot beyond ±3 % is refused
DEAD_FRACTION = 0.2     # under this fraction of the calibrated light: no light (dead lamp, shutter stuck closed)
LEAK_FRACTION = 0.1     # a closed shutter passing more than this fraction of the open light did not close
MIN_SPAN_COUNTS = 300   # the calibration's open − closed reading: less and the photodiode sees no lamp


def record(panels: bool, collimated: bool, readings: list[dict]) -> dict:
    """One set-up's monitor record: which shutters were open, and its readings {lamp: counts}."""
    return {"panels": bool(panels), "collimated": bool(collimated),
            "readings": [{lamp: int(r[lamp]) for lamp in LAMPS} for r in readings]}


def _is_open(setup: dict, lamp: str) -> bool:
    return bool(setup["collimated"] if lamp == "collimated" else setup["panels"])


def _well_formed(records: object) -> bool:
    try:
        return isinstance(records, dict) and all(
            isinstance(s["panels"], bool) and isinstance(s["collimated"], bool) and s["readings"]
            and all(np.isfinite(float(r[lamp])) for r in s["readings"] for lamp in LAMPS)
            for s in records.values())
    except (KeyError, TypeError, ValueError):
        return False


def references(records: dict) -> dict[str, tuple[float, float]]:
    """Each photodiode's (dark, lit) counts from a calibration's records (lamps without both: left out)."""
    out = {}
    for lamp in LAMPS:
        lit = [float(r[lamp]) for s in records.values() if _is_open(s, lamp) for r in s["readings"]]
        dark = [float(r[lamp]) for s in records.values() if not _is_open(s, lamp) for r in s["readings"]]
        if lit and dark:
            out[lamp] = (float(np.median(dark)), float(np.median(lit)))
    return out


def relative_light(calibration_records: dict, shot_records: dict) -> dict | None:
    """The shot's readings as fractions of the calibrated light: {setup: {"panels", "collimated",
    "fractions": {lamp: [...]}}}; {"error": why} when the two cannot be compared; None without a shot record."""
    if not shot_records:
        return None
    if not calibration_records:
        return {"error": "the calibration holds no lamp-monitor readings (taken before the lamp monitor): "
                         "calibrate again"}
    if not _well_formed(calibration_records) or not _well_formed(shot_records):
        return {"error": "the lamp-monitor readings are malformed: calibrate again"}
    refs = references(calibration_records)
    out = {}
    for key, setup in shot_records.items():
        fractions = {}
        for lamp, (dark, lit) in refs.items():
            span = max(lit - dark, 1.0)
            fractions[lamp] = [(float(r[lamp]) - dark) / span for r in setup["readings"]]
        out[key] = {"panels": setup["panels"], "collimated": setup["collimated"], "fractions": fractions}
    return out


def calibration_problems(records: dict) -> list[str]:
    """Does every photodiode see its lamp through its open shutter, and nothing through the closed one, and
    did the light hold still during the calibration? Empty records (a hand-made calibration): nothing to say."""
    if not records:
        return []
    if not _well_formed(records):
        return ["the lamp-monitor readings of the calibration are malformed"]
    problems = []
    refs = references(records)
    for lamp in LAMPS:
        name = LAMP_NAMES[lamp]
        if lamp not in refs:
            problems.append(f"the calibration has no lamp-monitor reading of the {name} with its shutter both open "
                            f"and closed")
            continue
        dark, lit = refs[lamp]
        if lit - dark < MIN_SPAN_COUNTS:
            if dark > 0.5 * lit and lit >= MIN_SPAN_COUNTS:
                problems.append(f"the {name}'s shutter does not block its lamp-monitor photodiode (closed: {dark:.0f} "
                                f"counts, open: {lit:.0f}): the shutter is stuck open")
            else:
                problems.append(f"the {name}'s lamp-monitor photodiode sees no light with its shutter open ({lit:.0f} "
                                f"counts, closed {dark:.0f}): the lamp is dead, its shutter did not open, or the "
                                f"monitor failed")
            continue
        worst = max((abs((float(r[lamp]) - dark) / (lit - dark) - 1.0) for s in records.values()
                     if _is_open(s, lamp) for r in s["readings"]), default=0.0)
        if worst > DRIFT_BOUND:
            problems.append(f"the {name}'s light changed by up to {worst:.1%} during the calibration (bound "
                            f"{DRIFT_BOUND:.0%}): the lamps were not stable; warm up and calibrate again")
    return problems


def shot_problems(light: dict | None) -> list[str]:
    """The lamps during a shot against the calibration (relative_light's result); empty: the light was right."""
    if not light:
        return []
    if "error" in light:
        return [light["error"]]
    worst: dict[tuple[str, str], tuple[float, list[str], float]] = {}

    def note(lamp: str, kind: str, value: float, setup: str, badness: float) -> None:
        previous = worst.get((lamp, kind))
        if previous is None or badness > previous[0]:
            worst[(lamp, kind)] = (badness, [setup], value)
        elif setup not in previous[1]:
            previous[1].append(setup)

    for key, setup in light.items():
        for lamp, fractions in setup["fractions"].items():
            for f in fractions:
                if _is_open(setup, lamp):
                    if f < DEAD_FRACTION:
                        note(lamp, "dead", f, key, 1.0 - f)
                    elif abs(f - 1.0) > DRIFT_BOUND:
                        note(lamp, "drift", f, key, abs(f - 1.0))
                elif f > LEAK_FRACTION:
                    note(lamp, "leak", f, key, f)
    problems = []
    for (lamp, kind), (_, setups, f) in sorted(worst.items()):
        name = LAMP_NAMES[lamp]
        where = " and ".join(setups) + (" captures" if len(setups) > 1 else " capture")
        if kind == "dead":
            problems.append(f"the {name} gave {f:.0%} of its calibrated light (lamp monitor, {where}): the "
                            f"lamp is dead or its shutter did not open")
        elif kind == "drift":
            problems.append(f"the {name} was at {f - 1:+.1%} of its calibrated light (lamp monitor, {where}; "
                            f"bound ±{DRIFT_BOUND:.0%}): a dimmed or drifting lamp — calibrate again (replace the "
                            f"lamp if it keeps dimming)")
        else:
            problems.append(f"the {name}'s shutter did not close (its lamp monitor saw {f:.0%} of the open light "
                            f"during the {where}): a stuck shutter")
    return problems
