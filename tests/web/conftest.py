"""A twin-backed `serve --http` in this process: the twin, the press-button Service, its job worker,
the history index and the web app on 127.0.0.1 (an ephemeral port), with the host directories in a
temporary place. One per test module: a twin start and a first calibration are the slow parts."""

from __future__ import annotations

import contextlib
import json
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

from hil_support import HIL_MAP, THICKNESS_MM, TIME_SCALE
from trimeter.bench._rig import host_dirs
from trimeter.cli._instrument import open_device, open_spectrometer
from trimeter.sequences.service import Service
from trimeter.paths import data_dir
from trimeter.sequences.settings import HostSettings


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args: object, **kwargs: object) -> None:
        return None  # the redirect itself is the answer (urllib raises it as an HTTPError)


@dataclass
class Answer:
    status: int
    body: bytes
    headers: dict

    @property
    def json(self):
        return json.loads(self.body)


@dataclass
class Web:
    url: str
    token: str
    twin: object
    jobs: object
    history: object
    root: Path

    def call(self, method: str, path: str, body=None, *, token: str | None = "default", headers=None,
             raw: bytes | None = None, timeout: float = 30.0, follow_redirects: bool = True) -> Answer:
        head = dict(headers or {})
        token = self.token if token == "default" else token
        if token is not None:
            head["Authorization"] = f"Bearer {token}"
        data = raw
        if body is not None:
            data = json.dumps(body).encode()
            head.setdefault("Content-Type", "application/json")
        request = urllib.request.Request(self.url + path, data=data, method=method, headers=head)
        opener = urllib.request.build_opener() if follow_redirects else urllib.request.build_opener(_NoRedirect)
        try:
            with opener.open(request, timeout=timeout) as response:
                return Answer(response.status, response.read(), dict(response.headers))
        except urllib.error.HTTPError as exc:
            return Answer(exc.code, exc.read(), dict(exc.headers))

    def wait_job(self, job_id: str, timeout_s: float = 120.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            job = self.call("GET", f"/api/jobs/{job_id}").json["job"]
            if job["state"] in ("done", "failed"):
                return job
            time.sleep(0.1)
        raise AssertionError(f"job {job_id} not finished within {timeout_s} s")

    def wait_state(self, state: str, timeout_s: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            status = self.call("GET", "/api/status").json
            if status["state"] == state:
                return status
            time.sleep(0.05)
        raise AssertionError(f"state {state!r} not reached within {timeout_s} s (last {status['state']})")

    def calibrate(self) -> dict:
        """The page's calibration: ask, the holder is (made) empty, confirm."""
        self.twin.control.remove_sample()
        if self.call("GET", "/api/status").json["state"] != "asking_empty_holder":
            asked = self.call("POST", "/api/calibrate", {})
            assert asked.status == 202, asked.body
            self.wait_job(asked.json["job"]["id"])
        confirmed = self.call("POST", "/api/calibrate", {"holder_empty": True})
        assert confirmed.status == 202, confirmed.body
        return self.wait_job(confirmed.json["job"]["id"])


@contextlib.contextmanager
def web_instrument(root: Path, *, webhook: str | None = None, map_table: bytes | None = None, host_map: bool = True,
                   twin_map: object = None):
    """map_table: a device table the twin carries in its active slot; host_map=False: the host config names
    no map, so the service fits with the instrument's table; twin_map: what the twin renders with (default:
    the HIL map's file, loaded when first needed)."""
    from trimeter.twin import Twin
    from trimeter.web.app import create_app
    from trimeter.web.server import WebServer
    from trimeter.web.auth import load_or_create_token
    from trimeter.web.history import History
    from trimeter.web.jobs import Jobs

    with host_dirs(root), Twin(sample=None, thickness_mm=THICKNESS_MM, time_scale=TIME_SCALE,
                               appearance_map=twin_map or str(HIL_MAP), state_dir=root / "twin", seed=3,
                               map_table=map_table) as twin:
        settings = HostSettings()
        for key, value in (("port", twin.modbus_port), ("spectrometer", twin.spectrometer_url),
                           ("results_dir", str(root / "results")), ("warmup_threshold", 0.003)):
            settings.set(key, value)
        if host_map:
            settings.set("map", str(HIL_MAP))
        service = Service(lambda: open_device(settings), lambda: open_spectrometer(settings), settings,
                          device_clock=twin.sim_time)
        history = History(settings.results_path, data_dir() / "history.sqlite")
        history.open()
        jobs = Jobs(service, on_measurement=history.add)
        server = WebServer(create_app(jobs, history, load_or_create_token(), webhook=webhook), "127.0.0.1", 0)
        server.start()
        jobs.start()
        try:
            yield Web(server.url, load_or_create_token(), twin, jobs, history, root)
        finally:
            server.close()
            jobs.stop()
            service.close()


@pytest.fixture(scope="module")
def web(tmp_path_factory):
    with web_instrument(tmp_path_factory.mktemp("web")) as instrument:
        instrument.wait_state("asking_empty_holder")
        yield instrument


def _no_instrument() -> object:
    raise AssertionError("this test's host has no instrument: nothing may open one")


@contextlib.contextmanager
def idle_web(root: Path, **server_options: float):
    """The web app of a host whose instrument loop never starts (no twin): for what the app answers by
    itself (headers, the map listing), in a fraction of a second. server_options: WebServer's."""
    from trimeter.web.app import create_app
    from trimeter.web.server import WebServer
    from trimeter.web.auth import load_or_create_token
    from trimeter.web.history import History
    from trimeter.web.jobs import Jobs

    with host_dirs(root):
        settings = HostSettings()
        settings.set("results_dir", str(root / "results"))
        service = Service(_no_instrument, _no_instrument, settings)
        history = History(settings.results_path, data_dir() / "history.sqlite")
        history.open()
        jobs = Jobs(service, on_measurement=history.add)
        server = WebServer(create_app(jobs, history, load_or_create_token()), "127.0.0.1", 0, **server_options).start()
        try:
            yield Web(server.url, load_or_create_token(), None, jobs, history, root)
        finally:
            server.close()
            history.close()


@pytest.fixture
def browser():
    """A headless chromium (browser_support.chrome), quit after the test."""
    from browser_support import chrome

    driver = chrome()
    yield driver
    driver.quit()
