"""A standalone result as a measurement (trimeter.sequences.standalone): the device's fit kept as is, the
reflectances its ratios of the same rates (NaN where it gave the fit no input), provenance saying it was
fitted on the device with no host; a last press that was no measurement is one clear error; the device's
white reference is the host's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hil_support import HIL_MAP
from trimeter import registers as regs
from trimeter.device.client import STANDALONE_DTYPE, StandaloneResult
from trimeter.domain import CaptureFlag, InstrumentInfo
from trimeter.errors import DeviceError
from trimeter.results.writer import write_measurement
from trimeter.sequences.settings import HostSettings
from trimeter.sequences.standalone import measurement_of, read_standalone


@pytest.fixture(scope="module")
def table():
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.table_builder import build_from_map

    return build_from_map(AppearanceMap.load(HIL_MAP))


def _result(status=regs.StandaloneStatus.DONE) -> StandaloneResult:
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
    return StandaloneResult(status, 7, bins, 0.99, 0.4, 0x1234ABCD, 0, {"black": 16000, "white": 8000, "open": 2000})


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
