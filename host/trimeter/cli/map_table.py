"""`trimeter map flash|verify|slots`: the device's map tables (A/B slots) over Modbus file records.

flash:  validates the device table (DeviceTable.from_bytes: every field, CRC), writes it into the
        inactive slot in chunks, lets the device verify its CRC-32, reads every byte back, and only
        then activates the new slot. Interrupted? Run it again: it resumes where the device stopped,
        and until activation the old map stays active.
verify: reads the active slot (or --slot a|b) back and compares it byte for byte with a file.
slots:  what each slot holds (valid, length, CRC-32, version) and which one is active.
"""

from __future__ import annotations

import zlib
from pathlib import Path

from trimeter.cli._instrument import add_instrument_args, open_device, settings_from
from trimeter.errors import DeviceError


def _read_table(path: str) -> bytes:
    from trimeter.formats.container import read_bounded
    from trimeter.formats.device_table import MAX_BYTES, DeviceTable

    data = read_bounded(Path(path), MAX_BYTES, "map table")  # a larger file is refused unread
    DeviceTable.from_bytes(data, source=path)  # MapFileError (one line) on any defect: never flash garbage
    return data


def _table_crc(data: bytes) -> int:
    """The table's own CRC-32 (its last 4 bytes, little-endian). The slot register's CRC-32 over the whole
    file is the same constant (0x2144DF1C, the CRC residue) for every valid table, so it names nothing."""
    return int.from_bytes(data[-4:], "little") if len(data) >= 4 else zlib.crc32(data)


def _bar(description):
    from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

    return Progress("{task.description}", BarColumn(), DownloadColumn(), TransferSpeedColumn())


def cmd_flash(args):
    data = _read_table(args.table)
    with open_device(settings_from(args)) as dev, _bar("flash") as bar:
        task = bar.add_task(f"writing {Path(args.table).name}", total=len(data) + len(data) % 2)
        slot = dev.flash_map(data, version=args.version,
                             progress=lambda done, total: bar.update(task, completed=done))
    print(f"map table {Path(args.table).name} ({len(data)} bytes, table CRC-32 0x{_table_crc(data):08X}) verified and "
          f"active in slot {slot.name}")


def cmd_verify(args):
    data = _read_table(args.table)
    with open_device(settings_from(args)) as dev:
        status = dev.map_status()
        slot = args.slot or status["map_active_slot"].name.lower()
        if slot == "none":
            raise DeviceError("the device has no active map table")
        back = dev.read_map(slot)
    if back != data:
        raise DeviceError(f"slot {slot.upper()} differs from {args.table} ({len(back)} vs {len(data)} bytes, table "
                          f"CRC-32 0x{_table_crc(back):08X} vs 0x{_table_crc(data):08X})")
    print(f"slot {slot.upper()} matches {args.table} byte for byte ({len(data)} bytes)")


def cmd_slots(args):
    with open_device(settings_from(args)) as dev:
        s = dev.map_status()
        own = {}
        for key in ("a", "b"):
            length = s[f"map_slot_{key}_length"]
            if s[f"map_slot_{key}_valid"] and length >= 4:
                at = (length - 4) & ~1
                own[key] = _table_crc(dev.read_map(key, length - at, offset=at)[-4:])
    print(f"active slot: {s['map_active_slot'].name}  (last operation: {s['map_op_status'].name.lower()}, "
          f"{s['map_op_bytes_written']} bytes written)")
    for key in ("a", "b"):
        valid = bool(s[f"map_slot_{key}_valid"])
        table = f", table CRC-32 0x{own[key]:08X}" if key in own else ""
        print(f"slot {key.upper()}: {'valid' if valid else 'empty/invalid'}, {s[f'map_slot_{key}_length']} bytes, "
              f"version {s[f'map_slot_{key}_version']}{table}")


def register(map_subparsers) -> None:
    p = map_subparsers.add_parser("flash", help="write a map table into the device (A/B, verified)",
                                  description=__doc__)
    p.add_argument("table", help="map table file (maps/<name>.tlut)")
    p.add_argument("--version", type=int, default=1, help="version number stamped on the slot (0-65535)")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_flash)
    p = map_subparsers.add_parser("verify", help="compare a device slot with a map table file", description=__doc__)
    p.add_argument("table")
    p.add_argument("--slot", choices=("a", "b"), help="default: the active slot")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_verify)
    p = map_subparsers.add_parser("slots", help="the device's map slots", description=__doc__)
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_slots)
