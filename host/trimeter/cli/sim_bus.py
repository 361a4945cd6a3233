"""`trimeter sim --instruments N`: N twins on one shared bus (one pty, addresses 1..N), until Ctrl-C."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from trimeter.errors import DeviceError, InputError

BUS_PORTS_FILE = "ports.json"  # in --state-dir: the bus's ports (what --json prints), for `--ctl --address`


def run_bus(args: argparse.Namespace, stop: threading.Event, state_dir: str) -> int:
    from trimeter.twin import FaultConfig
    from trimeter.twin.bus import MAX_INSTRUMENTS, TwinBus

    if not 1 <= args.instruments <= MAX_INSTRUMENTS:
        raise InputError(f"--instruments must be within 1..{MAX_INSTRUMENTS}, got {args.instruments}")
    faults = FaultConfig.parse(args.faults or "")
    with TwinBus(args.instruments, faults=[faults] * args.instruments, state_dir=state_dir, sample=args.sample,
                 thickness_mm=args.thickness, time_scale=args.time_scale, appearance_map=args.map, seed=args.seed,
                 white=args.white, sensor=args.sensor) as bus:
        ports = bus.ports()
        ports_file = Path(state_dir) / BUS_PORTS_FILE
        ports_file.write_text(json.dumps(ports) + "\n")
        try:
            if args.json:
                print(json.dumps(ports), flush=True)
            else:
                print(f"bus (modbus): {ports['modbus_port']}")
                for instrument in ports["instruments"]:
                    print(f"  address {instrument['address']:3d}: spectrometer {instrument['spectrometer_url']}  "
                          f"control {instrument['control_path']}")
                print(f"sample: {args.sample or 'none'}  time scale {args.time_scale:g}x  state {state_dir}")
                print("running; Ctrl-C to stop", flush=True)
            return run_until_stopped(stop, lambda: bus.running, "a firmware sim exited; see firmware.log in its state "
                                     "directory")
        finally:
            ports_file.unlink(missing_ok=True)


def run_until_stopped(stop: threading.Event, running: Callable[[], bool], when_dead: str) -> int:
    """`trimeter sim`'s foreground: 0 once `stop` is set (Ctrl-C), 1 with `when_dead` as soon as the twin is not
    `running` any more."""
    while not stop.wait(0.5):
        if not running():
            print(f"trimeter sim: {when_dead}", file=sys.stderr)
            return 1
    return 0


def control_path_of(ports: dict, address: int | None) -> str:
    """The control socket of the instrument at `address` from a ports.json (one twin's, or a bus's)."""
    instruments = ports.get("instruments")
    if not isinstance(instruments, list):
        if address is not None and address != ports.get("address", address):
            raise InputError(f"--address {address}: the running twin is a single instrument")
        if not isinstance(ports.get("control_path"), str):
            raise DeviceError("the running twin's ports.json names no control socket; give --control PATH")
        return ports["control_path"]
    if address is None:
        raise InputError("the running twin is a bus of instruments: give --address (one of "
                         f"{', '.join(str(i.get('address')) for i in instruments if isinstance(i, dict))})")
    for instrument in instruments:
        if isinstance(instrument, dict) and instrument.get("address") == address:
            return str(instrument.get("control_path"))
    raise DeviceError(f"no instrument at address {address} on the running bus")
