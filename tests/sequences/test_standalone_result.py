"""A standalone result as a measurement (trimeter.sequences.standalone): the device's fit kept as is, the
reflectances its ratios of the same rates (NaN where it gave the fit no input), provenance saying it was
fitted on the device with no host; a last press that was no measurement is one clear error; the device's
white reference is the host's; a press whose lamps changed since the calibration is recorded with its lamp
levels and tells the operator to recalibrate, and the device's lamp tolerance is the α / σt bias it claims."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hil_support import HIL_MAP
from trimeter import registers as regs
from trimeter.device.client import STANDALONE_DTYPE, STANDALONE_LAMP_TOLERANCE, StandaloneResult
from trimeter.domain import CaptureFlag, InstrumentInfo
from trimeter.errors import DeviceError
from trimeter.results.writer import write_measurement
from trimeter.sequences.settings import HostSettings
from trimeter.sequences.standalone import measurement_of, read_standalone, recalibrate_advice


@pytest.fixture(scope="module")
def table():
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.table_builder import build_from_map

    return build_from_map(AppearanceMap.load(HIL_MAP))


def _result(status=regs.StandaloneStatus.DONE, lamp_levels: dict | None = None) -> StandaloneResult:
    n = 6
    bins = np.zeros(n, dtype=STANDALONE_DTYPE)
    bins["wavelength_nm"] = np.linspace(400, 700, n)
    bins["diffuse"], bins["collimated"], bins["rho_black"] = 2e5, 8e5, 0.03
    bins["black"], bins["white"], bins["open"] = 2e4, 1e5, 2e5
    bins["alpha"], bins["sigma_t"], bins["g"] = 0.9, 4.0, 0.6
    bins["capture_flags"][0] = int(CaptureFlag.NO_REFERENCE_LIGHT)
    bins["capture_flags"][5] = int(CaptureFlag.SATURATED)
    for k in (0, 5):
        bins["alpha"][k] = bins["sigma_t"][k] = bins["g"][k] = np.nan
        bins["fit_flags"][k] = 1
    return StandaloneResult(status, 7, bins, 0.99, 0.4, 0x1234ABCD, 0, {"black": 16000, "white": 8000, "open": 2000},
                            lamp_levels or {"panel_left": 1.001, "panel_right": 0.999, "collimated": 1.0})


def test_a_standalone_result_is_written_as_the_devices_measurement(tmp_path, table):
    m = measurement_of(_result(), table, "A", InstrumentInfo((0, 1, 0), 5, 1, 2))
    r = m.captures[0].reflectances
    np.testing.assert_allclose(r.I_b[1:5], 0.1)
    np.testing.assert_allclose(r.I_w[1:5], 0.5)
    np.testing.assert_allclose(r.I_c[1:5], 0.25)
    assert np.isnan(r.I_b[[0, 5]]).all() and r.flags[5] == int(CaptureFlag.SATURATED)
    assert np.isnan(m.calibration.diffuse[0]) and m.calibration.rho_white == pytest.approx(0.99)
    np.testing.assert_allclose(m.parameters.alpha[1:5], 0.9, rtol=1e-7)  # the device's fit, not fitted again
    assert np.isnan(m.parameters.alpha_std).all()
    out = write_measurement(tmp_path, m, label="press", figure=False, medium=False)
    meta = json.loads((out / "measurement.json").read_text())
    assert meta["fitted_on"] == "device" and meta["hostless"] is True and meta["method"] == "lut"
    assert meta["standalone"]["integration_us"] == {"black": 16000, "white": 8000, "open": 2000}
    assert meta["device_map_table"] == {"slot": "A", "crc32": "0x1234abcd", "length": None, "version": None,
                                        "matches_fit_table": True, "map": table.name}
    assert meta["maps"] == [table.name]
    for name in ("calibration.csv", "raw_black.csv", "reflectances.csv", "parameters.csv"):
        assert (out / name).is_file()


@pytest.mark.parametrize("status, message", [
    (regs.StandaloneStatus.CALIBRATED, "was a calibration: insert a sample and press again"),
    (regs.StandaloneStatus.ERROR_NO_CALIBRATION, "ended error_no_calibration: it holds no measurement"),
])
def test_a_last_press_that_was_no_measurement_is_one_clear_error(status, message):
    class Device:
        def standalone_result(self):
            return _result(status)

    with pytest.raises(DeviceError, match=message):
        read_standalone(Device())  # type: ignore[arg-type]


def test_the_devices_white_reference_is_the_hosts():
    assert regs.BY_NAME["white_reference_reflectance"].default == pytest.approx(HostSettings().white_reference)


def test_a_press_whose_lamps_changed_is_recorded_and_says_recalibrate(tmp_path, table):
    levels = {"panel_left": 0.9, "panel_right": 0.9, "collimated": float("nan")}
    result = _result(regs.StandaloneStatus.LAMP_CHANGED, levels)
    advice = recalibrate_advice(result)
    assert advice is not None and advice.startswith("RECALIBRATE: ")
    assert "the left diffuse panel gave 90.0% of its light at the calibration" in advice
    assert "right diffuse panel gave 90.0%" in advice and "collimated" not in advice  # NaN: not compared
    assert "trimeter device standalone calibrate" in advice
    out = write_measurement(tmp_path, measurement_of(result, table, "A", InstrumentInfo((0, 1, 0), 5, 1, 2)),
                            figure=False, medium=False)
    meta = json.loads((out / "measurement.json").read_text())["standalone"]
    assert meta["status"] == "lamp_changed" and meta["recalibrate"] is True
    assert meta["lamp_levels"] == {"panel_left": pytest.approx(0.9), "panel_right": pytest.approx(0.9),
                                   "collimated": None}
    assert recalibrate_advice(_result()) is None
    assert recalibrate_advice(_result(regs.StandaloneStatus.FLAGGED)) is None


def test_the_lamp_tolerance_bounds_the_bias_it_claims():
    """registers.toml, enums.standalone_lamp: a lamp dimmed by the tolerance since the calibration moves α by
    about a third of it (the panels: I_b and I_w alike; the beam: I_c) and σt by up to all of it (the beam),
    on the shipped device table, for the twin's materials over 420-720 nm."""
    from trimeter.formats.device_table import DeviceTable
    from trimeter.inversion import native
    from trimeter.paths import REPO_ROOT
    from trimeter.twin.optics import Optics, material_names

    table = DeviceTable.load(REPO_ROOT / "maps" / "device-n1.5-l0.4.tlut")
    fitter = native.TableFitter(table.to_bytes())
    optics = Optics()
    band = (optics.wavelengths_nm > 420) & (optics.wavelengths_nm < 720)
    d = STANDALONE_LAMP_TOLERANCE
    worst = {"alpha_panels": 0.0, "alpha_beam": 0.0, "sigma_t_beam": 0.0, "sigma_t_panels": 0.0}
    for name in material_names():
        optics.insert_sample(name, table.thickness_mm)
        s = optics.sample
        rho_b = np.broadcast_to(np.asarray(optics.rho_black, dtype=float), s.I_b.shape)
        alpha, sigma_t, _, flags = fitter.fit(s.I_b, s.I_w, s.I_c, rho_b, optics.rho_white)
        panels = fitter.fit(s.I_b * (1 - d), s.I_w * (1 - d), s.I_c, rho_b, optics.rho_white)
        beam = fitter.fit(s.I_b, s.I_w, s.I_c * (1 - d), rho_b, optics.rho_white)
        ok = band & (flags == 0) & (panels[3] == 0) & (beam[3] == 0)
        assert ok.sum() > 100
        changes = {"alpha_panels": panels[0] - alpha, "alpha_beam": beam[0] - alpha,
                   "sigma_t_panels": panels[1] / sigma_t - 1, "sigma_t_beam": beam[1] / sigma_t - 1}
        for key, change in changes.items():
            worst[key] = max(worst[key], float(np.percentile(np.abs(change[ok]), 95)))
    print(f"a lamp {d:.0%} off its calibrated light: |Δα| p95 ≤ {worst['alpha_panels']:.4f} (panels), "
          f"{worst['alpha_beam']:.4f} (beam); |Δσt|/σt p95 ≤ {worst['sigma_t_panels']:.2%} (panels), "
          f"{worst['sigma_t_beam']:.2%} (beam)")
    assert 0.2 * d < worst["alpha_panels"] < 0.4 * d and worst["alpha_beam"] < 0.4 * d
    assert 0.5 * d < worst["sigma_t_beam"] < 1.1 * d and worst["sigma_t_panels"] < 0.1 * d
