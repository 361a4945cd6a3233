"""The press-button service against fakes: first press calibrates, the next measures and writes a
results directory; a device reset makes the calibration stale; a failed measurement writes nothing
and the LED says so."""

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from hil_support import HIL_MAP
from trimeter import registers as regs
from trimeter.device.client import Device
from trimeter.domain import Sample
from trimeter.formats.appearance import AppearanceMap
from trimeter.sequences.service import Service, calibration_is_stale  # noqa: F401
from trimeter.sequences.settings import HostSettings

WL = np.linspace(420, 720, 61)


@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    amap = AppearanceMap.load(HIL_MAP)
    fake = FakeInstrument(busy_polls=1)
    rho_b = 0.03 + 0.05 * (WL > 650)
    optics = FakeOptics(WL, diffuse=np.full(WL.size, 3e6), collimated=np.full(WL.size, 5e6), rho_black=rho_b,
                        rho_white=0.99)
    spec = FakeSpectrometer(fake, optics)
    settings = HostSettings()
    settings.set("results_dir", str(tmp_path / "results"))
    settings.set("map", str(amap.path))
    settings.set("warmup_interval_s", 2)
    events = []
    service = Service(lambda: Device(fake), lambda: spec, settings, on_event=events.append)
    truth = (np.linspace(0.6, 0.99, WL.size), np.linspace(2, 5, WL.size), np.full(WL.size, 0.5))
    sample = amap.query(*truth, rho_b, 0.99)
    return service, fake, optics, events, truth, sample, tmp_path


def test_press_calibrates_then_measures_and_writes_results(rig):
    service, fake, optics, events, truth, sample, tmp = rig
    service.connect()
    assert service.poll_once() is None  # no press yet
    fake.press_button()
    assert service.poll_once() == "calibrated"
    assert fake.get("status_pattern") == regs.StatusPattern.ON
    service.close()
    service.connect()  # a reconnect with the lamps still on keeps the calibration
    optics.sample = sample
    fake.press_button()
    assert service.poll_once() == "measured"
    out = service.last_result
    assert out.parent == tmp / "results" and (out / "parameters.csv").exists()
    p = service.last_parameters
    np.testing.assert_allclose(p.alpha, truth[0], atol=0.01)
    np.testing.assert_allclose(p.sigma_t, truth[1], rtol=0.01)
    np.testing.assert_allclose(p.g, truth[2], atol=0.02)
    assert [e.kind for e in events if e.kind in ("calibrating", "warmed_up", "calibrated", "measured")] == \
        ["calibrating", "warmed_up", "calibrated", "measured"]
    assert service.last_advice == []  # a well-conditioned sample: nothing to advise


def test_a_thick_dark_sample_gets_advice_in_the_log_and_the_results(rig):
    """Bins the fit flags UNDERDETERMINED come with what to do about them: logged before the results
    line, and kept in measurement.json."""
    import json

    service, fake, optics, events, truth, sample, tmp = rig
    amap = AppearanceMap.load(HIL_MAP)
    red = WL > 600  # dark and optically thick there (σt·ℓ = 5); well-conditioned elsewhere (the rig's truth)
    service.connect()
    fake.press_button()
    assert service.poll_once() == "calibrated"
    optics.sample = amap.query(np.where(red, 0.2, truth[0]), np.where(red, 5 / amap.thickness_mm, truth[1]),
                               truth[2], 0.03 + 0.05 * (WL > 650), 0.99)
    fake.press_button()
    assert service.poll_once() == "measured"
    flagged = int(np.count_nonzero(service.last_parameters.flags & 1024))
    assert flagged >= np.count_nonzero(WL > 620)  # the dark bins, nearly all of them
    # (with the capture's noise some of those bins also reach the map's α = 0 edge: a second note)
    assert service.last_advice[0].startswith(f"{flagged} of {WL.size} bins are UNDERDETERMINED")
    n = len(service.last_advice)
    assert [e.kind for e in events][-n - 1:] == ["advice"] * n + ["measured"]
    meta = json.loads((service.last_result / "measurement.json").read_text())
    assert meta["advice"] == service.last_advice


def test_connect_warns_when_the_device_ignored_its_saved_configuration(rig):
    service, fake, optics, events, truth, sample, tmp = rig
    service.connect()
    assert not [e for e in events if e.kind == "warning"]
    service.close()
    fake._set("ir", regs.BY_NAME["config_source"], regs.ConfigSource.OTHER_REGISTER_MAP)
    service.connect()
    warnings = [e.message for e in events if e.kind == "warning"]
    assert len(warnings) == 1 and "another register map" in warnings[0] and "config import" in warnings[0]


def test_reset_makes_the_calibration_stale_and_is_not_a_press(rig):
    service, fake, optics, events, truth, sample, tmp = rig
    service.connect()
    fake.press_button()
    service.poll_once()
    fake.reset()
    assert service.poll_once() == "reset"
    assert fake.get("led_panel_left_on")  # lamps switched back on
    fake.press_button()
    assert service.poll_once() == "calibrated"
    assert any(e.kind == "calibrating" and "reset" in e.message for e in events)


def test_failed_measurement_writes_nothing_and_shows_fast_blink(rig):
    service, fake, optics, events, truth, sample, tmp = rig
    service.connect()
    fake.press_button()
    service.poll_once()
    optics.sample = sample
    service.settings.set("map", str(tmp / "missing.tmap"))  # an impossible set-up: refused, not crashed
    fake.press_button()
    assert service.poll_once() == "failed"
    assert fake.get("status_pattern") == regs.StatusPattern.FAST_BLINK
    assert not (tmp / "results").exists()
    assert events[-1].kind == "failed" and "missing.tmap" in events[-1].message


def test_calibration_staleness_rules():
    from trimeter.domain import Calibration

    cal = Calibration(WL, WL, WL, WL, 0.99, np.zeros(WL.size, np.int32), device_time_s=100.0)
    assert calibration_is_stale(None, 5, 1800) == "no calibration yet"
    assert calibration_is_stale(cal, 50, 1800) == "the device was reset since the calibration"
    assert calibration_is_stale(cal, 1000, 1800) is None
    assert "old" in calibration_is_stale(cal, 2000, 1800)


def test_two_thicknesses_are_captured_in_turn_fitted_and_combined(rig):
    service, fake, optics, events, truth, sample, tmp = rig
    service.connect()
    fake.press_button()
    service.poll_once()
    optics.sample = sample
    amap = AppearanceMap.load(HIL_MAP)
    swaps = []
    # the same map twice stands in for two thicknesses: what is tested is the plumbing around trimeter.fit
    path = service.measure([Sample(0.4, amap), Sample(0.4, amap)], between=swaps.append, label="two")
    assert swaps == [0.4]
    names = {p.name for p in path.iterdir()}
    assert {"raw_black_1_0.4mm.csv", "raw_black_2_0.4mm.csv", "reflectances_2_0.4mm.csv", "parameters_1_0.4mm.csv",
            "parameters_2_0.4mm.csv", "parameters.csv"} <= names
    np.testing.assert_allclose(service.last_parameters.sigma_t, truth[1], rtol=0.01)


def _two_sample_service(rig, **settings):
    """The rig's service set to two samples (the same map twice stands in for two thicknesses: what is
    tested is the press-button flow), calibrated, with the sample in the optics."""
    service, fake, optics, events, truth, sample, tmp = rig
    service.settings.set("second_thickness_mm", 0.4)
    service.settings.set("second_map", service.settings.map)
    for key, value in settings.items():
        service.settings.set(key, value)
    service.connect()
    fake.press_button()
    assert service.poll_once() == "calibrated"
    optics.sample = sample
    return rig


def _second_sample_on_press(fake, optics, second, *, press=True, reset=False):
    """When the service double-blinks for the next sample: swap the optics to `second` and press (or
    reset the device) once, as a user would."""
    done = []

    def on_request(f):
        if not done and f.get("status_pattern") == regs.StatusPattern.DOUBLE_BLINK:
            done.append(True)
            optics.sample = second
            if reset:
                f.reset()
            elif press:
                f.press_button()
    fake.on_request = on_request
    return done


def test_serve_with_two_samples_waits_for_the_second_press_and_combines(rig):
    service, fake, optics, events, truth, sample, tmp = _two_sample_service(rig)
    swapped = _second_sample_on_press(fake, optics, sample)
    fake.press_button()
    assert service.poll_once() == "measured"
    assert swapped and fake.get("status_pattern") == regs.StatusPattern.ON
    names = {p.name for p in service.last_result.iterdir()}
    assert {"parameters_1_0.4mm.csv", "parameters_2_0.4mm.csv", "parameters.csv"} <= names
    np.testing.assert_allclose(service.last_parameters.alpha, truth[0], atol=0.01)
    assert [e.kind for e in events][-4:] == ["press", "next_sample", "press", "measured"]
    assert service.poll_once() is None  # the second sample's press was consumed, not a new measurement


def _written_alone(service, truth):
    """The last result holds the first sample only, fitted, and says why."""
    import json

    names = {p.name for p in service.last_result.iterdir()}
    assert "parameters.csv" in names and not any(n.startswith("parameters_2") for n in names)
    meta = json.loads((service.last_result / "measurement.json").read_text())
    assert meta["thicknesses_mm"] == [0.4] and "only 1 of 2 samples" in meta["incomplete"]
    np.testing.assert_allclose(service.last_parameters.sigma_t, truth[1], rtol=0.01)


def test_serve_keeps_the_first_sample_when_no_second_press_comes(rig):
    service, fake, optics, events, truth, sample, tmp = _two_sample_service(rig, swap_timeout_s=0.2)
    _second_sample_on_press(fake, optics, sample, press=False)
    fake.press_button()
    assert service.poll_once() == "incomplete"  # written, but not what was asked for
    assert fake.get("status_pattern") == regs.StatusPattern.FAST_BLINK
    assert events[-1].kind == "failed" and "no press within 0.2 s" in events[-1].message
    _written_alone(service, truth)


def test_a_reset_while_waiting_for_the_second_sample_keeps_the_first_and_reconnects(rig):
    from trimeter.errors import DeviceError

    service, fake, optics, events, truth, sample, tmp = _two_sample_service(rig)
    _second_sample_on_press(fake, optics, sample, reset=True)
    fake.press_button()
    with pytest.raises(DeviceError, match="reset while waiting"):
        service.poll_once()  # serve() reconnects on a DeviceError; the reset makes the calibration stale
    _written_alone(service, truth)
    service.connect()
    assert fake.get("status_pattern") == regs.StatusPattern.TRIPLE_BLINK  # the reset: empty the holder and press
    fake.press_button()
    assert service.poll_once() == "refused"  # the second sample is still in the holder
    optics.sample = None
    fake.press_button()
    assert service.poll_once() == "calibrated"


def test_second_sample_settings_are_checked():
    from trimeter.errors import InputError

    s = HostSettings()
    assert s.serve_samples == [(0.4, None)]
    with pytest.raises(InputError, match="second_thickness_mm"):
        s.set("second_thickness_mm", -0.8)
    with pytest.raises(InputError, match="swap_timeout_s"):
        s.set("swap_timeout_s", 0)
    for bad in ("inf", "nan", float("-inf")):  # no thickness or time is infinite
        with pytest.raises(InputError, match="not a finite number"):
            s.set("second_thickness_mm", bad)
    for key, bad in (("frames", "1e400"), ("frames", True), ("map", {"a": 1}), ("port", ["COM1"]), ("map", None)):
        with pytest.raises(InputError, match=key):  # what a web request's JSON may hold: no OverflowError, no str()
            s.set(key, bad)
    s.set("second_thickness_mm", 0.8)
    s.set("map", "a.tmap")
    assert s.serve_samples == [(0.4, "a.tmap"), (0.8, None)]


def test_a_poll_that_the_link_fails_says_so_at_its_first_failed_try_and_again_when_it_answers(rig):
    from trimeter.device.transport import LinkError
    from trimeter.sequences.steps import RetryPolicy

    service, fake, optics, events, truth, sample, tmp = rig
    service.retry = RetryPolicy(attempts=3, backoff_s=0.0)
    service.connect()
    transport = service.device.transport
    read_words, failures = transport.read_words, []

    def flaky(*args, **kwargs):
        if len(failures) < 2:
            failures.append(len(events))
            raise LinkError("no valid reply")
        return read_words(*args, **kwargs)

    transport.read_words = flaky
    transport.reopen = lambda: None
    assert service.poll_once() is None
    kinds = [e.kind for e in events]
    # told once, at the first failed try (before the retries), and once when the device answers again
    assert kinds.count("link_lost") == 1 and kinds.count("link_restored") == 1
    assert kinds.index("link_lost") == failures[0] and kinds.index("link_restored") > kinds.index("link_lost")
