"""The lamp monitor against the twin (the real firmware reading the plant's photodiodes): after a good
calibration, a diffuse panel dimmed to 80 %, the collimated LED dimmed to 50 % or a panel or the
collimated shutter stuck open make `measure` exit 2 with nothing written, saying which lamp or shutter and
by how much; a drift within the ±3 % bound is measured."""

from __future__ import annotations

import re

import pytest

from hil_support import HIL_MAP, SAMPLE, THICKNESS_MM, empty_twin
from trimeter.cli import main


@pytest.fixture
def twin(tmp_path, monkeypatch):
    with empty_twin(tmp_path, monkeypatch, seed=7) as twin:
        yield twin


def test_a_dimmed_lamp_or_a_stuck_shutter_after_calibration_is_refused_and_a_small_drift_is_not(twin, tmp_path,
                                                                                                 capsys):
    port = ["--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url]
    measure = ["measure", *port, "--thickness", "0.4", "--map", str(HIL_MAP), "--results", str(tmp_path / "results")]
    # The warm-up ends when the light changes by < 0.2 % per 10 s, which the panels (τ 90 s, 4 % droop when
    # hot) reach short of their steady heat; a second calibration right after is taken nearly hot, so the
    # lamps' own droop since then is a few tenths of a % and the 99 % case below sits ~2 % inside the ±3 %
    # bound whatever the machine's load (a slower host only lets the lamps heat longer, simulated time
    # being wall time × time scale).
    assert main(["calibrate", *port]) == 0
    assert main(["calibrate", *port, "--no-warm-up"]) == 0
    heat = twin.control.state()["lamp_temperature"]
    assert min(heat.values()) > 0.9, f"lamps not near their steady heat after two calibrations: {heat}"
    capsys.readouterr()
    twin.control.insert_sample(SAMPLE, THICKNESS_MM)
    refusals = (
        ({"lamp_dimmed": "panels:0.8"}, {"left diffuse panel": -20, "right diffuse panel": -20}),
        ({"lamp_dimmed": "collimated:0.5"}, {"collimated LED": -50}),
        ({"lamp_dimmed": "panel_right:0.9"}, {"right diffuse panel": -10}),
        ({"stuck_shutter_open": "panel_left"}, {}),
    )
    for fault, dimmed in refusals:
        twin.control.set_fault(**fault)
        assert main(measure) == 2
        err = capsys.readouterr().err
        assert err.startswith("trimeter: error: the 0.4 mm capture was refused, nothing was written"), err
        for lamp, percent in dimmed.items():
            said = re.search(rf"the {lamp} was at ([-+][0-9.]+)% of its calibrated light", err)
            assert said and percent - 3 <= float(said.group(1)) <= percent + 1, (fault, err)
        if not dimmed:
            assert "left diffuse panel's shutter did not close" in err, err
        assert "lamp monitor" in err
        assert not (tmp_path / "results").exists() or list((tmp_path / "results").iterdir()) == []
        twin.control.set_fault(**dict.fromkeys(fault))
    twin.control.set_fault(lamp_dimmed="panels:0.99")  # within the ±3 % bound
    assert main(measure) == 0, (capsys.readouterr().err, twin.control.state()["lamp_temperature"])
    assert len(list((tmp_path / "results").iterdir())) == 1


def test_calibration_with_a_panel_shutter_stuck_open_is_refused(twin, capsys):
    # with the holder empty no spectrum shows it (panel light falls through the open slot unseen)
    twin.control.set_fault(stuck_shutter_open="panel_right")
    assert main(["calibrate", "--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url,
                 "--no-warm-up"]) == 2
    err = capsys.readouterr().err
    assert "right diffuse panel's shutter does not block its lamp-monitor photodiode" in err, err


def test_a_collimated_shutter_stuck_open_is_named(twin, tmp_path, capsys):
    port = ["--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url]
    assert main(["calibrate", *port, "--no-warm-up"]) == 0
    capsys.readouterr()
    twin.control.insert_sample(SAMPLE, THICKNESS_MM)
    twin.control.set_fault(stuck_shutter_open="collimated")
    assert main(["measure", *port, "--thickness", "0.4", "--map", str(HIL_MAP), "--results",
                 str(tmp_path / "results")]) == 2
    err = capsys.readouterr().err
    assert "the collimated LED's shutter did not close" in err, err
    # the spectra's consequences (a lit dark frame makes I_w look panel-less) point at what the monitor found
    assert "diffuse panels gave" not in err and "what the lamp monitor found explains it" in err, err
