"""The checks against the twin (the real firmware, its plant and optics): the issue's scenarios end to
end. `serve` with a stale calibration and the sample in the holder triple-blinks, refuses presses until
the holder is empty, then calibrates; `calibrate` with a sample in is refused; a lamp failing after the
calibration makes `measure` exit non-zero with no results directory."""

from __future__ import annotations

import time

import pytest

from hil_support import HIL_MAP, SAMPLE, THICKNESS_MM, empty_twin
from trimeter.cli import main
from trimeter.device import Device
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings
from trimeter.spectrometer import open_spectrometer


@pytest.fixture
def twin(tmp_path, monkeypatch):
    with empty_twin(tmp_path, monkeypatch, seed=5) as twin:
        yield twin


def pattern(twin) -> str:
    return twin.control.state()["plant"]["status_pattern"]


def poll_until(service, events, kinds, timeout_s=60.0):
    start, deadline = len(events), time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        service.poll_once()
        new = [e for e in events[start:] if e.kind in kinds]
        if new:
            return new[0]
        time.sleep(0.02)
    raise AssertionError(f"none of {kinds} within {timeout_s} s: {[(e.kind, e.message) for e in events[start:]]}")


def test_serve_never_calibrates_with_the_sample_in_the_holder(twin, tmp_path):
    settings = HostSettings()
    settings.set("map", str(HIL_MAP))
    settings.set("results_dir", str(tmp_path / "results"))
    settings.set("warmup_threshold", 0.003)
    events = []
    service = Service(lambda: Device.open(twin.modbus_port, timeout_s=0.2),
                      lambda: open_spectrometer(twin.spectrometer_url), settings, on_event=events.append)
    service.connect()
    try:
        assert pattern(twin) == "triple_blink"  # no calibration yet: empty the holder and press
        twin.control.press_button()
        assert poll_until(service, events, ("calibrated", "refused", "failed")).kind == "calibrated"
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        twin.control.press_button()
        assert poll_until(service, events, ("measured", "failed")).kind == "measured"
        # the calibration goes stale with the sample still in the holder
        settings.set("calibration_max_age_s", max(1.0, twin.sim_time() - service.calibration.device_time_s) / 2)
        assert poll_until(service, events, ("empty_holder",)).kind == "empty_holder"
        assert pattern(twin) == "triple_blink"
        twin.control.press_button()
        refused = poll_until(service, events, ("refused", "calibrated", "failed"))
        assert refused.kind == "refused" and "a sample seems to be in the holder" in refused.message, refused.message
        assert pattern(twin) == "triple_blink"  # still asking
        twin.control.remove_sample()
        twin.control.press_button()
        assert poll_until(service, events, ("calibrated", "refused", "failed")).kind == "calibrated"
        assert pattern(twin) == "on"
        assert len(list((tmp_path / "results").iterdir())) == 1  # the one good measurement, nothing else
    finally:
        service.close()


def test_cli_refuses_a_sample_at_calibration_and_a_failed_lamp_at_measurement(twin, tmp_path, capsys):
    port = ["--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url]
    twin.control.insert_sample(SAMPLE, THICKNESS_MM)
    assert main(["calibrate", *port, "--no-warm-up"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: the holder does not look empty") and "ρ_black" in err, err
    twin.control.remove_sample()
    assert main(["calibrate", *port, "--no-warm-up"]) == 0
    twin.control.insert_sample(SAMPLE, THICKNESS_MM)
    results = tmp_path / "results"
    for lamp in ("panels", "collimated"):
        twin.control.set_fault(lamp_failure=lamp)
        assert main(["measure", *port, "--thickness", "0.4", "--map", str(HIL_MAP), "--results", str(results)]) == 2
        out = capsys.readouterr()
        assert "thickness: 0.4 mm (--thickness), map hil-ideal-l0.4" in out.out
        assert "trimeter: error: the 0.4 mm capture was refused, nothing was written" in out.err, out.err
        assert not results.exists() or list(results.iterdir()) == []
    twin.control.set_fault(lamp_failure=None)
    assert main(["measure", *port, "--thickness", "0.4", "--map", str(HIL_MAP), "--results", str(results)]) == 0
    assert len(list(results.iterdir())) == 1
