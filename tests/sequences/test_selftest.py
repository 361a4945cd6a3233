"""`trimeter selftest` against the twin (the real firmware core, plant and optics): a healthy twin
passes every check; each injected fault fails the check that owns it, with a message naming what to
fix, while the checks it does not touch still pass and those it makes impossible say why."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from hil_support import HIL_MAP, TIME_SCALE
from trimeter.cli import main
from trimeter.device import Device
from trimeter.errors import InputError
from trimeter.sequences.selftest import CHECKS, FAIL, PASS, SKIP, run_selftest
from trimeter.spectrometer import open_spectrometer
from trimeter.twin import FaultConfig, Twin

NAMES = [name for name, _ in CHECKS]
LAMPS = "lamps vs calibration"
COLLIMATED = ["exposure collimated", "LED collimated", "shutter collimated"]
PANEL_LIGHTS = ["exposure panels", "LED panel left", "LED panel right", "shutter panel left", "shutter panel right"]


@pytest.fixture
def twin_with(tmp_path):
    twins = []

    def start(**faults):
        twin = Twin(time_scale=TIME_SCALE, faults=FaultConfig(**faults), appearance_map=HIL_MAP,
                    state_dir=tmp_path / f"twin{len(twins)}", seed=len(twins) + 1).start()
        twins.append(twin)
        return twin

    yield start
    for twin in twins:
        twin.close()


def selftest(twin, calibration=None) -> dict:
    """Run the self-test on a twin: {check name: CheckResult}."""
    with Device.open(twin.modbus_port, timeout_s=0.1, attempts=8) as device, \
            open_spectrometer(twin.spectrometer_url) as spectrometer:
        report = run_selftest(device, spectrometer, device_clock=twin.sim_time, calibration=calibration)
        assert not any(device.read_many("led_panel_left_on", "led_panel_right_on", "led_collimated_on",
                                        "shutter_panel_left_open", "shutter_panel_right_open",
                                        "shutter_collimated_open").values()), "lights left on"
    results = {c.name: c for c in report.checks}
    assert list(results) == NAMES
    assert report.passed == all(c.status != FAIL for c in report.checks)
    return results


def statuses(results: dict, names) -> dict:
    return {name: results[name].status for name in names}


def test_a_healthy_twin_passes_every_check_and_the_cli_exits_0(twin_with, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))  # no calibration on this host, whatever ran before
    twin = twin_with()
    rc = main(["selftest", "--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url, "--json"])
    report = json.loads(capsys.readouterr().out)
    assert rc == 0 and report["passed"] is True
    assert {c["name"]: c["status"] for c in report["checks"]} == {name: PASS for name in NAMES if name != LAMPS} | {
        LAMPS: SKIP}   # no calibration on this host: the lamps are not judged, and it says so
    assert "no calibration" in next(c["message"] for c in report["checks"] if c["name"] == LAMPS)
    figures = {c["name"]: c["figures"] for c in report["checks"]}
    assert figures["slot white"]["position_mm"] == pytest.approx(figures["slot white"]["target_mm"], abs=0.1)
    assert figures["backgrounds"]["white_over_black"] > 5            # ρ_white 0.99 against a ~3-30 % black
    for light in ("panel left", "panel right", "collimated"):
        assert figures[f"LED {light}"]["rise_fraction"] > 0.1
        assert figures[f"shutter {light}"]["transmitted_when_closed"] < 0.01
    assert 0.35 < figures["exposure panels"]["peak_fraction"] < 0.98


def test_stuck_slider_fails_homing_and_every_slot_while_the_lights_still_report(twin_with, tmp_path, monkeypatch,
                                                                                  capsys):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    twin = twin_with(stuck_slider=True)
    rc = main(["selftest", "--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url])
    out = capsys.readouterr().out
    assert rc == 1
    assert "FAIL" in out and "stepper" in out and "4 of 16 checks failed" in out

    results = selftest(twin)
    homing = results["homing"]
    assert homing.status == FAIL and homing.figures["fault"] == "stall"
    assert "did not move while homing" in homing.message and "stepper_step PB0" in homing.message
    for slot in ("white", "black", "open"):
        assert results[f"slot {slot}"].status == FAIL
        assert "not homed" in results[f"slot {slot}"].message
    # The panels light the spectrometer wherever the slider stands: those checks still judge, and pass.
    assert statuses(results, ["device", "dark level", *PANEL_LIGHTS]) == {n: PASS for n in
                                                                        ["device", "dark level", *PANEL_LIGHTS]}
    # The beam is only seen through the open slot, the backgrounds need both slots: said, not passed.
    for name in ["backgrounds", *COLLIMATED]:
        assert results[name].status == SKIP and "did not reach" in results[name].message


def test_a_slider_that_jams_after_homing_fails_the_move_naming_the_stepper(twin_with):
    twin = twin_with()

    def jam_after_homing(result, index, total):
        if result.name == "homing":
            twin.control.set_fault(stuck_slider=True)

    with Device.open(twin.modbus_port, timeout_s=0.1, attempts=8) as device, \
            open_spectrometer(twin.spectrometer_url) as spectrometer:
        report = run_selftest(device, spectrometer, on_result=jam_after_homing)
    results = {c.name: c for c in report.checks}
    assert results["homing"].status == PASS
    white = results["slot white"]
    assert white.status == FAIL and white.figures["fault"] == "stall"
    assert "stopped on the way to the white slot" in white.message and "stepper_dir PB1" in white.message
    assert "not homed" in results["slot black"].message  # a stall loses the homing: later moves say why they can't
    assert not report.passed


def test_a_broken_endstop_fails_homing_naming_the_endstop(twin_with):
    results = selftest(twin_with(endstop_broken=True))
    homing = results["homing"]
    assert homing.status == FAIL and homing.figures["fault"] == "homing_timeout"
    assert "endstop did not trigger" in homing.message and "endstop PC0" in homing.message
    assert results["slot open"].status == FAIL


@pytest.mark.parametrize("lamp, dead, alive", [
    ("panels", ["LED panel left", "LED panel right"], ["LED collimated", "shutter collimated", "slot open"]),
    ("collimated", ["LED collimated"], ["LED panel left", "LED panel right", "shutter panel left", "backgrounds"]),
])
def test_a_dead_lamp_fails_its_led_checks_only(twin_with, lamp, dead, alive):
    results = selftest(twin_with(lamp_failure=lamp))
    for name in dead:
        assert results[name].status == FAIL, results[name].message
        assert "does not light the spectrometer" in results[name].message
        assert results[name].figures["rise_fraction"] < 0.01
    assert "led_panel_left PB6" in results["LED panel left"].message or lamp != "panels"
    assert statuses(results, alive) == {name: PASS for name in alive}
    # with no light, a shutter cannot be judged: it says so rather than pass
    shutters = ["shutter panel left", "shutter panel right"] if lamp == "panels" else ["shutter collimated"]
    for name in shutters:
        assert results[name].status == SKIP and "no light" in results[name].message
    assert all(results[n].status == PASS for n in ("homing", "slot white", "slot black", "dark level"))


def test_a_shutter_stuck_open_fails_its_shutter_check(twin_with):
    results = selftest(twin_with(stuck_shutter_open="panel_right"))
    shutter = results["shutter panel right"]
    assert shutter.status == FAIL and shutter.figures["transmitted_when_closed"] > 0.9
    assert "servo_panel_right PA7" in shutter.message and "servo_panel_right_closed_us" in shutter.message
    others = [n for n in NAMES if n not in ("shutter panel right", LAMPS)]
    assert statuses(results, others) == {name: PASS for name in others}


def test_the_twin_faults_for_the_selftest_are_validated():
    assert FaultConfig.parse("stuck_shutter_open=collimated,endstop_broken") == \
        FaultConfig(stuck_shutter_open="collimated", endstop_broken=True)
    with pytest.raises(InputError, match="stuck_shutter_open must be one of panel_left"):
        FaultConfig.parse("stuck_shutter_open=lid")
    with pytest.raises(InputError, match="endstop_broken must be true/false"):
        FaultConfig(endstop_broken="yes")


def test_selftest_without_an_instrument_or_spectrometer_is_a_clear_error(twin_with, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    twin = twin_with()
    assert main(["selftest", "--port", twin.modbus_port, "--spectrometer", f"sim:{tmp_path / 'no-such-pty'}"]) == 2
    assert capsys.readouterr().err.startswith("trimeter: error: cannot open sim spectrometer")
    assert main(["selftest", "--port", twin.modbus_port, "--spectrometer", "nonsense"]) == 2
    assert "spectrometer must be '<backend>:<address>'" in capsys.readouterr().err
    assert main(["selftest", "--spectrometer", "sim:/nonexistent"]) == 2
    assert "no instrument port" in capsys.readouterr().err


def _monitor_calibration(twin) -> SimpleNamespace:
    """What a calibration records of the lamp monitor (LEDs on; all shutters closed, then each set-up's open),
    read from this twin now: the reference the lamps are judged against."""
    from trimeter import registers as regs
    from trimeter.sequences import lamp_monitor

    def readings(device, open_: tuple[str, ...]) -> list[dict]:
        coils = [False] * regs.SPANS["coil"]
        for light in ("panel_left", "panel_right", "collimated"):
            coils[regs.COILS[f"led_{light}_on"].address] = True
            coils[regs.COILS[f"shutter_{light}_open"].address] = light in open_
        device.transport.write_bits(0, coils)
        device.wait_idle(10)
        values = device.read_many(*(f"lamp_monitor_{lamp}" for lamp in lamp_monitor.LAMPS))
        return [{lamp: values[f"lamp_monitor_{lamp}"] for lamp in lamp_monitor.LAMPS}]

    with Device.open(twin.modbus_port, timeout_s=0.1, attempts=8) as device:
        records = {"dark": lamp_monitor.record(False, False, readings(device, ())),
                   "white": lamp_monitor.record(True, False, readings(device, ("panel_left", "panel_right"))),
                   "open": lamp_monitor.record(False, True, readings(device, ("collimated",)))}
        device.transport.write_bits(0, [False] * regs.SPANS["coil"])
    return SimpleNamespace(lamp_monitor=records, created_utc="2026-12-06T03:00:00+00:00")


@pytest.mark.parametrize("dimmed, wrong", [("panels:0.5", ["left panel", "right panel"]),
                                           ("collimated:0.05", ["collimated"]),
                                           ("both:1.9", ["left panel", "right panel", "collimated"])])
def test_lamps_off_their_calibrated_level_fail_against_the_last_calibration(twin_with, dimmed, wrong):
    twin = twin_with()
    calibration = _monitor_calibration(twin)
    healthy = selftest(twin, calibration)[LAMPS]
    assert healthy.status == PASS, healthy.message
    twin.control.set_fault(lamp_dimmed=dimmed)
    lamps = selftest(twin, calibration)[LAMPS]
    assert lamps.status == FAIL, lamps.message
    for name in wrong:
        assert f"the {name} gives" in lamps.message
    assert lamps.message.count(" gives ") == len(wrong)
