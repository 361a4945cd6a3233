"""Nothing garbage is reported as a measurement (against fakes): a calibration with a sample in the holder
or with the slots swapped is refused, one that disagrees with the previous good calibration too (unless
forced); `serve` asks for an empty holder before it calibrates; a lamp that fails after the calibration
refuses the shot and nothing is written, while genuinely black or opaque samples still measure; a map
for another thickness than the declared one is an error."""

import json

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from hil_support import HIL_MAP
from trimeter import registers as regs
from trimeter.device.client import Device
from trimeter.errors import CheckError, InputError
from trimeter.formats.appearance import AppearanceMap
from trimeter.sequences.calibrate import previous_calibration
from trimeter.sequences.checks import calibration_problems, shot_problems, surface_floor
from trimeter.domain import Calibration, Reflectances, Sample
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings

WL = np.linspace(420, 720, 61)
RHO_B = 0.03 + 0.05 * (WL > 650)


@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    amap = AppearanceMap.load(HIL_MAP)
    fake = FakeInstrument(busy_polls=1)
    optics = FakeOptics(WL, diffuse=np.full(WL.size, 3e6), collimated=np.full(WL.size, 5e6), rho_black=RHO_B,
                        rho_white=0.99)
    spec = FakeSpectrometer(fake, optics, noise=2.0)
    settings = HostSettings()
    settings.set("results_dir", str(tmp_path / "results"))
    settings.set("map", str(amap.path))
    settings.set("warmup_interval_s", 2)
    events = []
    service = Service(lambda: Device(fake), lambda: spec, settings, on_event=events.append)
    return service, fake, optics, events, amap, tmp_path


def sample_of(amap, alpha, sigma_t, g):
    alpha, sigma_t, g, _ = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(sigma_t, float),
                                               np.asarray(g, float), WL)
    return amap.query(alpha, sigma_t, g, RHO_B, 0.99)


def cyan(amap):
    return sample_of(amap, np.linspace(0.6, 0.99, WL.size), np.linspace(2, 5, WL.size), 0.5)


def calibrated(rig):
    service, fake, optics, events, amap, tmp = rig
    service.connect()
    fake.press_button()
    assert service.poll_once() == "calibrated", [e.message for e in events]
    return service


def results(tmp):
    out = tmp / "results"
    return sorted(out.iterdir()) if out.exists() else []


# ------------------------------------------------------------------------------- calibration
def test_a_sample_in_the_holder_is_refused_before_the_warm_up_saying_what_was_seen(rig):
    service, fake, optics, events, amap, tmp = rig
    optics.sample = cyan(amap)
    service.connect()
    with pytest.raises(CheckError, match=r"ρ_black 0\.\d+ \(expected ≤ 0.12\): a sample seems to be in the holder"):
        service.calibrate()
    assert not [e for e in events if e.kind == "warmed_up"]  # refused before the warm-up
    assert not (service.settings.calibration_path / "calibration.json").exists()


def test_swapped_slots_are_refused(rig):
    service, fake, optics, events, amap, tmp = rig
    optics.rho_black, optics.rho_white = np.full(WL.size, 0.99), RHO_B  # the backgrounds in each other's slot
    service.connect()
    with pytest.raises(CheckError, match=r"ρ_black \d+(\.\d+)? is above the white reference's 0.99: the black "
                                         r"and white slots seem swapped"):
        service.calibrate()


def test_a_calibration_disagreeing_with_the_previous_good_one_is_refused_unless_forced(rig):
    service, fake, optics, events, amap, tmp = rig
    service.connect()
    first = service.calibrate()
    assert json.loads((service.settings.calibration_path / "calibration.json").read_text())["device"]["firmware"] \
        == list(regs.FIRMWARE_VERSION)  # stored with the identity of the instrument
    optics.collimated = optics.collimated * 0.5  # a replaced (dimmer) collimated LED
    with pytest.raises(CheckError, match=r"collimated beam is -50% against the previous good calibration.*--force"):
        service.calibrate()
    assert Calibration.load(service.settings.calibration_path).created_utc == first.created_utc  # kept
    cal = service.calibrate(force=True)
    np.testing.assert_allclose(cal.collimated, first.collimated * 0.5, rtol=0.01)
    assert calibration_problems(previous_calibration(service.settings), first) != []  # the new one is the reference now


def test_physical_bounds_of_a_calibration():
    ok = Calibration(WL, np.full(WL.size, 3e6), np.full(WL.size, 5e6), RHO_B.copy(), 0.99,
                     np.zeros(WL.size, np.int32), spectrometer={"saturation_counts": 65535.0}, dark_counts=1500.0)
    assert calibration_problems(ok) == [] and calibration_problems(ok, ok) == []
    dark = Calibration(**{**vars(ok), "flags": np.where(WL > 500, 4, 0).astype(np.int32)})
    assert "bins have usable light" in calibration_problems(dark)[0]
    leak = Calibration(**{**vars(ok), "dark_counts": 30000.0})
    assert "dark frames read 30000 counts (46% of full scale" in calibration_problems(leak)[0]


def test_a_corrupt_calibration_file_is_a_clear_error(rig):
    service, fake, optics, events, amap, tmp = rig
    service.connect()
    service.calibrate()
    path = service.settings.calibration_path / "calibration.json"
    meta = json.loads(path.read_text())
    for bad in ([1, 2], {**meta, "dark_counts": "lots"}, {**meta, "rho_white": None}):
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match="calibration in .*(unknown format|bad field)"):
            Calibration.load(service.settings.calibration_path)


# ------------------------------------------------------------------------------------- serve
def test_serve_with_a_stale_calibration_asks_for_an_empty_holder_and_waits(rig):
    service, fake, optics, events, amap, tmp = rig
    service = calibrated(rig)
    optics.sample = cyan(amap)
    service.settings.set("calibration_max_age_s", 1)
    fake.time_s += 5  # the calibration goes stale while the sample sits in the holder
    assert service.poll_once() is None  # no press: the LED asks at once
    assert fake.get("status_pattern") == regs.StatusPattern.TRIPLE_BLINK
    assert events[-1].kind == "empty_holder" and "empty the sample holder and press" in events[-1].message
    for _ in range(2):  # pressed with the sample still in: refused, and the LED keeps asking
        fake.press_button()
        assert service.poll_once() == "refused"
        assert fake.get("status_pattern") == regs.StatusPattern.TRIPLE_BLINK
        refusal = [e for e in events if e.kind == "refused"][-1].message
        assert "a sample seems to be in the holder — remove it" in refusal and "press the button again" in refusal
    assert not [e for e in events if e.kind == "warmed_up"][1:]  # never warmed up (nor calibrated) again
    optics.sample = None
    fake.press_button()
    assert service.poll_once() == "calibrated"
    assert fake.get("status_pattern") == regs.StatusPattern.ON


def test_a_press_meant_to_measure_never_calibrates(rig):
    """The calibration turns stale between two polls, just as the button is pressed to measure: that
    press only starts the asking."""
    service, fake, optics, events, amap, tmp = rig
    service = calibrated(rig)
    optics.sample = cyan(amap)
    service.settings.set("calibration_max_age_s", 1)
    fake.time_s += 5
    fake.press_button()
    assert service.poll_once() == "asked"
    assert fake.get("status_pattern") == regs.StatusPattern.TRIPLE_BLINK
    assert [e.kind for e in events][-1] == "empty_holder" and "calibrating" not in [e.kind for e in events][-3:]


# --------------------------------------------------------------------------------------- shots
@pytest.mark.parametrize("lamp", ["diffuse", "collimated"])
def test_a_lamp_failing_after_the_calibration_refuses_the_shot_and_writes_nothing(rig, lamp):
    service, fake, optics, events, amap, tmp = rig
    service = calibrated(rig)
    optics.sample = cyan(amap)
    setattr(optics, lamp, getattr(optics, lamp) * 0)
    fake.press_button()
    assert service.poll_once() == "failed"
    assert fake.get("status_pattern") == regs.StatusPattern.FAST_BLINK
    assert events[-1].kind == "failed" and "capture was refused, nothing was written" in events[-1].message
    assert ("the diffuse panels gave (almost) no light" if lamp == "diffuse" else "no material of the map explains") \
        in events[-1].message
    assert results(tmp) == []


@pytest.mark.parametrize("name, alpha, sigma_t", [("black", 0.0, 30.0), ("white opaque", 0.99, 30.0),
                                                  ("clear", 0.5, 0.3)])
def test_black_opaque_and_clear_samples_still_measure(rig, name, alpha, sigma_t):
    service, fake, optics, events, amap, tmp = rig
    service = calibrated(rig)
    optics.sample = sample_of(amap, alpha, sigma_t, 0.5)
    fake.press_button()
    assert service.poll_once() == "measured", events[-1].message
    assert len(results(tmp)) == 1


def test_shot_checks_name_the_bins_and_the_cause():
    amap = AppearanceMap.load(HIL_MAP)
    floor = surface_floor(amap, 0.99)
    assert 0.0 < floor < 0.1  # a front surface's reflection

    def refl(I_b, I_w, I_c):
        b, w, c = (np.full(WL.size, v, float) for v in (I_b, I_w, I_c))
        return Reflectances(WL, b, w, c, RHO_B, np.full(WL.size, 0.99), np.zeros(WL.size, np.int32))

    assert shot_problems(refl(0.2, 0.5, 0.3), amap) == []
    assert "I_w is under half the sample surface's own reflection" in shot_problems(refl(0.0, 0.004, 0.3), amap)[0]
    assert "I_b is above I_w" in shot_problems(refl(0.6, 0.5, 0.3), amap)[0]
    assert "I_c is above the calibrated beam" in shot_problems(refl(0.2, 0.5, 1.6), amap)[0]
    assert "no bin has a usable" in shot_problems(refl(np.nan, 0.5, 0.3), amap)[0]


# ----------------------------------------------------------------------------------- thickness
def test_a_map_for_another_thickness_than_the_declared_one_is_an_error(rig):
    service, fake, optics, events, amap, tmp = rig
    service = calibrated(rig)
    optics.sample = cyan(amap)
    with pytest.raises(InputError, match=r"map hil-ideal-l0.4 is for ℓ = 0.4 mm, not the declared 0.8 mm"):
        service.measure([Sample(0.8, amap)])
    path = service.measure([Sample(0.4, amap)])
    meta = json.loads((path / "measurement.json").read_text())
    assert meta["declared_thicknesses_mm"] == [0.4] and meta["map_thicknesses_mm"] == [0.4]


def test_a_saved_calibration_failing_its_checks_is_not_used(rig):
    """E.g. one taken with a sample in the holder before these checks existed: serve asks for a new one."""
    service, fake, optics, events, amap, tmp = rig
    bad = Calibration(WL, np.full(WL.size, 3e6), np.full(WL.size, 5e6), np.full(WL.size, 0.27), 0.99,
                      np.zeros(WL.size, np.int32), device_time_s=0.0)
    bad.save(service.settings.calibration_path)
    service = Service(service._open_device, service._open_spectrometer, service.settings, on_event=events.append)
    service.connect()
    assert fake.get("status_pattern") == regs.StatusPattern.TRIPLE_BLINK
    assert events[-1].kind == "empty_holder" and "the saved calibration fails its checks (ρ_black 0.27" in \
        events[-1].message
