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
was written). Survives device resets and reconnects. Stop with Ctrl-C."""

from __future__ import annotations

import threading
from datetime import datetime

from trimeter.cli._instrument import add_instrument_args, open_device, open_spectrometer, settings_from
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.service import Service


def run(args):
    settings = settings_from(args)
    if args.thickness:
        settings.set("thickness_mm", args.thickness)
    if args.second_thickness is not None:
        settings.set("second_thickness_mm", args.second_thickness)
    for number, (thickness, map_name) in enumerate(settings.serve_samples, start=1):  # never assumed silently
        amap = map_for_thickness(thickness, map_name)  # a map of another thickness is an error, before serving
        option = "--thickness" if number == 1 else "--second-thickness"
        source = option if getattr(args, option[2:].replace("-", "_")) else "host config"
        print(f"sample {number}: thickness {thickness:g} mm ({source}), map {amap.name}", flush=True)
    stop = threading.Event()

    def show(event):
        print(f"{datetime.now():%H:%M:%S} {event.kind:<12} {event.message}", flush=True)

    service = Service(lambda: open_device(settings), lambda: open_spectrometer(settings), settings,
                      on_event=show, label=args.label)
    print(f"serving the instrument on {settings.port}; results in {settings.results_path} (Ctrl-C stops)", flush=True)
    try:
        service.serve(stop=stop.is_set)
    except KeyboardInterrupt:
        stop.set()
    finally:
        service.close()


def register(subparsers) -> None:
    p = subparsers.add_parser("serve", help="press-button standalone mode", description=__doc__)
    add_instrument_args(p)
    p.add_argument("--thickness", type=float, help="sample thickness in mm (default: host config)")
    p.add_argument("--second-thickness", type=float,
                   help="a second sample's thickness in mm, measured after the first on each press (0: none; "
                        "default: host config)")
    p.add_argument("--label", help="a name for the results directories")
    p.set_defaults(func=run)
