"""A device configuration backup: the persisted holding registers by name, as TOML.

A firmware whose register map differs from the one that saved the configuration ignores the saved
words and runs on defaults (input register config_source says so): the words can't be read by
position across maps. Names can: `trimeter config export` before the update and `trimeter config
import` after it restore every item both maps know, and say which they don't.

    [device]
    steps_per_mm = 80.0
    homing_direction = -1
"""

from __future__ import annotations

import tomllib
from datetime import datetime, timezone
from enum import IntEnum

import numpy as np

from trimeter import registers as regs
from trimeter.device.client import CONFIG_NAMES, Identity
from trimeter.errors import InputError


def dump_config(values: dict, identity: Identity, port: str = "") -> str:
    """TOML text of a device configuration (Device.config()), with where and when it came from."""
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [f"# trimeter device configuration, exported {stamp}" + (f" from {port}" if port else ""),
             f"# firmware {'.'.join(map(str, identity.firmware_version))}, register map 0x{identity.regmap_hash:08X}",
             "# restore: trimeter config import FILE --save", "[device]"]
    for name in CONFIG_NAMES:
        value = values[name]
        reg = regs.BY_NAME[name]
        if isinstance(value, IntEnum):
            text = f'"{value.name.lower()}"'
        elif reg.type == "f32":
            text = str(np.float32(value))  # the shortest text that reads back as the same f32 (0.1, not 0.100000001)
        else:
            text = str(int(value))
        unit = f"  # {reg.unit}" if reg.unit and reg.unit != "1" else ""
        lines.append(f"{name} = {text}{unit}")
    return "\n".join(lines) + "\n"


def parse_config(text: str, source: str) -> tuple[dict, list[str]]:
    """(values this register map knows, names it does not) from a backup's text. Anything else wrong
    (not TOML, no [device] table, a read-only or non-configuration name) is one InputError."""
    try:
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{source}: not a configuration backup ({exc})") from None
    device = data.get("device")
    if not isinstance(device, dict) or not device:
        raise InputError(f"{source}: no [device] table with configuration items")
    values, unknown = {}, []
    for name, value in device.items():
        if isinstance(value, (dict, list)):
            raise InputError(f"{source}: [device] {name} is a {type(value).__name__}, not a value")
        if name in CONFIG_NAMES:
            if not isinstance(value, (int, float, str)) or isinstance(value, bool):
                raise InputError(f"{source}: {name} = {value!r} is not a number or a name")
            values[name] = value
        elif name in regs.BY_NAME:
            raise InputError(f"{source}: {name} is not a configuration item (read-only, a command or a live output)")
        else:
            unknown.append(name)
    if not values:
        raise InputError(f"{source}: none of its items ({', '.join(unknown)}) is in this firmware's register map")
    return values, unknown


def config_source_warning(source) -> str | None:
    """What to tell a person when the device ignored its saved configuration at boot (input register
    config_source), else None."""
    why = {regs.ConfigSource.OTHER_REGISTER_MAP: "was written by firmware with another register map (a firmware "
                                                 "update?)",
           regs.ConfigSource.REFUSED: "fails the firmware's checks"}.get(source)
    if why is None:
        return None
    return (f"the device runs on its default configuration: the saved one {why} and was ignored; restore a "
            f"backup with `trimeter config import FILE --save`, or set the items and `trimeter config save`")
