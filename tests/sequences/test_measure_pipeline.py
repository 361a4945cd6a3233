"""The one-shot pipelines as plain functions, without the press-button service: capture → fit → write
from (thickness, map) samples, the one door into the fit that refuses bad input before any light, and
calibrating."""

import json

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from hil_support import HIL_MAP
from trimeter.device.client import Device
from trimeter.domain import InstrumentInfo, Sample
from trimeter.errors import CheckError, DeviceError, InputError, TrimeterError
from trimeter.formats.appearance import AppearanceMap
from trimeter.sequences import Runner, calibration
from trimeter.sequences.calibrate import calibrate, previous_calibration
from trimeter.sequences.measure import measure, prepare_fit
from trimeter.sequences.settings import HostSettings

WL = np.linspace(420, 720, 61)


@pytest.fixture(scope="module")
def amap():
    return AppearanceMap.load(HIL_MAP)


@pytest.fixture
def rig(tmp_path, monkeypatch, amap):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    fake = FakeInstrument(busy_polls=1)
    rho_b = np.full(WL.size, 0.03)
    optics = FakeOptics(WL, diffuse=np.full(WL.size, 3e6), collimated=np.full(WL.size, 5e6), rho_black=rho_b,
                        rho_white=0.99)
    runner = Runner(Device(fake), FakeSpectrometer(fake, optics), sleep=lambda s: None)
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    truth = (np.linspace(0.6, 0.99, WL.size), np.linspace(2, 5, WL.size), np.full(WL.size, 0.5))
    optics.sample = amap.query(*truth, rho_b, 0.99)
    settings = HostSettings()
    settings.set("results_dir", str(tmp_path / "results"))
    return runner, cal, settings, truth


def test_two_samples_are_captured_fitted_and_written_by_one_call(rig, amap):
    runner, cal, settings, truth = rig
    swaps = []
    outcome = measure(runner, cal, [Sample(0.4, amap), Sample(0.4, amap)], settings, label="pair",
                      between=swaps.append)
    assert swaps == [0.4] and outcome.stopped is None and outcome.incomplete is None
    np.testing.assert_allclose(outcome.parameters.sigma_t, truth[1], rtol=0.01)
    assert len(outcome.measurement.per_thickness) == 2
    meta = json.loads((outcome.path / "measurement.json").read_text())
    assert meta["maps"] == [amap.name, amap.name] and meta["thicknesses_mm"] == [0.4, 0.4]
    assert meta["label"] == "pair" and meta["method"] == settings.method and "fit_wall_s" in meta["timing"]
    assert (outcome.path / "parameters_1_0.4mm.csv").is_file() and (outcome.path / "parameters_2_0.4mm.csv").is_file()


def test_a_second_sample_that_never_comes_leaves_the_first_written_and_marked_incomplete(rig, amap):
    runner, cal, settings, _ = rig

    def never(thickness):
        raise TrimeterError("no press within 1 s")

    outcome = measure(runner, cal, [Sample(0.4, amap), Sample(0.4, amap)], settings, between=never)
    assert isinstance(outcome.stopped, TrimeterError) and outcome.incomplete.startswith("only 1 of 2 samples")
    meta = json.loads((outcome.path / "measurement.json").read_text())
    assert meta["thicknesses_mm"] == [0.4] and meta["incomplete"] == outcome.incomplete


def test_bad_input_is_refused_before_any_light_is_measured(rig, amap, monkeypatch):
    runner, cal, settings, _ = rig
    monkeypatch.setattr(runner, "run", lambda plan: pytest.fail("a capture was started"))
    with pytest.raises(DeviceError, match="no calibration"):
        measure(runner, None, [Sample(0.4, amap)], settings)
    with pytest.raises(InputError, match="not the declared 0.8 mm"):
        measure(runner, cal, [Sample(0.8, amap)], settings)
    settings.set("method", "lut")
    with pytest.raises(InputError, match="method"):
        prepare_fit([Sample(0.4, amap)], "nonesuch")
    with pytest.raises(InputError, match="no sample"):
        prepare_fit([], "lut")
    broken = cal.__class__(**{**vars(cal), "rho_black": np.full(WL.size, 0.5)})
    with pytest.raises(CheckError, match="calibration fails its checks"):
        measure(runner, broken, [Sample(0.4, amap)], settings)


def test_a_prepared_fit_takes_only_captures_of_its_own_samples(rig, amap):
    runner, cal, settings, _ = rig
    outcome = measure(runner, cal, [Sample(0.4, amap)], settings)
    other = prepare_fit([Sample(0.4, amap)], "lut")
    with pytest.raises(InputError, match="not of the samples"):
        other.fit(outcome.measurement.captures)
    assert other.fit_table_bytes()[:4] and prepare_fit([Sample(0.4, amap)], "paper").fit_table_bytes() is None


def test_calibrate_saves_a_checked_calibration_and_refuses_a_sample_in_the_holder(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    fake = FakeInstrument(busy_polls=1)
    optics = FakeOptics(WL, diffuse=np.full(WL.size, 3e6), collimated=np.full(WL.size, 5e6),
                        rho_black=np.full(WL.size, 0.03), rho_white=0.99)
    runner = Runner(Device(fake), FakeSpectrometer(fake, optics), sleep=lambda s: None)
    settings = HostSettings()
    instrument = InstrumentInfo((0, 1, 0), 0xC7026EF1, vendor_id=1, model_id=2)
    cal = calibrate(runner, settings, instrument=instrument, warm=False)
    assert previous_calibration(settings).device == instrument and np.array_equal(
        previous_calibration(settings).rho_black, cal.rho_black, equal_nan=True)
    optics.sample = (np.full(WL.size, 0.2), np.full(WL.size, 0.5), np.full(WL.size, 0.1))
    with pytest.raises(CheckError, match="holder does not look empty"):
        calibrate(runner, settings, instrument=instrument, warm=False)
    assert previous_calibration(settings).created_utc == cal.created_utc   # the good one is kept
