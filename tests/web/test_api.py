"""The web API against the twin: calibrate and measure as the page does them, the history (search,
CSV, files, zip), refit into a new record, configuration, the event websocket, a webhook, two
clients at once, and bad input — each a clear 4xx, nothing changed, the service still working."""

from __future__ import annotations

import asyncio
import csv
import hashlib
import http.server
import io
import json
import threading
import zipfile
from concurrent.futures import ThreadPoolExecutor

import pytest

from conftest import web_instrument
from hil_support import SAMPLE, THICKNESS_MM
from trimeter.sequences.settings import HostSettings


class WebhookReceiver(http.server.ThreadingHTTPServer):
    def __init__(self):
        self.received: list[dict] = []
        outer = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self):
                outer.received.append(json.loads(self.rfile.read(int(self.headers["Content-Length"]))))
                self.send_response(204)
                self.end_headers()

            def log_message(self, *args):
                pass

        super().__init__(("127.0.0.1", 0), Handler)
        threading.Thread(target=self.serve_forever, daemon=True).start()


@pytest.fixture(scope="module")
def hook():
    receiver = WebhookReceiver()
    yield receiver
    receiver.shutdown()


@pytest.fixture(scope="module")
def web(tmp_path_factory, hook):
    with web_instrument(tmp_path_factory.mktemp("web"), webhook=f"http://127.0.0.1:{hook.server_port}/hook") as w:
        w.wait_state("asking_empty_holder")
        yield w


@pytest.fixture(scope="module")
def measured(web):
    """A calibration from the page, then one measurement of the twin's sample."""
    assert web.calibrate()["outcome"] == "calibrated"
    web.twin.control.insert_sample(SAMPLE, THICKNESS_MM)
    answer = web.call("POST", "/api/measure", {"label": "cyan", "thickness_mm": THICKNESS_MM})
    assert answer.status == 202 and answer.headers["Location"] == f"/api/jobs/{answer.json['job']['id']}"
    job = web.wait_job(answer.json["job"]["id"])
    assert job["outcome"] == "measured", job
    return job["measurement"]


def directory_digest(path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(path.iterdir())}


def test_every_api_call_needs_the_token_and_the_page_turns_it_into_a_cookie(web):
    assert web.call("GET", "/api/status", token=None).status == 401
    assert web.call("GET", "/api/openapi.json", token="wrong-" * 8).status == 401
    spec = web.call("GET", "/api/openapi.json").json
    assert spec["openapi"].startswith("3.") and "/api/measurements/{id}/refit" in spec["paths"]
    import urllib.request

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args):
            return None

    opener = urllib.request.build_opener(NoRedirect)
    try:
        opener.open(f"{web.url}/?token={web.token}")
    except urllib.error.HTTPError as exc:  # the 302 itself
        assert exc.code == 302 and exc.headers["Location"] == "/"
        cookie = exc.headers["Set-Cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    value = cookie.split(";")[0]
    page = web.call("GET", "/", token=None, headers={"Cookie": value})
    assert page.status == 200 and b"/static/app.js" in page.body
    assert web.call("GET", "/api/status", token=None, headers={"Cookie": value}).status == 200
    assert web.call("GET", "/?token=nope", token=None).status == 401


def test_status_says_what_the_instrument_asks_and_who_it_is(web):
    status = web.call("GET", "/api/status").json
    assert status["device"]["firmware"] and status["device"]["regmap_hash"].startswith("0x")
    assert {"state", "step", "progress", "lamp_drift", "calibration", "map_table", "job"} <= set(status)


def test_measure_is_refused_while_the_holder_is_asked_for(web):
    status = web.call("GET", "/api/status").json
    if status["state"] == "asking_empty_holder":
        answer = web.call("POST", "/api/measure", {"thickness_mm": THICKNESS_MM})
        assert answer.status == 409 and "empty holder" in answer.json["error"]["message"]


def test_calibrate_measure_and_find_it_in_the_history(web, measured, hook):
    status = web.call("GET", "/api/status").json
    assert status["state"] == "ready" and status["calibration"]["due"] is None
    assert status["lamp_drift"]["drift"] < 0.01 and status["last_measurement"] == measured
    found = web.call("GET", "/api/measurements?label=cya&since=2000-01-01").json
    assert [m["id"] for m in found["measurements"]] == [measured] and found["total"] == 1
    assert web.call("GET", "/api/measurements?label=magenta").json["total"] == 0
    assert web.call("GET", "/api/measurements?until=2000-01-01").json["total"] == 0
    row = found["measurements"][0]
    flagged = "true" if row["flagged_bins"] else "false"
    assert web.call("GET", f"/api/measurements?flagged={flagged}").json["total"] == 1
    table = list(csv.DictReader(io.StringIO(web.call("GET", "/api/measurements?format=csv").body.decode())))
    assert table[0]["id"] == measured and table[0]["label"] == "cyan"
    details = web.call("GET", f"/api/measurements/{measured}").json
    assert details["meta"]["declared_thicknesses_mm"] == [THICKNESS_MM]
    assert len(details["parameters"]["combined"]["alpha"]) == row["bins"]
    assert all(isinstance(a, str) for a in details["advice"]) and "figure.png" in details["files"]
    png = web.call("GET", f"/api/measurements/{measured}/files/figure.png")
    assert png.status == 200 and png.body[:8] == b"\x89PNG\r\n\x1a\n"
    names = zipfile.ZipFile(io.BytesIO(web.call("GET", f"/api/measurements/{measured}/zip").body)).namelist()
    assert sorted(n.split("/", 1)[1] for n in names) == details["files"]
    # the webhook heard of the calibration and the measurement
    events = [(r["event"], r["job"]["kind"]) for r in hook.received]
    assert ("done", "calibrate") in events and (("flagged" if row["flagged_bins"] and details["advice"] else "done"),
                                                 "measure") in events


def test_refit_writes_a_new_record_and_leaves_the_original(web, measured):
    original = web.history.root / measured
    before = directory_digest(original)
    answer = web.call("POST", f"/api/measurements/{measured}/refit", {"maps": ["device-n1.5-l0.4"], "method": "lut"})
    assert answer.status == 202
    job = web.wait_job(answer.json["job"]["id"])
    assert job["outcome"] == "refitted", job
    new = web.call("GET", f"/api/measurements/{job['measurement']}").json
    assert new["measurement"]["refit_of"] == measured and new["measurement"]["maps"] == ["device-n1.5-l0.4"]
    assert new["meta"]["label"] == "cyan" and new["measurement"]["bins"] > 0
    assert directory_digest(original) == before
    old = json.loads((original / "parameters.json").read_text())["combined"]["alpha"]
    assert len(new["parameters"]["combined"]["alpha"]) == len(old)
    assert web.call("GET", "/api/measurements?label=cyan").json["total"] == 2
    refused = web.call("POST", f"/api/measurements/{measured}/refit", {"maps": ["/etc/passwd"]})
    assert refused.status == 400 and "not known here" in refused.json["error"]["message"]


def test_a_refit_runs_beside_the_instrument_and_is_stopped_at_its_time_limit(web, measured, monkeypatch):
    from trimeter.web import refit_routes

    monkeypatch.setattr(refit_routes, "REFIT_TIME_LIMIT_S", 0.05)
    records = web.call("GET", "/api/measurements").json["total"]
    answer = web.call("POST", f"/api/measurements/{measured}/refit", {"maps": ["device-n1.5-l0.4"], "method": "lut"})
    assert answer.status == 202
    assert web.call("GET", "/api/status").json["job"] is None   # not on the instrument's queue
    job = web.wait_job(answer.json["job"]["id"])
    assert job["state"] == "failed" and "took longer than 0.05 s and was stopped" in job["message"], job
    assert web.call("GET", "/api/measurements").json["total"] == records


def test_a_paper_refit_above_its_size_is_refused_up_front_with_the_limit(web, measured, monkeypatch):
    from trimeter.web import refit

    records = web.call("GET", "/api/measurements").json["total"]
    monkeypatch.setattr(refit, "PAPER_MAX_TRIANGULATED_NODES", 1000)  # under one triangulation of the map
    answer = web.call("POST", f"/api/measurements/{measured}/refit", {"maps": ["device-n1.5-l0.4"], "method": "paper"})
    assert answer.status == 400, answer.json
    assert "map nodes" in answer.json["error"]["message"] and "the limit is 1,000" in answer.json["error"]["message"]
    refused = web.call("POST", f"/api/measurements/{measured}/refit", {"method": "paper"})  # the recorded map
    assert refused.status == 400 and "the limit is 1,000" in refused.json["error"]["message"]
    assert web.call("GET", "/api/measurements").json["total"] == records
    assert web.call("GET", "/api/status").json["job"] is None


def test_a_refit_of_a_record_with_a_fifo_fails_at_once(web, measured):
    import os
    import shutil
    import time

    copy = web.history.root / f"{measured[:16]}-fifo"
    shutil.copytree(web.history.root / measured, copy)
    raw = next(copy.glob("raw_black*.csv"))
    raw.unlink()
    os.mkfifo(raw)
    started = time.monotonic()
    answer = web.call("POST", f"/api/measurements/{copy.name}/refit", {"maps": ["device-n1.5-l0.4"], "method": "lut"})
    job = web.wait_job(answer.json["job"]["id"], timeout_s=60)
    assert job["state"] == "failed" and raw.name in job["message"], job
    assert time.monotonic() - started < 60
    status = web.call("GET", "/api/status").json
    assert status["state"] == "ready" and status["job"] is None


def test_config_goes_through_the_same_checks(web, measured):
    config = web.call("GET", "/api/config").json
    assert config["device_source"] == "read" and "speed_mm_s" in config["device"]
    speed = config["device"]["speed_mm_s"]
    changed = web.call("PUT", "/api/config", {"host": {"frames": 3}, "device": {"speed_mm_s": speed}})
    assert changed.status == 200 and changed.json["host"]["frames"] == 3
    assert web.jobs.service.settings.frames == 3
    for bad in ({"host": {"frames": 0}}, {"host": {"no_such": 1}}, {"device": {"speed_mm_s": -5}},
                {"device": {"uptime_s": 1}}, {"host": {"frames": 2}, "device": {"speed_mm_s": "fast"}}):
        answer = web.call("PUT", "/api/config", bad)
        assert answer.status == 400, (bad, answer.body)
    after = web.call("GET", "/api/config").json
    assert after["host"]["frames"] == 3 and after["device"]["speed_mm_s"] == speed
    # a PUT whose device part the firmware refuses (a white slot inside the homing back-off) saves no host part
    refused = web.call("PUT", "/api/config", {"host": {"frames": 4}, "device": {"slot_white_mm": 0.0}})
    assert refused.status == 400 and "refused" in refused.json["error"]["message"], refused.body
    assert HostSettings.load().frames == 3 and web.jobs.service.settings.frames == 3


def test_events_arrive_live_on_the_websocket_for_every_client(web, measured):
    from aiohttp import ClientSession

    async def listen(session, got):
        async with session.ws_connect(f"{web.url}/api/events", headers={"Authorization": f"Bearer {web.token}"}) as ws:
            got.append(await ws.receive_json())
            while True:
                record = await ws.receive_json(timeout=60)
                got.append(record)
                if record["type"] == "job" and record["job"]["state"] == "done":
                    return

    async def main():
        got_a, got_b = [], []
        async with ClientSession() as session:
            tasks = [asyncio.create_task(listen(session, got)) for got in (got_a, got_b)]
            await asyncio.sleep(0.3)
            answer = await asyncio.to_thread(web.call, "POST", "/api/measure", {"label": "ws"})
            assert answer.status == 202
            await asyncio.wait_for(asyncio.gather(*tasks), 120)
        return got_a, got_b

    for got in asyncio.run(main()):
        assert got[0]["type"] == "status"
        kinds = [r.get("kind") for r in got if r["type"] == "event"]
        assert "measured" in kinds and any(r["type"] == "progress" for r in got)
    cross = web.call("GET", "/api/events", headers={"Origin": "http://elsewhere.example", "Connection": "Upgrade",
                                                    "Upgrade": "websocket"})
    assert cross.status == 403


def test_two_clients_at_once_one_job_the_other_409(web, measured):
    def ask(_):
        return web.call("POST", "/api/measure", {"label": "twice"})

    with ThreadPoolExecutor(2) as pool:
        answers = list(pool.map(ask, range(2)))
    assert sorted(a.status for a in answers) == [202, 409]
    busy = next(a for a in answers if a.status == 409).json["error"]
    winner = next(a for a in answers if a.status == 202).json["job"]
    assert busy["job"]["id"] == winner["id"]
    with ThreadPoolExecutor(8) as pool:  # readers meanwhile are not held up by the job
        assert {a.status for a in pool.map(lambda _: web.call("GET", "/api/status"), range(16))} == {200}
    assert web.wait_job(winner["id"])["outcome"] == "measured"


BAD_INPUT = [
    ("malformed JSON", "POST", "/api/measure", dict(raw=b'{"label": ', headers={"Content-Type": "application/json"}),
     400),
    ("a 100 MB body", "POST", "/api/measure", dict(raw=b"{" + b" " * (100 << 20) + b"}",
                                                   headers={"Content-Type": "application/json"}), 413),
    ("not an object", "POST", "/api/measure", dict(body=[1, 2]), 400),
    ("unknown field", "POST", "/api/measure", dict(body={"thickness": 0.4}), 400),
    ("label with a path", "POST", "/api/measure", dict(body={"label": "../../etc"}), 400),
    ("negative thickness", "POST", "/api/measure", dict(body={"thickness_mm": -1}), 400),
    ("thickness without a map", "POST", "/api/measure", dict(body={"thickness_mm": 7.7}), 400),
    ("'..' in a file name", "GET", "/api/measurements/{id}/files/..%2F..%2Fcalibration", {}, 400),
    ("'..' as the id", "GET", "/api/measurements/..%2F..%2Fetc/files/passwd", {}, 400),
    ("a hidden file", "GET", "/api/measurements/{id}/files/.partial", {}, 400),
    ("an unknown file", "GET", "/api/measurements/{id}/files/nope.csv", {}, 404),
    ("an unknown id", "GET", "/api/measurements/20000101T000000Z-nope", {}, 404),
    ("an unknown job", "GET", "/api/jobs/123456", {}, 404),
    ("a bad date", "GET", "/api/measurements?since=yesterday", {}, 400),
    ("a bad page size", "GET", "/api/measurements?limit=100000", {}, 400),
    ("a wrong token", "POST", "/api/calibrate", dict(body={}, token="x" * 43), 401),
    ("no token", "GET", "/api/config", dict(token=None), 401),
    ("cross-origin state change", "POST", "/api/calibrate",
     dict(body={}, headers={"Origin": "http://evil.example"}), 403),
    ("not asked for the next sample", "POST", "/api/next-sample", dict(body={}), 409),
    ("holder_empty while not asked", "POST", "/api/calibrate", dict(body={"holder_empty": True}), 409),
    ("a refit with an unknown method", "POST", "/api/measurements/{id}/refit", dict(body={"method": "magic"}), 400),
]


@pytest.mark.parametrize("what,method,path,kwargs,status", BAD_INPUT, ids=[b[0] for b in BAD_INPUT])
def test_bad_input_is_a_clear_4xx_and_changes_nothing(web, measured, what, method, path, kwargs, status):
    web.wait_state("ready")
    before = (web.call("GET", "/api/measurements").json["total"], directory_digest(web.history.root / measured),
              web.call("GET", "/api/config").json["host"])
    answer = web.call(method, path.format(id=measured), **kwargs)
    assert answer.status == status, answer.body
    assert answer.json["error"]["status"] == status and answer.json["error"]["message"]
    after = (web.call("GET", "/api/measurements").json["total"], directory_digest(web.history.root / measured),
             web.call("GET", "/api/config").json["host"])
    assert after == before
    status_now = web.call("GET", "/api/status").json
    assert status_now["state"] == "ready" and status_now["job"] is None  # still working, nothing queued
