"""`trimeter serve` with the host config's [[instruments]]: one Service per instrument, on one thread each;
instruments on one port share it as a bus (trimeter.sequences.instruments). With --http one page shows them all."""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable
from datetime import datetime

from trimeter.sequences.instruments import Instrument, Lab
from trimeter.sequences.service import Event, Service
from trimeter.sequences.settings import HostSettings


def _printer(name: str) -> Callable[[Event], None]:
    def show(event: Event) -> None:
        print(f"{datetime.now():%H:%M:%S} {name:<12} {event.kind:<12} {event.message}", flush=True)
    return show


def serve_lab(args: argparse.Namespace, settings: HostSettings) -> None:
    lab = Lab(settings)
    try:
        lab.check_buses()  # an address collision is refused here, before anything is measured
        services = [(i, lab.service(i, on_event=_printer(i.name), label=args.label)) for i in lab.instruments]
        where = ", ".join(f"{i.name} ({i.port} @{i.address})" for i in lab.instruments)
        if args.http:
            _serve_http(args, settings, services, where)
        else:
            _serve_buttons(services, where, settings)
    finally:
        lab.close()


def _serve_buttons(services: list[tuple[Instrument, Service]], where: str, settings: HostSettings) -> None:
    stop = threading.Event()
    threads = [threading.Thread(target=service.serve, kwargs={"stop": stop.is_set}, name=f"trimeter-{i.name}",
                                daemon=True) for i, service in services]
    print(f"serving {where}; results in {settings.results_path} (Ctrl-C stops)", flush=True)
    for thread in threads:
        thread.start()
    try:
        while any(t.is_alive() for t in threads):
            for thread in threads:
                thread.join(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        for thread in threads:
            thread.join(30)
        for _, service in services:
            service.close()


def _serve_http(args: argparse.Namespace, settings: HostSettings, services: list[tuple[Instrument, Service]],
                where: str) -> None:
    from trimeter.cli.serve_web import serve_web
    from trimeter.web.app import create_lab_app

    instruments = [instrument for instrument, _ in services]
    serve_web(args, settings, [service for _, service in services], where,
              lambda jobs, history, token: create_lab_app(list(zip(instruments, jobs, strict=True)), history, token,
                                                          webhook=args.webhook))
