"""A host-less press: on a twin with the C12880MA and a table in its slot, a calibration press (holder empty)
and a measurement press run with no host attached; a host that connects afterwards reads the device's
result (`trimeter device last-result`, into a results directory), and it matches a host fit (`trimeter fit
--table`, double precision) of the same capture within the on-device tolerances."""

from __future__ import annotations

import contextlib
import csv
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest

from hil_support import SAMPLE, THICKNESS_MM, TIME_SCALE
from trimeter import registers as regs
from trimeter.cli import main


@pytest.fixture(scope="module")
def hil_map():
    from hil_support import HIL_MAP, build_hil_map
    from trimeter.formats.appearance import AppearanceMap

    return AppearanceMap.load(HIL_MAP) if HIL_MAP.exists() else build_hil_map(HIL_MAP)


def _press(twin, timeout_s: float = 120.0) -> str:
    """Press the button and wait, watching only the twin's status LED (no Modbus), until the press ended."""
    twin.control.press_button()
    deadline = time.monotonic() + timeout_s
    started = False
    while time.monotonic() < deadline:
        pattern = twin.control.state()["plant"]["status_pattern"]
        if pattern == "slow_blink":
            started = True
        elif started:
            return pattern
        time.sleep(0.02)
    raise AssertionError("the standalone press did not end")


@contextlib.contextmanager
def _c12880_twin(request, tmp_path, hil_map, monkeypatch, seed):
    """A twin with the C12880MA and the HIL map's table in its slot (the table also in tmp_path / hil.tlut), set up
    once by a host that then goes away;
    yields (twin, its --port arguments)."""
    if request.config.getoption("--port"):
        pytest.skip("needs the twin (its storage seeded with a table, its lamps dimmed on demand)")
    from trimeter.device import Device
    from trimeter.inversion.table_builder import build_from_map
    from trimeter.twin import Twin

    for name in ("DATA", "CONFIG", "CACHE"):
        monkeypatch.setenv(f"TRIMETER_{name}_DIR", str(tmp_path / name.lower()))
    table_file = build_from_map(hil_map).save(tmp_path / "hil.tlut")
    with Twin(sample=None, thickness_mm=THICKNESS_MM, time_scale=TIME_SCALE, appearance_map=hil_map,
              state_dir=tmp_path / "twin", seed=seed, map_table=table_file.read_bytes(), sensor="c12880ma") as twin:
        with Device.open(twin.modbus_port) as device:
            device.write_many({"spectro_integration_us": 4000, "spectro_frames": 4})
        yield twin, ["--port", twin.modbus_port]


def test_a_hostless_press_leaves_a_result_that_matches_a_host_fit(request, tmp_path, hil_map, monkeypatch, capsys):
    from trimeter.device import Device

    with _c12880_twin(request, tmp_path, hil_map, monkeypatch, seed=3) as (twin, port):
        assert main(["device", "last-result", *port]) == 2
        assert "no standalone result: no press since it started" in capsys.readouterr().err
        assert main(["device", "standalone", "calibrate", *port]) == 0
        assert _press(twin) == "on"  # calibrated
        capsys.readouterr()
        assert main(["device", "last-result", *port]) == 2
        assert "was a calibration: insert a sample and press again" in capsys.readouterr().err
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        pattern = _press(twin)
        truth = twin.control.truth()
        with Device.open(twin.modbus_port) as device:  # a host connects later
            result = device.standalone_result()
        assert main(["device", "last-result", *port, "--out", str(tmp_path / "results"), "--no-figure"]) == 0
        out = capsys.readouterr().out
    written = Path([line.split(": ", 1)[1] for line in out.splitlines() if line.startswith("results: ")][0])
    meta = json.loads((written / "measurement.json").read_text())
    assert meta["fitted_on"] == "device" and meta["hostless"] and meta["method"] == "lut"
    assert meta["device_map_table"]["matches_fit_table"]
    assert meta["declared_thicknesses_mm"] == [pytest.approx(THICKNESS_MM)]
    written_fit = np.genfromtxt(written / "parameters.csv", delimiter=",", names=True)
    np.testing.assert_allclose(written_fit["alpha"], result.bins["alpha"], rtol=1e-7)  # the device's fit, as is (%.8g)
    assert pattern in ("on", "double_blink")
    assert result.status in (regs.StandaloneStatus.DONE, regs.StandaloneStatus.FLAGGED)
    assert result.thickness_mm == pytest.approx(THICKNESS_MM)
    b = result.bins
    lit = (b["capture_flags"] & 4) == 0
    assert lit.sum() > 100 and not np.any(b["capture_flags"] & 1)  # nothing saturated at this integration time
    # the host's own ratios from the device's rates, in double precision, fitted by the host with the same table
    diffuse, collimated = b["diffuse"].astype(float), b["collimated"].astype(float)
    measured = tmp_path / "capture.csv"
    with open(measured, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["wavelength_nm", "I_b", "I_w", "I_c", "rho_b", "rho_w"])
        for k in np.flatnonzero(lit):
            writer.writerow([float(b["wavelength_nm"][k]), b["black"][k] / diffuse[k], b["white"][k] / diffuse[k],
                             b["open"][k] / collimated[k], float(b["rho_black"][k]), result.rho_white])
    host = tmp_path / "host.csv"
    assert main(["fit", "--table", str(tmp_path / "hil.tlut"), "--input", str(measured), "-o", str(host)]) == 0
    with open(host, newline="") as f:
        rows = list(csv.DictReader(f))
    on_host = {k: np.array([float(r[k]) for r in rows]) for k in ("alpha", "sigma_t", "g")}
    on_device = {k: b[k][lit].astype(float) for k in ("alpha", "sigma_t", "g")}
    both = np.isfinite(on_host["alpha"]) & np.isfinite(on_device["alpha"])
    np.testing.assert_array_equal(np.isfinite(on_device["alpha"]), np.isfinite(on_host["alpha"]))
    assert both.sum() > 100
    d_alpha = np.max(np.abs(on_device["alpha"] - on_host["alpha"])[both])
    d_sigma = np.max(np.abs(on_device["sigma_t"] / on_host["sigma_t"] - 1)[both])
    d_g = np.max(np.abs(on_device["g"] - on_host["g"])[both])
    print(f"standalone vs host fit over {both.sum()} bins: max |Δα| {d_alpha:.2e}, max |Δσt|/σt {d_sigma:.2e}, "
          f"max |Δg| {d_g:.2e}; status {result.status.name.lower()}, {result.flagged_bins} flagged lit bins")
    assert d_alpha <= 1e-3 and d_sigma <= 1e-3 and d_g <= 2e-3  # the on-device fit's tolerances
    # against the twin's truth (the device corrects no lamp drift between its calibration and the press)
    wl = b["wavelength_nm"][lit][both]
    want = {k: np.interp(wl, truth["wavelengths_nm"], truth[k]) for k in ("alpha", "sigma_t", "g")}
    band = (wl > 420) & (wl < 720)
    print(f"standalone vs twin truth over 420-720 nm ({band.sum()} bins): |Δα| p95 "
          f"{np.percentile(np.abs(on_device['alpha'][both] - want['alpha'])[band], 95):.4f}, |Δσt|/σt p95 "
          f"{np.percentile(np.abs(on_device['sigma_t'][both] / want['sigma_t'] - 1)[band], 95):.2%}, |Δg| p95 "
          f"{np.percentile(np.abs(on_device['g'][both] - want['g'])[band], 95):.3f}")


def test_a_hostless_press_with_dimmed_lamps_says_recalibrate(request, tmp_path, hil_map, monkeypatch, capsys):
    """Calibrated on the device, then the panels dim (an aged LED, the twin's lamp_dimmed fault): the press is
    flagged lamp_changed (status LED double blink) and `trimeter device last-result` tells the operator to
    recalibrate; with the lamps as calibrated, before and after, the press is not."""
    from trimeter.device import Device
    from trimeter.device.client import STANDALONE_LAMP_TOLERANCE

    with _c12880_twin(request, tmp_path, hil_map, monkeypatch, seed=5) as (twin, port):
        assert main(["device", "standalone", "calibrate", *port]) == 0
        assert re.search(r"warming up: a press waits (29\d|300) s more", capsys.readouterr().out)  # lamps just on
        assert _press(twin) == "on"  # calibrated, after the warm-up
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)

        def press_and_read(label: str) -> tuple[str, object, str]:
            pattern = _press(twin)
            with Device.open(twin.modbus_port) as device:
                result = device.standalone_result()
            capsys.readouterr()
            assert main(["device", "last-result", *port, "--out", str(tmp_path / "results"), "--label", label,
                         "--no-figure"]) == 0
            return pattern, result, capsys.readouterr().out

        pattern, result, out = press_and_read("as-calibrated")
        assert result.status in (regs.StandaloneStatus.DONE, regs.StandaloneStatus.FLAGGED)
        assert pattern == ("on" if result.status == regs.StandaloneStatus.DONE else "double_blink")
        assert all(abs(level - 1) < 0.5 * STANDALONE_LAMP_TOLERANCE for level in result.lamp_levels.values())
        assert "RECALIBRATE" not in out

        twin.control.set_fault(lamp_dimmed="panels:0.9")
        pattern, result, out = press_and_read("dimmed")
        assert result.status == regs.StandaloneStatus.LAMP_CHANGED and pattern == "double_blink"
        assert result.lamp_levels["panel_left"] == pytest.approx(0.9, abs=0.005)
        assert result.lamp_levels["collimated"] == pytest.approx(1.0, abs=0.005)
        recalibrate = [line for line in out.splitlines() if line.startswith("RECALIBRATE: ")]
        left = f"the left diffuse panel gave {result.lamp_levels['panel_left']:.1%} of its light at the calibration"
        assert len(recalibrate) == 1 and left in recalibrate[0]
        assert "trimeter device standalone calibrate" in recalibrate[0]
        written = Path([line.split(": ", 1)[1] for line in out.splitlines() if line.startswith("results: ")][0])
        assert json.loads((written / "measurement.json").read_text())["standalone"]["recalibrate"] is True

        twin.control.set_fault(lamp_dimmed=None)  # the lamps as they were at the calibration
        pattern, result, out = press_and_read("restored")
        assert result.status in (regs.StandaloneStatus.DONE, regs.StandaloneStatus.FLAGGED)
        assert "RECALIBRATE" not in out


def test_a_sample_left_in_the_holder_is_not_taken_for_the_calibration(request, tmp_path, hil_map, monkeypatch,
                                                                       capsys):
    """A device-side calibration press with a sample in the holder is refused (status LED triple blink, as `trimeter
    serve` asks for an empty holder), says why, and keeps the calibration the device had: a later measurement is
    made against that one, not against the sample."""
    from trimeter.device import Device

    with _c12880_twin(request, tmp_path, hil_map, monkeypatch, seed=7) as (twin, port):
        assert main(["device", "standalone", "measure", "--force", *port]) == 2
        assert "--force applies to `calibrate` only" in capsys.readouterr().err
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        assert main(["device", "standalone", "calibrate", *port]) == 0
        assert _press(twin) == "triple_blink"  # no calibration at all yet: the empty-holder bound alone refuses it
        capsys.readouterr()
        assert main(["device", "last-result", *port]) == 2
        assert "a calibration it refused: ρ_black" in capsys.readouterr().err
        assert main(["device", "standalone", "calibrate", *port]) == 0
        out = capsys.readouterr().out
        print(out)
        assert "last press: calibration_refused; not calibrated" in out
        assert "a sample seems to be in the holder" in out

        twin.control.remove_sample()
        assert _press(twin) == "on"  # the same mode, the holder emptied: calibrated
        with Device.open(twin.modbus_port) as device:
            calibration = device.standalone_result().bins["diffuse"].copy()
            assert device.read("standalone_check") == regs.StandaloneCheck.NONE
            assert device.read("standalone_check_value") < 0.12

        twin.control.insert_sample(SAMPLE, THICKNESS_MM)  # a recalibration with the sample still in
        assert main(["device", "standalone", "calibrate", *port]) == 0
        assert _press(twin) == "triple_blink"
        with Device.open(twin.modbus_port) as device:
            assert device.read("standalone_status") == regs.StandaloneStatus.CALIBRATION_REFUSED
            assert device.read("standalone_calibrated") == 1
            print("recalibration with the sample in:", device.read("standalone_check").name.lower(),
                  device.read("standalone_check_value"))
        assert main(["device", "standalone", "measure", *port]) == 0
        assert _press(twin) in ("on", "double_blink")
        with Device.open(twin.modbus_port) as device:
            result = device.standalone_result()
        assert result.status in (regs.StandaloneStatus.DONE, regs.StandaloneStatus.FLAGGED)
        np.testing.assert_array_equal(result.bins["diffuse"], calibration)  # measured against the kept calibration
