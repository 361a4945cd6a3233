"""The job worker without an instrument: what a failing job leaves behind."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
from types import SimpleNamespace

import pytest

from trimeter.errors import DeviceError, InputError
from trimeter.web.app import create_app
from trimeter.web.server import WebServer
from trimeter.web.history import History
from trimeter.sequences.service import Event
from trimeter.web.jobs import Jobs, LinkDown


def _jobs() -> Jobs:
    return Jobs(SimpleNamespace(on_event=lambda event: None, on_progress=None))


@pytest.mark.parametrize("error, message", [(ValueError("bad column"), "internal error: ValueError: bad column"),
                                            (InputError("no such map"), "no such map")])
def test_a_job_that_raises_fails_alone_and_frees_the_worker(error, message):
    jobs = _jobs()
    finished = []
    jobs.listeners.append(lambda record: finished.append(record["job"]["state"]) if record["type"] == "job" else None)

    def broken(job):
        raise error

    job = jobs.submit("refit", {}, broken)
    jobs.between_polls(None)  # Service.serve would end on anything but a DeviceError raised here
    assert (job.state, job.outcome, jobs.current) == ("failed", "failed", None)
    assert message in job.message
    assert finished == ["queued", "failed"]
    assert jobs.submit("refit", {}, lambda job: "refitted") is jobs.current  # not Busy


def test_a_device_error_still_reaches_the_loop_that_reconnects():
    jobs = _jobs()

    def lost(job):
        raise DeviceError("no answer")

    job = jobs.submit("measure", {}, lost)
    with pytest.raises(DeviceError):
        jobs.between_polls(None)
    assert (job.state, jobs.current) == ("failed", None)


def test_a_device_call_after_the_loop_stopped_is_503_at_once(tmp_path):
    jobs = Jobs(SimpleNamespace(on_event=lambda event: None, on_progress=None, device=object()))
    jobs.stopped = "no device port configured"
    token = "t" * 32
    server = WebServer(create_app(jobs, History(tmp_path / "results", tmp_path / "h.sqlite"), token),
                       "127.0.0.1", 0).start()
    try:
        request = urllib.request.Request(server.url + "/api/config", headers={"Authorization": f"Bearer {token}"})
        start = time.monotonic()
        with pytest.raises(urllib.error.HTTPError) as answer:
            urllib.request.urlopen(request, timeout=30)
        assert time.monotonic() - start < 5  # not the device call's timeout
        assert answer.value.code == 503
        assert "no device port configured" in json.loads(answer.value.read())["error"]["message"]
    finally:
        server.close()


def test_a_job_left_when_the_loop_stops_is_failed_not_running_forever():
    def serve(stop, between_polls):
        raise InputError("no device port configured")

    jobs = Jobs(SimpleNamespace(on_event=lambda event: None, on_progress=None, serve=serve))
    job = jobs.submit("measure", {}, lambda job: "measured")
    jobs.start()
    jobs.stop(timeout_s=5)
    assert jobs.stopped == "no device port configured"
    assert (job.state, jobs.current) == ("failed", None)
    assert "no device port configured" in job.message


def test_a_history_index_failure_does_not_reach_the_measurement():
    def index(path):
        raise OSError("database or disk is full")

    jobs = Jobs(SimpleNamespace(on_event=lambda event: None, on_progress=None), on_measurement=index)
    seen = []
    jobs.listeners.append(seen.append)
    jobs.on_event(Event("measured", "measured", {"path": "/results/20260301T000000Z-red"}))
    assert seen[-1]["data"]["measurement"] == "20260301T000000Z-red"  # still told to the page


def test_work_apart_runs_beside_the_queue_one_at_a_time():
    import threading

    from trimeter.web.jobs import Busy

    jobs = _jobs()
    release = threading.Event()
    apart = jobs.run_apart("refit", {}, lambda job: (release.wait(10), "refitted")[1])
    assert jobs.current is None and jobs.job(apart.id) is apart and apart.state == "running"
    queued = jobs.submit("measure", {}, lambda job: "measured")   # the instrument's queue is free meanwhile
    assert jobs.current is queued
    with pytest.raises(Busy):
        jobs.run_apart("refit", {}, lambda job: "refitted")
    release.set()
    deadline = time.monotonic() + 10
    while apart.state == "running" and time.monotonic() < deadline:
        time.sleep(0.01)
    assert apart.state == "done" and jobs.apart is None and jobs.current is queued

    def lost_link(job):
        raise DeviceError("the link is gone")

    failed = jobs.run_apart("refit", {}, lost_link)
    while failed.state == "running" and time.monotonic() < deadline:
        time.sleep(0.01)
    assert failed.state == "failed" and "link is gone" in failed.message


def test_queued_work_expires_with_the_link_and_none_is_taken_until_it_answers():
    jobs = _jobs()
    ran = []
    job = jobs.submit("calibrate", {"holder_empty": True}, lambda job: ran.append(job) or "calibrated")
    jobs.on_event(Event("link_lost", "the device stopped answering while polling the button; trying again"))
    assert (job.state, job.outcome, jobs.current) == ("failed", "expired", None)
    assert "expired before it ran: the device stopped answering" in job.message
    with pytest.raises(LinkDown, match="the device is not answering"):
        jobs.submit("calibrate", {"holder_empty": True}, lambda job: "calibrated")
    jobs.on_event(Event("link_restored", "the device answers again"))
    jobs.between_polls(None)
    assert ran == []  # the expired confirmation never runs, after the link came back either
    again = jobs.submit("calibrate", {"holder_empty": True}, lambda job: ran.append(job) or "calibrated")
    jobs.between_polls(None)
    assert ran == [again] and again.state == "done"
    jobs.on_event(Event("reconnecting", "device link problem; reconnecting"))
    with pytest.raises(LinkDown):
        jobs.submit("measure", {}, lambda job: "measured")


def test_status_drops_the_device_as_soon_as_the_link_is_lost():
    identity = SimpleNamespace(vendor_id=1, model_id=2, firmware_version=(0, 1, 0), regmap_hash=3)
    service = SimpleNamespace(on_event=lambda event: None, on_progress=None, pattern="on", calibration=None,
                              device=SimpleNamespace(identity=identity), device_uptime_s=5.0, last_result=None,
                              settings=SimpleNamespace(port="/dev/ttyX", serve_samples=[]))
    jobs = Jobs(service)
    jobs.on_event(Event("connected", "connected (firmware 0.1.0)"))
    assert jobs.status()["device"]["firmware"] == "0.1.0"
    jobs.on_event(Event("link_lost", "the device stopped answering; trying again"))
    assert jobs.status()["device"] is None and jobs.status()["state"] == "connecting"
    jobs.on_event(Event("link_restored", "the device answers again"))
    assert jobs.status()["device"]["firmware"] == "0.1.0"


def test_work_asked_for_while_the_link_is_down_is_a_503_with_retry_after(tmp_path):
    jobs = Jobs(SimpleNamespace(on_event=lambda event: None, on_progress=None, pattern="on"))
    jobs.on_event(Event("link_lost", "the device stopped answering; trying again"))
    token = "t" * 32
    server = WebServer(create_app(jobs, History(tmp_path / "results", tmp_path / "h.sqlite"), token),
                       "127.0.0.1", 0).start()
    try:
        request = urllib.request.Request(server.url + "/api/calibrate", data=b"{}", method="POST",
                                         headers={"Authorization": f"Bearer {token}",
                                                  "Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as answer:
            urllib.request.urlopen(request, timeout=30)
        assert answer.value.code == 503 and answer.value.headers["Retry-After"]
        assert "the device is not answering" in json.loads(answer.value.read())["error"]["message"]
    finally:
        server.close()
