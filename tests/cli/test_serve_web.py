"""`trimeter serve --http`'s loop (trimeter.cli.serve_web), shared by one instrument and several: every service
gets its jobs, the app is served until Ctrl-C, and Ctrl-C stops the server, the jobs and the services."""

from __future__ import annotations

import argparse
import signal
import threading
import time
import urllib.request

import pytest

from trimeter.bench._rig import host_dirs
from trimeter.cli.serve_web import serve_web
from trimeter.errors import DeviceError
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings
from trimeter.web.app import create_app
from trimeter.web.server import WebServer


def _no_device() -> object:
    raise DeviceError("no instrument on this test host")


def test_serve_web_serves_every_service_until_ctrl_c_then_stops_them_all(tmp_path, monkeypatch, capsys):
    servers: list[WebServer] = []
    real_start = WebServer.start

    def start(self: WebServer) -> WebServer:
        servers.append(real_start(self))
        return self

    monkeypatch.setattr(WebServer, "start", start)
    made = []

    def create(jobs, history, token):
        made.append((jobs, token))
        return create_app(jobs[0], history, token)

    answers: list[int] = []
    returned = threading.Event()
    main_thread_signalled: list[bool] = []

    def ctrl_c_once_served() -> None:
        deadline = time.monotonic() + 30
        while not servers and time.monotonic() < deadline:
            time.sleep(0.05)
        try:
            request = urllib.request.Request(f"{servers[0].url}/api/status",
                                             headers={"Authorization": f"Bearer {made[0][1]}"})
            with urllib.request.urlopen(request, timeout=10) as answer:
                answers.append(answer.status)
        finally:
            # Ctrl-C is sent to the process and the kernel may hand it to any thread: here, the worst case, not
            # the main one. serve_web must still stop; if it does not, the main thread is signalled itself so
            # that the test fails rather than hangs.
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)
            if not returned.wait(5):
                main_thread_signalled.append(True)
                signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

    with host_dirs(tmp_path):
        settings = HostSettings()
        settings.set("results_dir", str(tmp_path / "results"))
        services = [Service(_no_device, _no_device, settings) for _ in range(2)]
        closed: list[Service] = []   # by serve_web, on this thread (the loops close theirs on reconnects)
        for service in services:
            real_close = service.close

            def close(s: Service = service, real=real_close) -> None:
                if threading.current_thread() is threading.main_thread():
                    closed.append(s)
                real()

            monkeypatch.setattr(service, "close", close)
        # Ctrl-C armed as in a terminal: a process started in the background by a non-interactive shell (nohup
        # make test &) inherits SIGINT ignored, and no Ctrl-C would then reach serve_web at all
        previous_handler = signal.signal(signal.SIGINT, signal.default_int_handler)
        helper = threading.Thread(target=ctrl_c_once_served, daemon=True)
        helper.start()
        try:
            serve_web(argparse.Namespace(http="127.0.0.1:0"), settings, services, "two idle instruments", create)
        finally:
            returned.set()
            signal.signal(signal.SIGINT, previous_handler)
        helper.join(5)
    assert not main_thread_signalled, "Ctrl-C handed to another thread did not stop serve_web"
    assert answers == [200]
    jobs = made[0][0]
    assert [j.service for j in jobs] == services
    assert all(j._stop.is_set() for j in jobs) and closed == services
    out = capsys.readouterr().out
    assert f"serving two idle instruments; results in {tmp_path / 'results'}; web page on {servers[0].url}/" in out


def test_serve_web_refuses_a_bad_address_before_serving(tmp_path):
    with host_dirs(tmp_path), pytest.raises(Exception, match="HOST:PORT"):
        serve_web(argparse.Namespace(http="nonsense"), HostSettings(), [], "nothing", create_app)
