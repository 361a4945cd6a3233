"""`trimeter serve`: press-button standalone mode. Waits for the instrument's front button; a press
calibrates when the calibration is missing, stale or the device was reset: the LED then triple-blinks
(empty the holder and press) and a press checks that the holder is empty (a sample is refused, the LED
keeps asking), warms up and calibrates; otherwise it measures the inserted sample and writes a results
directory. With a second thickness (`--second-thickness`, or host config second_thickness_mm) a press
measures the first sample, then
the LED double-blinks until the second is in and the button pressed again; both are fitted together
(the paper's procedure, which thick samples need for α and g); if the second never comes (host
config swap_timeout_s) the first is written alone, marked incomplete. Status LED: steady = ready, slow
blink = working, triple blink = empty the holder and press (to calibrate), double blink = put the next
sample in and press, fast blink = the last press failed (e.g. a shot refused by its light checks: nothing
was written). Survives device resets and reconnects. Stop with Ctrl-C.

`--http HOST:PORT` also serves the instrument on the network (default bind 127.0.0.1; 0.0.0.0 only when
asked): a JSON API (/api/openapi.json), a live event websocket and a page with status, calibration,
measurement, history and results. The button and the page start jobs in one queue. Access needs the
token made at first start (0600 in the host config directory): `--show-token` prints it and the link.
`--webhook URL` is POSTed {event: done|failed|flagged, job, measurement} when a job ends."""

from __future__ import annotations

import argparse
import threading
from datetime import datetime
from urllib.parse import urlsplit

from trimeter.cli._instrument import add_instrument_args, open_device, open_spectrometer, settings_from
from trimeter.errors import InputError
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.service import Event, Service
from trimeter.sequences.settings import HostSettings


def show_token(args: argparse.Namespace) -> None:
    from trimeter.web.server import parse_bind
    from trimeter.web.auth import load_or_create_token, token_path

    token = load_or_create_token()
    host, port = parse_bind(args.http) if args.http else ("127.0.0.1", 8080)
    print(f"token: {token}  ({token_path()}, mode 0600)")
    print(f"page:  http://{'localhost' if host in ('127.0.0.1', '0.0.0.0', '') else host}:{port}/?token={token}")


def check_webhook(url: str | None) -> None:
    if url is None:
        return
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise InputError(f"--webhook: {url!r} is not an http(s) URL")


def run(args: argparse.Namespace) -> None:
    if args.show_token:
        return show_token(args)
    check_webhook(args.webhook)
    settings = settings_from(args)
    if args.thickness:
        settings.set("thickness_mm", args.thickness)
    if args.second_thickness is not None:
        settings.set("second_thickness_mm", args.second_thickness)
    for number, (thickness, map_name) in enumerate(settings.serve_samples, start=1):  # never assumed silently
        option = "--thickness" if number == 1 else "--second-thickness"
        source = option if getattr(args, option[2:].replace("-", "_")) else "host config"
        if map_name:
            amap = map_for_thickness(thickness, map_name)  # a map of another thickness is an error, before serving
            fitted = f"map {amap.name}"
        else:  # checked against the sample's thickness at each press, as the active slot may change
            fitted = "the map table the instrument carries"
        print(f"sample {number}: thickness {thickness:g} mm ({source}), {fitted}", flush=True)
    if settings.instruments and not (args.port or args.address):  # --port/--address: that one instrument alone
        from trimeter.cli.serve_lab import serve_lab

        return serve_lab(args, settings)
    stop = threading.Event()

    def show(event: Event) -> None:
        print(f"{datetime.now():%H:%M:%S} {event.kind:<12} {event.message}", flush=True)

    service = Service(lambda: open_device(settings), lambda: open_spectrometer(settings), settings,
                      on_event=show, label=args.label)
    if args.http:
        return serve_http(args, service, settings)
    print(f"serving the instrument on {settings.port}; results in {settings.results_path} (Ctrl-C stops)", flush=True)
    try:
        service.serve(stop=stop.is_set)
    except KeyboardInterrupt:
        stop.set()
    finally:
        service.close()


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("serve", help="press-button standalone mode", description=__doc__)
    add_instrument_args(p)
    p.add_argument("--thickness", type=float, help="sample thickness in mm (default: host config)")
    p.add_argument("--second-thickness", type=float,
                   help="a second sample's thickness in mm, measured after the first on each press (0: none; "
                        "default: host config)")
    p.add_argument("--label", help="a name for the results directories")
    p.add_argument("--http", metavar="HOST:PORT",
                   help="also serve the web page and API, e.g. 127.0.0.1:8080 (0.0.0.0:8080: the whole LAN)")
    p.add_argument("--show-token", action="store_true",
                   help="print the web token and the page's link (made if missing), then exit")
    p.add_argument("--webhook", metavar="URL", help="POSTed JSON when a job is done, failed or flagged (with --http)")
    p.set_defaults(func=run)


def serve_http(args: argparse.Namespace, service: Service, settings: HostSettings) -> None:
    """The press-button loop on a worker thread, the web app on another; Ctrl-C stops both."""
    from trimeter.cli.serve_web import serve_web
    from trimeter.web.app import create_app

    serve_web(args, settings, [service], f"the instrument on {settings.port}",
              lambda jobs, history, token: create_app(jobs[0], history, token, webhook=args.webhook))
