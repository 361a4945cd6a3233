#!/usr/bin/env python3
"""Generate the register map's C, Python and Markdown forms from hardware/registers.toml.

    python tools/gen_registers.py           # (re)write the generated files
    python tools/gen_registers.py --check   # exit 1 naming each stale file; write nothing

Outputs (committed, each carries a "generated - do not edit" banner):
    firmware/core/registers_gen.h   #defines, enums, identity constants, the descriptor table type
    firmware/core/registers_gen.c   the descriptor table (used by firmware/core/regmap.c)
    host/trimeter/registers.py      plain data: frozen dataclasses, IntEnums, dicts by name
    hardware/registers.md           the table for humans

The TOML is validated first (overlaps, wide values, ranges, enums, defaults); an impossible map
stops the generator with one line naming the item and field.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import tomllib
import zlib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "hardware" / "registers.toml"
OUT_C_HEADER = ROOT / "firmware" / "core" / "registers_gen.h"
OUT_C_SOURCE = ROOT / "firmware" / "core" / "registers_gen.c"
OUT_PY = ROOT / "host" / "trimeter" / "registers.py"
OUT_MD = ROOT / "hardware" / "registers.md"

# Table key in the TOML -> (Modbus reference prefix used as the table id, short C name, bit table?)
TABLES = {
    "coil": (0, "COIL", True),
    "discrete_input": (1, "DI", True),
    "input_register": (3, "IR", False),
    "holding_register": (4, "HR", False),
}
TYPE_WORDS = {"bool": 1, "u16": 1, "i16": 1, "u32": 2, "i32": 2, "f32": 2}
INT_RANGE = {
    "bool": (0, 1),
    "u16": (0, 0xFFFF),
    "i16": (-0x8000, 0x7FFF),
    "u32": (0, 0xFFFFFFFF),
    "i32": (-0x80000000, 0x7FFFFFFF),
}
F32_MAX = 3.4028234663852886e38
ITEM_FIELDS = {"name", "address", "type", "access", "scale", "unit", "min", "max", "default",
               "enum", "allowed", "description"}


class MapError(Exception):
    """An impossible register map; the message names the item and field."""


@dataclass(frozen=True)
class Item:
    name: str
    table: str
    address: int
    type: str
    words: int
    access: str
    scale: float
    unit: str
    min: int | float
    max: int | float
    default: int | float
    enum: str | None
    allowed: tuple[int, ...]
    description: str


def _f32(value: float) -> float:
    """Round to binary32, so limits/defaults mean the same in C and Python."""
    return struct.unpack(">f", struct.pack(">f", value))[0]


def load(path: Path = SOURCE) -> dict:
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise MapError(f"{path}: {exc}") from exc
    if raw.get("schema") != 1:
        raise MapError(f"{path}: schema must be 1, got {raw.get('schema')!r}")
    enums = {}
    for ename, values in raw.get("enums", {}).items():
        if not values or not all(isinstance(v, int) and 0 <= v <= 0xFFFF for v in values.values()):
            raise MapError(f"enums.{ename}: values must be integers 0..65535")
        if len(set(values.values())) != len(values):
            raise MapError(f"enums.{ename}: duplicate value")
        enums[ename] = dict(values)
    items: list[Item] = []
    for table, (_, _, is_bits) in TABLES.items():
        for entry in raw.get(table, []):
            items.append(_item(table, is_bits, entry, enums))
    _check_layout(items)
    identity = raw["identity"]
    version = tuple(int(p) for p in str(identity["firmware_version"]).split("."))
    if len(version) != 3 or not all(0 <= p <= 0xFFFF for p in version):
        raise MapError("identity.firmware_version: must be MAJOR.MINOR.PATCH, each 0..65535")
    transfer = raw["map_transfer"]
    if transfer["records_per_file"] != 10000:
        raise MapError("map_transfer.records_per_file: the spec allows record numbers 0..9999 only")
    return {"items": items, "enums": enums, "identity": identity, "version": version,
            "transfer": transfer}


def _item(table: str, is_bits: bool, entry: dict, enums: dict) -> Item:
    name = entry.get("name", "?")
    where = f"{table} {name}"
    unknown = set(entry) - ITEM_FIELDS
    if unknown:
        raise MapError(f"{where}: unknown field {sorted(unknown)[0]!r}")
    if not name.isidentifier() or name != name.lower():
        raise MapError(f"{where}: name must be a lower-case identifier")
    address = entry.get("address")
    if not isinstance(address, int) or not 0 <= address <= 0xFFFF:
        raise MapError(f"{where}: address must be an integer 0..65535")
    type_ = entry.get("type", "bool" if is_bits else None)
    if type_ not in TYPE_WORDS or (type_ == "bool") != is_bits:
        raise MapError(f"{where}: type {type_!r} not allowed in this table")
    writable_table = table in ("coil", "holding_register")
    access = entry.get("access", "rw" if table == "coil" else "r")
    if access not in ("r", "rw") or (access == "rw" and not writable_table):
        raise MapError(f"{where}: access {access!r} not allowed in this table")
    enum = entry.get("enum")
    if enum is not None and (enum not in enums or type_ != "u16"):
        raise MapError(f"{where}: enum {enum!r} unknown or not on a u16")
    if type_ == "f32":
        lo, hi = -F32_MAX, F32_MAX
        conv = lambda v: _f32(float(v))  # noqa: E731
    else:
        lo, hi = INT_RANGE[type_]
        conv = int
    if enum is not None:
        lo, hi = min(enums[enum].values()), max(enums[enum].values())
    vmin = conv(entry.get("min", lo))
    vmax = conv(entry.get("max", hi))
    if access == "rw" and "default" not in entry:
        raise MapError(f"{where}: a writable item needs an explicit default")
    default = conv(entry.get("default", 0))  # read-only items: the value before the app sets it
    for field, value in (("min", vmin), ("max", vmax), ("default", default)):
        if isinstance(value, float) and not math.isfinite(value):
            raise MapError(f"{where}: {field} must be finite")
        if type_ != "f32" and not INT_RANGE[type_][0] <= value <= INT_RANGE[type_][1]:
            raise MapError(f"{where}: {field} {value} does not fit {type_}")
    if not vmin <= default <= vmax:
        raise MapError(f"{where}: default {default} outside min..max {vmin}..{vmax}")
    if enum is not None and default not in enums[enum].values():
        raise MapError(f"{where}: default {default} is not a value of enum {enum}")
    allowed = tuple(int(v) for v in entry.get("allowed", ()))
    if allowed and (type_ == "f32" or default not in allowed
                    or not all(vmin <= v <= vmax for v in allowed)):
        raise MapError(f"{where}: allowed values must be integers in min..max including the default")
    if enum is not None and sorted(enums[enum].values()) != list(range(int(lo), int(hi) + 1)) and access == "rw":
        allowed = tuple(sorted(enums[enum].values()))
    scale = float(entry.get("scale", 1.0))
    if not math.isfinite(scale) or scale <= 0:
        raise MapError(f"{where}: scale must be a positive number")
    return Item(name=name, table=table, address=address, type=type_, words=TYPE_WORDS[type_],
                access=access, scale=scale, unit=str(entry.get("unit", "")), min=vmin, max=vmax,
                default=default, enum=enum, allowed=allowed,
                description=" ".join(str(entry.get("description", "")).split()))


def _check_layout(items: list[Item]) -> None:
    names: dict[str, Item] = {}
    for it in items:
        if it.name in names:
            raise MapError(f"{it.table} {it.name}: name already used by {names[it.name].table}")
        names[it.name] = it
    for table in TABLES:
        used: dict[int, str] = {}
        for it in (i for i in items if i.table == table):
            if it.address + it.words > 0x10000:
                raise MapError(f"{table} {it.name}: runs past address 65535")
            for a in range(it.address, it.address + it.words):
                if a in used:
                    raise MapError(f"{table} {it.name}: address {a} already used by {used[a]}")
                used[a] = it.name


def regmap_hash(m: dict) -> int:
    """CRC-32 of the canonical JSON of everything that changes what is on the wire."""
    canon = {
        "enums": {k: sorted(v.items(), key=lambda kv: kv[1]) for k, v in sorted(m["enums"].items())},
        "items": [
            [it.name, it.table, it.address, it.type, it.scale, it.unit, it.access,
             it.min, it.max, it.default, it.enum, list(it.allowed)]
            for it in sorted(m["items"], key=lambda i: (TABLES[i.table][0], i.address))
        ],
        "transfer": {k: m["transfer"][k] for k in sorted(m["transfer"])},
    }
    text = json.dumps(canon, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return zlib.crc32(text.encode("ascii")) & 0xFFFFFFFF


def spans(items: list[Item]) -> dict[str, int]:
    """Per table: one past the highest used address (reads below it never raise exception 02)."""
    return {t: max((i.address + i.words for i in items if i.table == t), default=0) for t in TABLES}


# ---------------------------------------------------------------------------------------------- C
def _c_string(s: str) -> str:
    return json.dumps(s, ensure_ascii=True)


def _c_number(it: Item, v: int | float) -> str:
    if it.type == "f32":
        return f"{float(v)!r}f"
    if it.type in ("u16", "u32", "bool"):
        return f"{int(v)}u"
    return f"({int(v)})" if v < 0 else str(int(v))


BANNER = "generated by tools/gen_registers.py from hardware/registers.toml - do not edit; run `make gen`"


def render_c_header(m: dict) -> str:
    items, ident, ver = m["items"], m["identity"], m["version"]
    out = [f"/* {BANNER} */",
           "/* The trimeter Modbus register map: addresses are 0-based PDU addresses. Wide values (u32,",
           " * i32, f32) take two registers, high word first (big-endian word order); see",
           " * hardware/registers.md. Validation helpers over the descriptor table: regmap.h. */",
           "#ifndef TRIMETER_REGISTERS_GEN_H", "#define TRIMETER_REGISTERS_GEN_H", "",
           "#include <stdint.h>", "",
           "/* ---- identity */",
           f"#define TRIMETER_REGMAP_HASH 0x{regmap_hash(m):08X}u",
           f"#define TRIMETER_FIRMWARE_VERSION {_c_string(ident['firmware_version'])}",
           f"#define TRIMETER_FIRMWARE_VERSION_MAJOR {ver[0]}u",
           f"#define TRIMETER_FIRMWARE_VERSION_MINOR {ver[1]}u",
           f"#define TRIMETER_FIRMWARE_VERSION_PATCH {ver[2]}u",
           f"#define TRIMETER_VENDOR_NAME {_c_string(ident['vendor_name'])}",
           f"#define TRIMETER_PRODUCT_CODE {_c_string(ident['product_code'])}",
           f"#define TRIMETER_VENDOR_URL {_c_string(ident['vendor_url'])}",
           f"#define TRIMETER_PRODUCT_NAME {_c_string(ident['product_name'])}",
           f"#define TRIMETER_VENDOR_ID 0x{int(ident['vendor_id']):04X}u",
           f"#define TRIMETER_MODEL_ID {int(ident['model_id'])}u", "",
           "/* ---- map transfer over file records: linear record = (file - 1) * 10000 + record */",
           f"#define TRIMETER_MAP_RECORDS_PER_FILE {m['transfer']['records_per_file']}u",
           f"#define TRIMETER_MAP_SLOT_CAPACITY_BYTES {m['transfer']['slot_capacity_bytes']}u", ""]
    out.append("/* ---- enums */")
    for ename, values in m["enums"].items():
        out.append("typedef enum {")
        for vname, v in sorted(values.items(), key=lambda kv: kv[1]):
            out.append(f"    TRIMETER_{ename.upper()}_{vname.upper()} = {v},")
        out.append(f"}} trimeter_{ename}_t;")
        # inline: only a build that names values (the sim's state dump) carries the strings, not the MCU's
        out.append(f"static inline const char *trimeter_{ename}_name(unsigned value) /* else \"unknown\" */")
        out.append("{")
        out.append("    switch (value) {")
        for vname, v in sorted(values.items(), key=lambda kv: kv[1]):
            out.append(f"    case {v}u: return \"{vname}\";")
        out.append("    default: return \"unknown\";")
        out.append("    }")
        out.append("}")
    out.append("")
    sp = spans(items)
    for table, (_, short, _) in TABLES.items():
        out.append(f"/* ---- {table}s */")
        out.append(f"#define REG_{short}_SPAN {sp[table]}u /* one past the highest used address */")
        for it in (i for i in items if i.table == table):
            stem = f"REG_{short}_{it.name.upper()}"
            out.append(f"#define {stem} {it.address}u")
            if it.table in ("coil", "holding_register"):
                out.append(f"#define {stem}_DEFAULT {_c_number(it, it.default)}")
                out.append(f"#define {stem}_MIN {_c_number(it, it.min)}")
                out.append(f"#define {stem}_MAX {_c_number(it, it.max)}")
        out.append("")
    out += [
        "/* ---- descriptor table (registers_gen.c), sorted by table then address */",
        "typedef enum { REGMAP_COIL = 0, REGMAP_DISCRETE_INPUT = 1, REGMAP_INPUT_REGISTER = 3,",
        "               REGMAP_HOLDING_REGISTER = 4 } regmap_table_t; /* = Modbus reference prefix */",
        "typedef enum { REGMAP_BOOL, REGMAP_U16, REGMAP_I16, REGMAP_U32, REGMAP_I32, REGMAP_F32 }"
        " regmap_type_t;",
        "typedef struct {",
        "    const char *name;",
        "    uint16_t address;",
        "    uint8_t table;      /* regmap_table_t */",
        "    uint8_t type;       /* regmap_type_t */",
        "    uint8_t words;      /* 1, or 2 for wide values */",
        "    uint8_t writable;   /* access rw */",
        "    uint8_t allowed_count;",
        "    const uint32_t *allowed; /* if allowed_count: the only accepted raw values */",
        "    int64_t min, max, def;   /* integer types (raw) */",
        "    float min_f, max_f, def_f; /* f32 */",
        "} regmap_entry_t;", "",
        f"#define REGMAP_ENTRY_COUNT {len(items)}u",
        "extern const regmap_entry_t regmap_entries[REGMAP_ENTRY_COUNT];", "",
        "#endif", ""]
    return "\n".join(out)


def render_c_source(m: dict) -> str:
    items = sorted(m["items"], key=lambda i: (TABLES[i.table][0], i.address))
    out = [f"/* {BANNER} */", '#include "registers_gen.h"', ""]
    for it in items:
        if it.allowed:
            vals = ", ".join(f"{v}u" for v in it.allowed)
            out.append(f"static const uint32_t allowed_{it.name}[] = {{{vals}}};")
    out += ["", "const regmap_entry_t regmap_entries[REGMAP_ENTRY_COUNT] = {"]
    for it in items:
        tname = {"coil": "REGMAP_COIL", "discrete_input": "REGMAP_DISCRETE_INPUT",
                 "input_register": "REGMAP_INPUT_REGISTER",
                 "holding_register": "REGMAP_HOLDING_REGISTER"}[it.table]
        allowed = f"{len(it.allowed)}, allowed_{it.name}" if it.allowed else "0, 0"
        if it.type == "f32":
            ints = "0, 0, 0"
            floats = f"{it.min!r}f, {it.max!r}f, {it.default!r}f"
        else:
            ints = f"{int(it.min)}LL, {int(it.max)}LL, {int(it.default)}LL"
            floats = "0.0f, 0.0f, 0.0f"
        out.append(f"    {{\"{it.name}\", {it.address}, {tname}, REGMAP_{it.type.upper()}, "
                   f"{it.words}, {int(it.access == 'rw')}, {allowed}, {ints}, {floats}}},")
    out += ["};", ""]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------- Python
def _camel(name: str) -> str:
    return "".join(p.capitalize() for p in name.split("_"))


def render_python(m: dict) -> str:
    items, ident, ver = m["items"], m["identity"], m["version"]
    out = [f'"""The trimeter Modbus register map as plain data ({BANNER}).',
           "",
           "Addresses are 0-based PDU addresses. Wide values (u32/i32/f32) span two registers, high word",
           "first (WORD_ORDER = 'big'). physical = raw * scale. See hardware/registers.md.",
           '"""', "",
           "from __future__ import annotations", "",
           "from dataclasses import dataclass",
           "from enum import IntEnum", "",
           f"REGMAP_HASH = 0x{regmap_hash(m):08X}",
           f"FIRMWARE_VERSION = {ver!r}",
           f"VENDOR_NAME = {ident['vendor_name']!r}",
           f"PRODUCT_CODE = {ident['product_code']!r}",
           f"VENDOR_URL = {ident['vendor_url']!r}",
           f"PRODUCT_NAME = {ident['product_name']!r}",
           f"VENDOR_ID = 0x{int(ident['vendor_id']):04X}",
           f"MODEL_ID = {int(ident['model_id'])}",
           'WORD_ORDER = "big"',
           f"MAP_RECORDS_PER_FILE = {m['transfer']['records_per_file']}",
           f"MAP_SLOT_CAPACITY_BYTES = {m['transfer']['slot_capacity_bytes']}",
           "MAP_FILE_REFERENCE_TYPE = 6",
           "# Modbus exception codes this map's rules produce (see registers.md).",
           "EXCEPTION_ILLEGAL_FUNCTION = 1",
           "EXCEPTION_ILLEGAL_DATA_ADDRESS = 2",
           "EXCEPTION_ILLEGAL_DATA_VALUE = 3",
           "EXCEPTION_SERVER_DEVICE_FAILURE = 4", "", ""]
    for ename, values in m["enums"].items():
        out.append(f"class {_camel(ename)}(IntEnum):")
        for vname, v in sorted(values.items(), key=lambda kv: kv[1]):
            out.append(f"    {vname.upper()} = {v}")
        out += ["", ""]
    out.append("ENUMS: dict[str, type[IntEnum]] = {")
    out += [f"    {e!r}: {_camel(e)}," for e in m["enums"]]
    out += ["}", "", "",
            "@dataclass(frozen=True)",
            "class Register:",
            '    """One item of the map. table: coil | discrete_input | input_register | holding_register."""',
            "",
            "    name: str",
            "    table: str",
            "    address: int",
            "    type: str  # bool | u16 | i16 | u32 | i32 | f32",
            "    words: int  # registers it spans (2 for u32/i32/f32)",
            "    access: str  # r | rw",
            "    scale: float",
            "    unit: str",
            "    min: int | float",
            "    max: int | float",
            "    default: int | float",
            "    enum: str | None",
            "    allowed: tuple[int, ...]",
            "    description: str", "", "",
            "REGISTERS: tuple[Register, ...] = ("]
    for it in items:
        out.append(
            f"    Register({it.name!r}, {it.table!r}, {it.address}, {it.type!r}, {it.words}, "
            f"{it.access!r}, {it.scale!r}, {it.unit!r}, {it.min!r}, {it.max!r}, {it.default!r}, "
            f"{it.enum!r}, {it.allowed!r},\n             {it.description!r}),")
    out += [")", "",
            "BY_NAME: dict[str, Register] = {r.name: r for r in REGISTERS}"]
    for table in TABLES:
        out.append(f"{table.upper()}S: dict[str, Register] = "
                   f"{{r.name: r for r in REGISTERS if r.table == {table!r}}}")
    out.append(f"SPANS: dict[str, int] = {spans(items)!r}")
    out.append("")
    return "\n".join(out)


# -------------------------------------------------------------------------------------- Markdown
def _md_value(it: Item, v, enums: dict[str, dict[str, int]]) -> str:
    if it.enum:
        names = {val: n for n, val in enums[it.enum].items()}
        return f"{v} ({names.get(v, '?')})"
    return f"{v:g}" if isinstance(v, float) else str(v)


def render_markdown(m: dict) -> str:
    ident, ver = m["identity"], m["version"]
    out = [f"<!-- {BANNER} -->", "# trimeter Modbus register map", "",
           f"Register-map hash `0x{regmap_hash(m):08X}` · firmware {'.'.join(map(str, ver))} · "
           f"vendor id `0x{int(ident['vendor_id']):04X}` · model id {ident['model_id']}", "",
           "- Modbus RTU, 8N1, default address 1 and 19200 baud. Addresses are 0-based PDU addresses "
           "(mbpoll: `-0`, or add 1).",
           "- Wide values (u32, i32, f32) span two registers, **high word first** (big-endian word "
           "order); f32 is IEEE-754 binary32. A write covering only one word of a wide value is "
           "refused with exception **02**; reading half of one is allowed.",
           "- physical = raw × scale. Writes to read-only or unmapped addresses: exception **02**; "
           "values outside min..max, or not an enum value / allowed value: exception **03**. Reads "
           "of unmapped addresses below the table's span return 0; past it: exception **02**.",
           "- Commands act on write and reply at once; motion only sets a target (discrete input "
           "`busy` tells when it is done).",
           "- The hash is the CRC-32 of the canonical JSON of every item's wire-relevant fields and "
           "the enums (not the descriptions); the host refuses a device whose hash differs.", "",
           "## Device identification (FC 0x2B / MEI 0x0E)", "",
           "| object | value |", "|---|---|",
           f"| 0x00 VendorName | {ident['vendor_name']} |",
           f"| 0x01 ProductCode | {ident['product_code']} |",
           f"| 0x02 MajorMinorRevision | {ident['firmware_version']} |",
           f"| 0x03 VendorUrl | {ident['vendor_url']} |",
           f"| 0x04 ProductName | {ident['product_name']} |", "",
           "## Map table transfer (FC 0x14 / 0x15, file records)", "",
           f"A map slot's bytes are 16-bit records, big-endian, odd length padded with 0x00. Linear "
           f"record k = (file − 1) × {m['transfer']['records_per_file']} + record, record 0…9999, "
           f"reference type 6; slot capacity {m['transfer']['slot_capacity_bytes']} bytes "
           f"(files 1…{-(-m['transfer']['slot_capacity_bytes'] // 2 // m['transfer']['records_per_file'])}). "
           "Sequence: write `map_expected_length`, `map_expected_crc32`, `map_version`, then "
           "`map_command` = begin_write (one FC 0x10 over 16…22 does it in order); FC 0x15 the bytes; "
           "`map_command` = verify; `map_command` = activate; watch `map_op_status`. Writes outside "
           "the open write's length: 02; with no write open: 01. Reads return the slot chosen by "
           "`map_read_slot` (none = the active slot), up to that slot's length (else 02).", ""]
    for table, (_, _, is_bits) in TABLES.items():
        out += [f"## {table.replace('_', ' ')}s", ""]
        if is_bits:
            out += ["| addr | name | access | default | description |", "|---:|---|---|---|---|"]
        else:
            out += ["| addr | name | type | access | scale · unit | min | max | default | description |",
                    "|---:|---|---|---|---|---|---|---|---|"]
        for it in (i for i in m["items"] if i.table == table):
            addr = f"{it.address}" if it.words == 1 else f"{it.address}–{it.address + 1}"
            if is_bits:
                out.append(f"| {addr} | `{it.name}` | {it.access} | "
                           f"{it.default if it.access == 'rw' else ''} | {it.description} |")
                continue
            su = ("" if it.scale == 1.0 else f"{it.scale:g} · ") + (it.unit or "")
            desc = it.description
            if it.allowed:
                desc += f" Allowed: {', '.join(map(str, it.allowed))}."
            rng = tuple(_md_value(it, v, m["enums"]) for v in (it.min, it.max, it.default)) \
                if it.access == "rw" else ("", "", "")
            out.append(f"| {addr} | `{it.name}` | {it.type}{' enum ' + it.enum if it.enum else ''} | "
                       f"{it.access} | {su} | {rng[0]} | {rng[1]} | {rng[2]} | {desc} |")
        out.append("")
    out += ["## Enums", ""]
    for ename, values in m["enums"].items():
        listing = ", ".join(f"{v} {n}" for n, v in sorted(values.items(), key=lambda kv: kv[1]))
        out.append(f"- **{ename}**: {listing}")
    out.append("")
    return "\n".join(out)


def outputs(m: dict) -> dict[Path, str]:
    return {OUT_C_HEADER: render_c_header(m), OUT_C_SOURCE: render_c_source(m),
            OUT_PY: render_python(m), OUT_MD: render_markdown(m)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 naming each generated file that differs; write nothing")
    args = parser.parse_args(argv)
    try:
        m = load()
    except (MapError, KeyError, ValueError, TypeError) as exc:
        print(f"gen_registers: {SOURCE.relative_to(ROOT)}: {exc}", file=sys.stderr)
        return 2
    stale = 0
    for path, text in outputs(m).items():
        rel = path.relative_to(ROOT)
        current = path.read_text(encoding="utf-8") if path.exists() else None
        if current == text:
            continue
        if args.check:
            print(f"gen_registers: {rel} is stale (run `make gen`)", file=sys.stderr)
            stale = 1
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            print(f"gen_registers: wrote {rel}")
    return stale


if __name__ == "__main__":
    sys.exit(main())
