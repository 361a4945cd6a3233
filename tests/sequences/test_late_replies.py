"""A reply to an earlier poll arriving late looks like this poll's (RTU has no transaction ids) and carries an
older uptime: the service believes a reset only when a second poll says so too."""

from __future__ import annotations

from types import SimpleNamespace

from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings


class _Polls:
    """A device whose uptime replies come from `uptimes` in turn (the lamps stay on)."""

    def __init__(self, uptimes: list[int]):
        self.uptimes = list(uptimes)
        self.transport = SimpleNamespace()

    def read_many(self, *names):
        return {"button_events": 7, "uptime_s": self.uptimes.pop(0)}

    def read(self, name):
        assert name == "led_panel_left_on"
        return True


def _service(tmp_path, monkeypatch, uptimes: list[int]) -> tuple[Service, list]:
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    events: list = []
    service = Service(lambda: None, lambda: None, HostSettings(), on_event=events.append)
    service.device = _Polls(uptimes)
    service._button, service._uptime = 7, 84
    monkeypatch.setattr(service, "calibration_due", lambda uptime: None)
    return service, events


def test_a_late_reply_with_an_older_uptime_is_no_reset(tmp_path, monkeypatch):
    service, events = _service(tmp_path, monkeypatch, [45, 85])   # 45: the late reply; 85: the line's truth
    assert service.poll_once() is None
    assert [e.kind for e in events if e.kind == "reset"] == [] and service.device_uptime_s == 85


def test_a_reset_both_polls_see_is_one(tmp_path, monkeypatch):
    service, events = _service(tmp_path, monkeypatch, [3, 3])
    calls = []
    monkeypatch.setattr(service, "_open_spectrometer", lambda: calls.append("spectrometer"))
    monkeypatch.setattr(service, "_show", lambda pattern: None)
    monkeypatch.setattr(service, "_ask_empty_holder", lambda reason: calls.append(reason))
    monkeypatch.setattr(service, "_on_device", lambda what, action: action(service.device)
                        if what != "switching the lamps on" else None)
    assert service.poll_once() == "reset"
    assert [e.kind for e in events] == ["reset"] and "the device was reset" in calls[-1]
