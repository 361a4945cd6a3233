"""What the several-instruments tests share (a uniquely named module, as hil_support): three twins on one simulated
bus served by one in-process `serve --http` with [[instruments]], and a small client of its page's API."""

from __future__ import annotations

import contextlib
import json
import time
import urllib.error
import urllib.request
from pathlib import Path

from hil_support import HIL_MAP, THICKNESS_MM, TIME_SCALE
from trimeter.bench._rig import host_dirs
from trimeter.paths import data_dir
from trimeter.sequences.instruments import Lab
from trimeter.sequences.settings import HostSettings

NAMES = ("left", "middle", "right")


class Page:
    def __init__(self, url: str, token: str) -> None:
        self.url, self.token = url, token

    def call(self, method: str, path: str, body: dict | None = None) -> tuple[int, dict]:
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method=method,
                                         headers={"Authorization": f"Bearer {self.token}",
                                                  "Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                return response.status, json.loads(response.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read() or b"{}")

    def wait_job(self, name: str, job_id: str, timeout_s: float = 180.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            job = self.call("GET", f"/instruments/{name}/api/jobs/{job_id}")[1]["job"]
            if job["state"] in ("done", "failed"):
                return job
            time.sleep(0.1)
        raise AssertionError(f"{name}: job {job_id} not finished within {timeout_s} s")

    def calibrate(self, name: str) -> dict:
        state = self.call("GET", f"/instruments/{name}/api/status")[1]["state"]
        if state != "asking_empty_holder":
            status, asked = self.call("POST", f"/instruments/{name}/api/calibrate", {})
            assert status == 202, asked
            self.wait_job(name, asked["job"]["id"])
        status, confirmed = self.call("POST", f"/instruments/{name}/api/calibrate", {"holder_empty": True})
        assert status == 202, confirmed
        return self.wait_job(name, confirmed["job"]["id"])

    def measure(self, name: str) -> tuple[dict, float]:
        started = time.monotonic()
        status, answer = self.call("POST", f"/instruments/{name}/api/measure", {"thickness_mm": THICKNESS_MM})
        assert status == 202, answer
        job = self.wait_job(name, answer["job"]["id"])
        return job, time.monotonic() - started

    def wait_state(self, name: str, state: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.call("GET", f"/instruments/{name}/api/status")[1]["state"] == state:
                return
            time.sleep(0.05)
        raise AssertionError(f"{name}: state {state!r} not reached within {timeout_s} s")


@contextlib.contextmanager
def served_lab(root: Path, faults: dict | None = None, seed: int = 11):
    """Three twins on one bus (`faults`: name → FaultConfig fields for that twin) and the page serving them all;
    yields (Page, {name: twin}, results directory)."""
    from trimeter.twin import FaultConfig
    from trimeter.twin.bus import TwinBus
    from trimeter.web.server import WebServer
    from trimeter.web.auth import load_or_create_token
    from trimeter.web.history import History
    from trimeter.web.app import create_lab_app
    from trimeter.web.jobs import Jobs

    twin_faults = [FaultConfig(**(faults or {})[name]) if name in (faults or {}) else None for name in NAMES]
    with host_dirs(root), TwinBus(3, faults=twin_faults, sample=None, thickness_mm=THICKNESS_MM, time_scale=TIME_SCALE,
                                  appearance_map=str(HIL_MAP), state_dir=root / "bus", seed=seed) as bus:
        settings = HostSettings()
        settings.update({"results_dir": str(root / "results"), "map": str(HIL_MAP), "warmup_threshold": 0.003,
                         "timeout_s": 0.1, "attempts": 8,
                         "instruments": [{"name": name, "port": bus.modbus_port, "address": twin.address,
                                          "spectrometer": twin.spectrometer_url}
                                         for name, twin in zip(NAMES, bus.twins, strict=True)]})
        lab = Lab(settings)
        lab.check_buses()
        history = History(settings.results_path, data_dir() / "history.sqlite")
        history.open()
        served = [(instrument, Jobs(lab.service(instrument, device_clock=twin.sim_time), on_measurement=history.add))
                  for instrument, twin in zip(lab.instruments, bus.twins, strict=True)]
        server = WebServer(create_lab_app(served, history, load_or_create_token()), "127.0.0.1", 0).start()
        for _, jobs in served:
            jobs.start()
        try:
            twins = dict(zip(NAMES, bus.twins, strict=True))
            yield Page(server.url, load_or_create_token()), twins, settings.results_path
        finally:
            server.close()
            for _, jobs in served:
                jobs.stop()
            for _, jobs in served:
                jobs.service.close()
            lab.close()
