"""trimeter.sequences.lamp_monitor: references from a calibration's records, each shot reading as a fraction of
the calibrated light, and the refusals (drift beyond ±3 %, a dead lamp, a shutter that did not close or does
not block); malformed or missing records are a clear problem, never an exception."""

from __future__ import annotations

import numpy as np

from trimeter.sequences import lamp_monitor as lm
from trimeter.domain import Calibration

DARK, SPAN = 60, 3200


def reading(left=1.0, right=1.0, collimated=1.0, *, panels=True, beam=False):
    return {"panel_left": DARK + round(SPAN * left * panels), "panel_right": DARK + round(SPAN * right * panels),
            "collimated": DARK + round(SPAN * collimated * beam)}


def records(**lamps):
    return {"white": lm.record(True, False, [reading(**lamps), reading(**lamps)]),
            "black": lm.record(True, False, [reading(**lamps), reading(**lamps)]),
            "collimated": lm.record(False, True, [reading(panels=False, beam=True, **lamps)] * 2),
            "dark": lm.record(False, False, [reading(panels=False)])}


def test_references_and_fractions():
    refs = lm.references(records())
    assert refs == {"panel_left": (DARK, DARK + SPAN), "panel_right": (DARK, DARK + SPAN),
                    "collimated": (DARK, DARK + SPAN)}
    light = lm.relative_light(records(), records(left=0.8))
    assert np.allclose(light["white"]["fractions"]["panel_left"], 0.8)
    assert np.allclose(light["white"]["fractions"]["collimated"], 0.0)
    assert lm.shot_problems(lm.relative_light(records(), records())) == []


def test_a_shot_beyond_the_bound_is_refused_with_its_figure_and_within_it_is_not():
    assert lm.shot_problems(lm.relative_light(records(), records(left=0.98, collimated=1.02))) == []
    problems = lm.shot_problems(lm.relative_light(records(), records(collimated=0.5)))
    assert len(problems) == 1 and "collimated LED was at -50.0%" in problems[0] and "collimated capture" in problems[0]
    problems = lm.shot_problems(lm.relative_light(records(), records(right=1.05)))
    assert len(problems) == 1 and "right diffuse panel was at +5.0%" in problems[0]
    assert "white and black captures" in problems[0]


def test_a_dead_lamp_and_a_shutter_that_did_not_close():
    problems = lm.shot_problems(lm.relative_light(records(), records(left=0.0)))
    assert len(problems) == 1 and "left diffuse panel gave 0%" in problems[0] and "dead" in problems[0]
    shot = records()
    shot["collimated"]["readings"][1]["panel_left"] = DARK + SPAN  # the blade stayed open in the beam's set-up
    problems = lm.shot_problems(lm.relative_light(records(), shot))
    assert problems == ["the left diffuse panel's shutter did not close (its lamp monitor saw 100% of the open light "
                        "during the collimated capture): a stuck shutter"]


def test_calibration_problems():
    assert lm.calibration_problems(records()) == []
    assert lm.calibration_problems({}) == []  # a hand-made calibration: nothing to judge
    stuck = records()
    for reading_ in stuck["collimated"]["readings"] + stuck["dark"]["readings"]:
        reading_["panel_right"] = DARK + SPAN
    assert any("right diffuse panel's shutter does not block" in p for p in lm.calibration_problems(stuck))
    dead = records(collimated=0.0)
    assert any("collimated LED's lamp-monitor photodiode sees no light" in p for p in lm.calibration_problems(dead))
    unsteady = records()
    unsteady["white"]["readings"][1] = reading(left=0.9)
    assert any("changed by up to" in p for p in lm.calibration_problems(unsteady))
    assert lm.calibration_problems({"white": {"panels": True}}) == [
        "the lamp-monitor readings of the calibration are malformed"]


def test_missing_or_malformed_references_are_a_problem_not_an_exception():
    assert lm.shot_problems(lm.relative_light({}, records())) == [
        "the calibration holds no lamp-monitor readings (taken before the lamp monitor): calibrate again"]
    assert "malformed" in lm.shot_problems(lm.relative_light(records(), {"white": {"readings": "x"}}))[0]
    assert lm.relative_light(records(), {}) is None


def test_the_calibration_file_keeps_the_readings(tmp_path):
    wl = np.linspace(400, 700, 4)
    cal = Calibration(wl, np.ones(4), np.ones(4), np.full(4, 0.03), 0.99, np.zeros(4, np.int32),
                      lamp_monitor=records())
    cal.save(tmp_path)
    assert Calibration.load(tmp_path).lamp_monitor == records()
