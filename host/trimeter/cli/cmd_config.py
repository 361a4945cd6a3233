"""`trimeter config list|get|set|save|export|import`: device configuration over Modbus, host
configuration as TOML.

A NAME from the register map (hardware/registers.md, e.g. speed_mm_s, slot_white_mm, led_panels_level)
is read/written on the device — `config save` makes device changes survive a power cycle. Any other
NAME (or --host) is a host setting stored in the platformdirs config directory.

`config export [-o FILE]` backs the device configuration up by name; `config import FILE [--save]`
restores it, e.g. after a firmware update that changed the register map (the device then ignores its
saved configuration and runs on defaults; `config list`, `serve`, `measure` and `calibrate` say so).
"""

from __future__ import annotations

import argparse
import sys
from enum import IntEnum
from pathlib import Path

from trimeter import registers as regs
from trimeter.device.backup import config_source_warning, dump_config, listing, read_config
from trimeter.device.client import CONFIG_NAMES
from trimeter.cli._instrument import add_instrument_args, open_device, settings_from
from trimeter.errors import InputError
from trimeter.sequences.settings import HostSettings

DEVICE_WRITABLE = {r.name for r in regs.REGISTERS if r.access == "rw" and r.name not in ("command", "map_command")}


def _show(value: object) -> str:
    if isinstance(value, IntEnum):
        return value.name.lower()
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _is_device(name: str, args: argparse.Namespace) -> bool:
    return not args.host and name in regs.BY_NAME


def cmd_list(args: argparse.Namespace) -> None:
    settings = settings_from(args)
    if not args.device:
        print(f"# host ({HostSettings.path()})")
        for key, value in settings.as_dict().items():
            print(f"{key} = {value!r}")
    if not args.host:
        with open_device(settings) as dev:
            identity = dev.identity or dev.check_identity()
            print(f"# device ({settings.port}, firmware {'.'.join(map(str, identity.firmware_version))})")
            source = dev.read("config_source")
            print(f"# configuration source: {source.name.lower()}")
            if warning := config_source_warning(source):
                print(f"# warning: {warning}")
            for name, value in dev.config().items():
                reg = regs.BY_NAME[name]
                print(f"{name} = {_show(value)}{(' ' + reg.unit) if reg.unit and reg.unit != '1' else ''}")


def cmd_get(args: argparse.Namespace) -> None:
    settings = settings_from(args)
    if _is_device(args.name, args):
        with open_device(settings) as dev:
            print(_show(dev.read(args.name)))
    else:
        settings.as_dict()  # validates
        if args.name not in settings.as_dict():
            raise InputError(f"{args.name}: neither a device register nor a host setting")
        print(settings.as_dict()[args.name])


def cmd_set(args: argparse.Namespace) -> None:
    if _is_device(args.name, args):
        if args.name not in DEVICE_WRITABLE:
            raise InputError(f"{args.name} is read-only (or a command: use the dedicated sub-command)")
        with open_device(settings_from(args)) as dev:
            dev.write(args.name, args.value)
            print(f"{args.name} = {_show(dev.read(args.name))} "
                  f"(device; `trimeter config save` to keep it after a reset)")
    else:
        settings = HostSettings.load()
        settings.set(args.name, args.value, source="command line")
        path = settings.save()
        print(f"{args.name} = {getattr(settings, args.name)!r} (host, {path})")


def cmd_save(args: argparse.Namespace) -> None:
    with open_device(settings_from(args)) as dev:
        dev.command("save_config")
        dev.wait_idle(10.0)
        print("device configuration saved")


def cmd_export(args: argparse.Namespace) -> None:
    settings = settings_from(args)
    with open_device(settings) as dev:
        text = dump_config(dev.config(), dev.identity or dev.check_identity(), settings.port)
    if args.output is None:
        print(text, end="")
        return
    try:
        args.output.write_text(text)
    except OSError as exc:
        raise InputError(f"-o {args.output}: cannot write ({exc.strerror or exc})") from None
    print(f"device configuration written to {args.output}")


def cmd_import(args: argparse.Namespace) -> None:
    values, unknown = read_config(args.file)
    if unknown:  # e.g. items a newer or older firmware had: the rest is still restored
        print(f"skipped, not in this firmware's register map: {listing(unknown)}", file=sys.stderr)
    with open_device(settings_from(args)) as dev:
        dev.write_config(values)
        kept = [n for n in CONFIG_NAMES if n not in values]
        print(f"restored {len(values)} device configuration items"
              + (f"; kept as they were: {', '.join(kept)}" if kept else ""))
        if args.save:
            dev.command("save_config")
            dev.wait_idle(10.0)
            print("device configuration saved")
        else:
            print("not saved: `trimeter config save` to keep it after a reset")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("config", help="device (Modbus) and host (TOML) configuration",
                                   description=__doc__)
    sub = parser.add_subparsers(dest="config_command", metavar="SUBCOMMAND")
    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])
    p = sub.add_parser("list", help="show host settings and the device configuration")
    grp = p.add_mutually_exclusive_group()
    grp.add_argument("--host", action="store_true", help="only the host settings")
    grp.add_argument("--device", action="store_true", help="only the device configuration")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_list)
    p = sub.add_parser("get", help="print one value")
    p.add_argument("name")
    p.add_argument("--host", action="store_true", help="NAME is a host setting")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_get)
    p = sub.add_parser("set", help="set one value (device register or host setting)")
    p.add_argument("name")
    p.add_argument("value")
    p.add_argument("--host", action="store_true", help="NAME is a host setting")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_set)
    p = sub.add_parser("save", help="store the device configuration in its flash (survives resets)")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_save)
    p = sub.add_parser("export", help="back the device configuration up as TOML (by name)")
    p.add_argument("-o", "--output", type=Path, help="file to write (default: stdout)")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_export)
    p = sub.add_parser("import", help="restore a device configuration backup (`config export`)")
    p.add_argument("file", type=Path)
    p.add_argument("--save", action="store_true", help="also store it in the device's flash")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_import)
