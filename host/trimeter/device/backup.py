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

import math
import os
import re
import tomllib
from datetime import datetime, timezone
from enum import IntEnum

import numpy as np

from trimeter import registers as regs
from trimeter.device.client import CONFIG_NAMES, Identity
from trimeter.errors import InputError
from trimeter.validation import shown

# A backup is ~2 KB of flat `name = value` lines: anything much larger or deeper is not one, and
# tomllib (recursive) would reach Python's recursion limit on a few thousand nested arrays.
MAX_BACKUP_BYTES = 1 << 20
MAX_NESTING = 8
_MAX_NAME = 64          # longer strings are neither register names nor enum names
_MAX_LISTED = 20        # unknown names listed in a message
# what TOML nesting is made of, strings and comments consumed whole so that their brackets don't count
_TOKENS = re.compile(r'#[^\n]*|"""(?:[^\\]|\\.)*?"""|' r"'''.*?'''|" r'"(?:[^"\\\n]|\\.)*"|' r"'[^'\n]*'|[\[\]{}]",
                     re.S)


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
            # the shortest text that reads back as the same f32 (0.1, not 0.100000001), whatever print options
            # another module set for this process (importing colour-science sets numpy's 1.13 legacy: 6 digits)
            with np.printoptions(legacy=False):
                text = str(np.float32(value))
        else:
            text = str(int(value))
        unit = f"  # {reg.unit}" if reg.unit and reg.unit != "1" else ""
        lines.append(f"{name} = {text}{unit}")
    return "\n".join(lines) + "\n"


def read_config(path: str | os.PathLike[str]) -> tuple[dict, list[str]]:
    """parse_config of a backup file, refused before reading when larger than MAX_BACKUP_BYTES."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_BACKUP_BYTES + 1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) > MAX_BACKUP_BYTES:
        raise InputError(f"{path}: larger than any configuration backup (at most {MAX_BACKUP_BYTES} bytes)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a configuration backup (not UTF-8 text at byte {exc.start})") from None
    return parse_config(text, str(path))


def nesting_depth(text: str) -> int:
    """The deepest nesting of TOML arrays, inline tables and table headers in `text`, found without
    recursion (strings and comments skipped; an unterminated string only makes it larger)."""
    depth = deepest = 0
    for token in _TOKENS.finditer(text):
        char = token.group()
        if char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth = max(0, depth - 1)
    return deepest


def parse_config(text: str, source: str) -> tuple[dict, list[str]]:
    """(values this register map knows, names it does not) from a backup's text. Anything else wrong
    (too large or deep, not TOML, no [device] table, a read-only or non-configuration name, a value
    no register could take) is one InputError, quoting at most SHOWN_CHARS of any value."""
    if len(text) > MAX_BACKUP_BYTES:
        raise InputError(f"{source}: larger than any configuration backup (at most {MAX_BACKUP_BYTES} bytes)")
    if nesting_depth(text) > MAX_NESTING:
        raise InputError(f"{source}: not a configuration backup (nested deeper than {MAX_NESTING} levels)")
    try:
        data = tomllib.loads(text)
    except (ValueError, RecursionError) as exc:  # ValueError: TOMLDecodeError, an integer of > 4300 digits
        raise InputError(f"{source}: not a configuration backup ({str(exc)[:200]})") from None
    device = data.get("device")
    if not isinstance(device, dict) or not device:
        raise InputError(f"{source}: no [device] table with configuration items")
    values, unknown = {}, []
    for name, value in device.items():
        if isinstance(value, (dict, list)):
            raise InputError(f"{source}: [device] {_cut(name)} is a {type(value).__name__}, not a value")
        if name in CONFIG_NAMES:
            if not _plausible(value):
                raise InputError(f"{source}: {name} = {shown(value)} is not a number or a name")
            values[name] = value
        elif name in regs.BY_NAME:
            raise InputError(f"{source}: {name} is not a configuration item (read-only, a command or a live output)")
        else:
            unknown.append(_cut(name))
    if not values:
        raise InputError(f"{source}: none of its items ({listing(unknown)}) is in this firmware's register map")
    return values, unknown


def _plausible(value: object) -> bool:
    """A value some configuration register could take: a finite number within 64 bits, or a short name."""
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return abs(value) < 2**63
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, str) and len(value) <= _MAX_NAME


def _cut(name: str) -> str:
    return name if len(name) <= _MAX_NAME else name[:_MAX_NAME] + "…"


def listing(names: list[str]) -> str:
    """Names for a message: at most _MAX_LISTED of them."""
    more = len(names) - _MAX_LISTED
    return ", ".join(names[:_MAX_LISTED]) + (f" and {more} more" if more > 0 else "")


def config_source_warning(source: int) -> str | None:
    """What to tell a person when the device ignored its saved configuration at boot (input register
    config_source), else None."""
    reasons: dict[int, str] = {
        regs.ConfigSource.OTHER_REGISTER_MAP: "was written by firmware with another register map (a firmware update?)",
        regs.ConfigSource.REFUSED: "fails the firmware's checks"}
    why = reasons.get(source)
    if why is None:
        return None
    return (f"the device runs on its default configuration: the saved one {why} and was ignored; restore a "
            f"backup with `trimeter config import FILE --save`, or set the items and `trimeter config save`")
