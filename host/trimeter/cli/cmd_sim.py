"""`trimeter sim`: run the twin (simulated instrument) and print the ports to use, until Ctrl-C.

Contract: host/trimeter/twin/README.md. In another terminal:
    trimeter measure --port /dev/pts/N --spectrometer sim:/dev/pts/M
and drive the virtual instrument through its control socket:
    trimeter sim --ctl insert_sample name=milk thickness_mm=0.4
    trimeter sim --ctl press_button
    trimeter sim --ctl state
(`--ctl` finds the running twin through ports.json in the same --state-dir, or take --control PATH).
"""

from __future__ import annotations

import argparse
import json
import signal
import threading

from trimeter.errors import InputError


def _default_state_dir() -> str:
    import platformdirs

    return platformdirs.user_state_dir("trimeter") + "/twin"


def _ctl(args: argparse.Namespace) -> int:
    """Send one control request to a running twin and print the reply as JSON."""
    from pathlib import Path

    from trimeter.errors import DeviceError
    from trimeter.twin import TwinClient

    command, *pairs = args.ctl
    fields = {}
    for pair in pairs:
        key, eq, value = pair.partition("=")
        if not eq or not key:
            raise InputError(f"--ctl fields must be FIELD=VALUE, got {pair!r}")
        try:
            fields[key] = json.loads(value)
        except ValueError:
            fields[key] = value  # a bare word: a string (material names)
    control = args.control
    if control is None:
        ports_file = Path(args.state_dir or _default_state_dir()) / "ports.json"
        from trimeter.cli.sim_bus import control_path_of

        try:
            ports = json.loads(ports_file.read_text())
            if not isinstance(ports, dict):
                raise ValueError
        except (OSError, ValueError):
            raise DeviceError(f"no running twin found ({ports_file} missing or unreadable); "
                              f"give --control PATH") from None
        control = control_path_of(ports, args.address)
    with TwinClient(control) as client:
        reply = client._call(command, **fields)
    reply.pop("ok", None)
    print(json.dumps(reply, indent=1 if command == "state" else None) if reply else "ok")
    return 0


def run(args: argparse.Namespace) -> int:
    from trimeter.twin import FaultConfig, Twin
    from trimeter.twin.optics import material_names

    if args.ctl:
        return _ctl(args)
    if args.list_materials:
        for name, description in material_names().items():
            print(f"{name:14s} {description}")
        print("mixtures by volume fractions: MATERIAL:FRACTION+MATERIAL:FRACTION…, e.g. cyan-ink:0.5+yellow-ink:0.5")
        return 0
    if args.thickness <= 0:
        raise InputError(f"--thickness must be positive, got {args.thickness:g}")
    faults = FaultConfig.parse(args.faults or "")
    state_dir = args.state_dir or _default_state_dir()

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        if args.instruments is not None:
            from trimeter.cli.sim_bus import run_bus

            return run_bus(args, stop, state_dir)
        with Twin(sample=args.sample, thickness_mm=args.thickness, time_scale=args.time_scale, faults=faults,
                  state_dir=state_dir, appearance_map=args.map, seed=args.seed, white=args.white,
                  sensor=args.sensor) as twin:
            ports = twin.control.ports()
            if args.json:
                print(json.dumps(ports), flush=True)
            else:
                print(f"modbus:       {ports['modbus_port']}")
                print(f"spectrometer: {ports['spectrometer_url']}")
                print(f"control:      {ports['control_path']}")
                print(f"sample:       {args.sample or 'none'}  time scale {args.time_scale:g}x  state {twin.state_dir}")
                print("running; Ctrl-C to stop", flush=True)
            from trimeter.cli.sim_bus import run_until_stopped

            return run_until_stopped(stop, lambda: twin.running,
                                     "the firmware sim exited; see firmware.log in the state directory")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("sim", help="run the simulated instrument (twin) and print its ports",
                              description=__doc__)
    p.add_argument("--sample", metavar="MATERIAL", default=None,
                   help="virtual sample inserted at start (default: none; see --list-materials)")
    p.add_argument("--thickness", type=float, default=0.4, metavar="MM", help="sample thickness (default 0.4)")
    p.add_argument("--faults", metavar="LIST", default="",
                   help="e.g. corrupt=0.01,drop=0.02,late=0.01,reset_at=STEP,stuck_slider,lamp_failure,"
                        "lamp_dimmed=panels:0.8")
    p.add_argument("--time-scale", type=float, default=1.0, metavar="K", help="simulated time runs K× wall time")
    p.add_argument("--state-dir", default=None, metavar="DIR",
                   help="firmware storage + links (default: the platformdirs state directory); reuse it to keep config")
    p.add_argument("--map", default=None, metavar="PATH",
                   help="appearance map for the sample's thickness (default: the shipped device maps)")
    p.add_argument("--white", default="white", choices=("white", "ptfe"), help="white background material")
    p.add_argument("--sensor", default="spectrometer", choices=("spectrometer", "as7341", "c12880ma"),
                   help="what the host reads: the spectrometer's pixels or the AS7341's nine channels (counts, gain, "
                        "integration, noise, saturation; its band weights over BANDS?), or the firmware's C12880MA "
                        "micro-spectrometer (read over Modbus: the spectrometer URL is mcu:<modbus port>)")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the noise and of the link faults (reproducible spectra and faults; default: a random "
                        "one, shown by --ctl state)")
    p.add_argument("--json", action="store_true", help="print the ports as one JSON line")
    p.add_argument("--list-materials", action="store_true", help="list the virtual samples and exit")
    p.add_argument("--ctl", nargs="+", metavar="ARG",
                   help="send COMMAND [FIELD=VALUE ...] to a running twin instead of starting one "
                        "(ports, state, sim_time, insert_sample, remove_sample, press_button, reset_firmware, "
                        "set_fault, truth, materials)")
    p.add_argument("--control", default=None, metavar="PATH", help="with --ctl: the twin's control socket")
    p.add_argument("--instruments", type=int, default=None, metavar="N",
                   help="N instruments on one shared bus (one Modbus pty, addresses 1..N; --json prints modbus_port "
                        "and instruments: [{address, spectrometer_url, control_path}]); --faults applies to each")
    p.add_argument("--address", type=int, default=None, metavar="A",
                   help="with --ctl on a bus: the instrument at this address")
    p.set_defaults(func=run)
