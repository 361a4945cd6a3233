"""`trimeter serve --http`: the instruments' loops on worker threads and the web app on another, for one
instrument or several (serve_lab); Ctrl-C stops them all."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import TYPE_CHECKING

from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings

if TYPE_CHECKING:
    from aiohttp import web

    from trimeter.web.history import History
    from trimeter.web.jobs import Jobs

# the app serving these jobs (one per service, in order), the history they share and the access token
AppFactory = Callable[["list[Jobs]", "History", str], "web.Application"]


def serve_web(args: argparse.Namespace, settings: HostSettings, services: Sequence[Service], where: str,
              create: AppFactory) -> None:
    """Serve `services` (described as `where`) with the app `create` makes, at args.http, until Ctrl-C."""
    from trimeter.paths import data_dir
    from trimeter.web.auth import load_or_create_token
    from trimeter.web.history import History
    from trimeter.web.jobs import Jobs
    from trimeter.web.server import WebServer, parse_bind

    host, port = parse_bind(args.http)
    token = load_or_create_token()
    history = History(settings.results_path, data_dir() / "history.sqlite")
    for note in history.open():
        print(f"{datetime.now():%H:%M:%S} {'history':<12} {note}", flush=True)
    history.close()  # this thread's connection; the workers and the web thread open their own
    jobs = [Jobs(service, on_measurement=history.add) for service in services]
    server = WebServer(create(jobs, history, token), host, port).start()
    for one in jobs:
        one.start()
    print(f"serving {where}; results in {settings.results_path}; web page on {server.url}/ "
          f"(`trimeter serve --show-token` prints the link with its token; Ctrl-C stops)", flush=True)
    try:
        # timed: Ctrl-C is a process signal the kernel may hand to any thread, and Python runs its handler on
        # the main thread only when that thread next runs bytecode, which an untimed wait never does
        while True:
            time.sleep(0.25)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
        for one in jobs:
            one.stop()
        for service in services:
            service.close()
