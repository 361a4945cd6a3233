"""The instrument's typed API, generated at import from the register map (trimeter.registers).

    dev = Device.open("/dev/ttyUSB0")            # checks vendor, firmware major, register-map hash
    dev.read("position_slot")                     # -> Slot.WHITE   (enums as IntEnum, floats scaled)
    dev.write("led_panels_level", 0.5)            # physical units; range-checked before it is sent
    dev.command("goto_slot", "white"); dev.wait_idle(timeout_s=10)
    dev.flash_map(table_bytes, version=3)         # chunked file records, resumable, read-back verified
    dev.fit(I_b, I_w, I_c, rho_b, rho_w, thickness_mm=0.4)  # fitted on the device with its active map table

Destructive commands (save_config, load_defaults, map begin_write / activate) are unlocked right before
they are sent (holding register `unlock`, see hardware/registers.md): the firmware refuses them otherwise.

Nothing here knows an address or a type by heart: every name, address, width, scale, range and enum
comes from trimeter.registers (generated from hardware/registers.toml).
"""

from __future__ import annotations

import contextlib
import struct
import time
import zlib
from dataclasses import dataclass, field
from enum import IntEnum
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike

from trimeter import registers as regs
from trimeter.device.transport import (MAX_FILE_RECORD_WORDS, record_words, MAX_READ_BITS, MAX_READ_WORDS, LinkError,
                                       ModbusExceptionReply, RtuTransport, Transport, unsuspected_record_words)
from trimeter.errors import DeviceError, InputError

_STRUCT = {"u16": ">H", "i16": ">h", "u32": ">I", "i32": ">i", "f32": ">f"}
# Device config: what `config list/get/set` show — the rw holding registers that persist with save_config.
# The firmware erases a flash sector before it answers these (STM32F405 at x32: a 16 KiB config sector
# 0.5 s, a 128 KiB map sector 2 s at most), so their replies get that much longer to arrive.
CONFIG_ERASE_S = 0.75
MAP_ERASE_S = 2.5
CONFIG_NAMES = tuple(r.name for r in regs.REGISTERS if r.table == "holding_register" and r.address >= 64)


# What a register holds once decoded: bool, IntEnum, int or float, which one known only from the register
# map at run time, so callers see Any.
Value = Any


# How long a map table read may keep resuming after lost records (a full table on a clean line takes seconds).
MAP_READ_BUDGET_S = 120.0
# A register read lost on the link this often is given up (each loss halves the requests, so a few losses
# reach the shortest; more mean the line carries nothing)
MAX_SPAN_LOSSES = 6

def encode(reg: regs.Register, value: Any) -> list[int]:
    """Physical value -> register words (or [0/1] for a bit), refusing out-of-range values by name. The same
    checks for the command line, the web API and a backup's import: a boolean is no number or name, a
    number no boolean unless 0 or 1."""
    if reg.type == "bool":
        if not (isinstance(value, (bool, str)) or type(value) is int and value in (0, 1)):
            raise InputError(f"{reg.name}: {value!r} is not a boolean (on/off, true/false, 1/0)")
    elif isinstance(value, bool) or not isinstance(value, (int, float, str, np.integer, np.floating)):
        raise InputError(f"{reg.name}: {value!r} is not a number or a name")
    if reg.enum:
        enum = regs.ENUMS[reg.enum]
        try:
            raw: int | float = enum[value.upper()] if isinstance(value, str) else enum(int(value))
        except (KeyError, ValueError):
            names = ", ".join(m.name.lower() for m in enum)
            raise InputError(f"{reg.name}: {value!r} is not one of {names}") from None
        raw = int(raw)
    elif reg.type == "bool":
        if isinstance(value, str):
            lowered = value.strip().lower()
            if lowered not in ("0", "1", "true", "false", "on", "off"):
                raise InputError(f"{reg.name}: {value!r} is not a boolean (on/off, true/false, 1/0)")
            value = lowered in ("1", "true", "on")
        return [1 if value else 0]
    else:
        try:
            physical = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{reg.name}: {value!r} is not a number") from None
        if not np.isfinite(physical):
            raise InputError(f"{reg.name}: {'NaN' if physical != physical else physical} is not a value")
        raw = physical / reg.scale
        if reg.type != "f32":
            if abs(raw - round(raw)) > 1e-6 * max(1.0, abs(raw)):
                raise InputError(f"{reg.name}: {value} is not a multiple of its resolution {reg.scale:g} {reg.unit}")
            raw = int(round(raw))
        lo, hi = reg.min, reg.max
        if not lo <= raw <= hi:
            raise InputError(f"{reg.name}: {value} is outside {lo * reg.scale:g}..{hi * reg.scale:g} "
                             f"{reg.unit}".rstrip())
        if reg.allowed and raw not in reg.allowed:
            raise InputError(f"{reg.name}: {value} is not one of {', '.join(map(str, reg.allowed))}")
    packed = struct.pack(_STRUCT[reg.type], raw)
    return list(struct.unpack(f">{reg.words}H", packed))


def decode(reg: regs.Register, words: list[int]) -> Value:
    """Register words -> physical value (bool, IntEnum, int or float)."""
    if reg.type == "bool":
        return bool(words[0])
    raw = struct.unpack(_STRUCT[reg.type], struct.pack(f">{reg.words}H", *words))[0]
    if reg.enum:
        enum = regs.ENUMS[reg.enum]
        try:
            return enum(raw)
        except ValueError:
            return raw  # an enum value this host does not know: show the number rather than crash
    if reg.type == "f32":
        return raw
    return raw * reg.scale if reg.scale != 1.0 else raw


def _lookup(name: str) -> regs.Register:
    try:
        return regs.BY_NAME[name]
    except KeyError:
        raise InputError(f"no register named {name!r} (see hardware/registers.md)") from None


def light_coils(*, panels: bool, collimated: bool, leds: bool = True) -> list[bool]:
    """Coils 0..5 (every coil of the map, in address order) for a light set-up."""
    want = {"shutter_panel_left_open": panels, "shutter_panel_right_open": panels,
            "shutter_collimated_open": collimated, "led_panel_left_on": leds, "led_panel_right_on": leds,
            "led_collimated_on": leds}
    if sorted(regs.COILS[name].address for name in want) != list(range(regs.SPANS["coil"])):
        raise AssertionError("the light coils are no longer coils 0..N in the register map")
    return [bool(want[name]) for name in sorted(want, key=lambda n: regs.COILS[n].address)]


# Commands the firmware runs only right after an unlock write (hardware/registers.toml, enums.command).
DESTRUCTIVE_COMMANDS = {"save_config": regs.Command.SAVE_CONFIG, "load_defaults": regs.Command.LOAD_DEFAULTS}
# Erases are rate-limited by the firmware (a burst, then about one a minute); what a refusal means.
_ERASE_LIMITED = ("the device's flash erase budget is used up for now (erases are rate-limited to spare the "
                  "flash; input register erase_refusals counts refusals): try again in a minute")

GOTO = {"black": regs.Command.GOTO_BLACK, "white": regs.Command.GOTO_WHITE, "open": regs.Command.GOTO_OPEN}
SLOT = {"black": regs.Slot.BLACK, "white": regs.Slot.WHITE, "open": regs.Slot.OPEN}


# Quantities computed from registers (declared nowhere else): name -> reader.
DERIVED: dict[str, Callable[["Device"], object]] = {
    "position_mm": lambda dev: (lambda v: v["position_steps"] / v["steps_per_mm"])(
        dev.read_many("position_steps", "steps_per_mm")),
}


@dataclass(frozen=True)
class Identity:
    vendor_id: int
    model_id: int
    firmware_version: tuple[int, int, int]
    regmap_hash: int


def _record_dtype(words: type[IntEnum], types: dict[str, str]) -> np.dtype:
    """One bin's records in a fit file as a big-endian numpy record (f32 = two words, high word first, is
    exactly a big-endian float32); offsets from the register map's word enums."""
    return np.dtype({"names": list(types), "formats": list(types.values()),
                     "offsets": [2 * int(words[name.upper()]) for name in types], "itemsize": 2 * int(words["STRIDE"])})


FIT_INPUT_FIELDS = ("i_b", "i_w", "i_c", "rho_b", "rho_w")
FIT_INPUT_DTYPE = _record_dtype(regs.FitInputWord, dict.fromkeys(FIT_INPUT_FIELDS, ">f4"))
FIT_OUTPUT_DTYPE = _record_dtype(regs.FitOutputWord, {"alpha": ">f4", "sigma_t": ">f4", "g": ">f4", "flags": ">u2"})
# One bin of file standalone_result (a standalone press: its calibration, rates and the device's fit).
STANDALONE_DTYPE = _record_dtype(regs.StandaloneWord, {
    **dict.fromkeys(("wavelength_nm", "diffuse", "collimated", "rho_black", "black", "white", "open", "alpha",
                     "sigma_t", "g"), ">f4"), "fit_flags": ">u2", "capture_flags": ">u2"})
# Why a run was refused or stopped (fit_status), as the person at the instrument can act on it.
_FIT_REFUSALS = {
    regs.FitStatus.ERROR_UNAVAILABLE: "this device's firmware was built without the inverse core (input register "
                                      "fit_available is 0): fit on the host, or flash firmware built with it",
    regs.FitStatus.ERROR_NO_TABLE: "the device has no valid active map table: flash one first "
                                   "(trimeter map flash TABLE --port PORT)",
    regs.FitStatus.ERROR_TABLE: "the device's inverse core does not fit with its active map table (a table format it "
                                "does not read): flash a table made for this firmware",
    regs.FitStatus.ABORTED: "the fit was aborted on the device (by another master?)",
}


def table_own_crc32(table: bytes) -> int:
    """What names a map table (input register fit_table_crc32): its own CRC-32, the last 4 bytes (little-endian),
    checked here against the bytes before them. A CRC-32 over a whole table would not do: it is the same
    constant for every table that ends with its own CRC."""
    if len(table) < 8 or zlib.crc32(table[:-4]) != int.from_bytes(table[-4:], "little"):
        raise InputError("not a map table: its last 4 bytes are not the CRC-32 of the bytes before them")
    return int.from_bytes(table[-4:], "little")


STANDALONE_LAMPS = ("panel_left", "panel_right", "collimated")  # input registers standalone_lamp_*
STANDALONE_LAMP_TOLERANCE = regs.StandaloneLamp.TOLERANCE_PERMILLE / 1000  # the device's bound on a lamp's change


@dataclass(frozen=True)
class StandaloneResult:
    """The last standalone press as the device keeps it (registers.toml, enums.standalone_*): its status,
    the bins of file standalone_result (STANDALONE_DTYPE: NaN α, σt, g where not fitted or unusable), and
    what it was fitted with."""

    status: regs.StandaloneStatus
    sequence: int
    bins: np.ndarray
    rho_white: float            # the white reference's reflectance the calibration divided by
    thickness_mm: float
    table_crc32: int
    flagged_bins: int
    integration_us: dict[str, int]  # per set-up (black, white, open): the device's auto-exposure
    # per lamp (STANDALONE_LAMPS): its light on its lamp-monitor photodiode / the calibration's (NaN: not compared)
    lamp_levels: dict[str, float] = field(default_factory=dict)

    def changed_lamps(self) -> dict[str, float]:
        """The lamps whose light differed from the calibration's beyond the device's tolerance."""
        return {lamp: level for lamp, level in self.lamp_levels.items()
                if abs(level - 1.0) > STANDALONE_LAMP_TOLERANCE}  # NaN compares False: not compared, not changed


@dataclass(frozen=True)
class DeviceFit:
    """Per-bin results of a fit on the device: α, σt [1/mm], g (NaN where a flag in
    trimeter.inversion.flags.UNUSABLE is set) and the FitFlag bits; table_crc32 names the map table used
    (table_own_crc32)."""

    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray
    flags: np.ndarray
    table_crc32: int


def _first_difference(a: bytes, b: bytes) -> int:
    # strict=False: the images may differ in length; past the shorter one the answer is its length
    return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))


class Device:
    """A connected trimeter. Construct with `Device.open(port)` or around any Transport (tests)."""

    def __init__(self, transport: Transport, *, check: bool = True, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.transport = transport
        self._clock = clock
        self._sleep = sleep
        self._reconnects_checked = getattr(getattr(transport, "stats", None), "reconnects", 0)
        self.identity = None
        self.identity = self.check_identity() if check else None

    @classmethod
    def open(cls, port: str, *, address: int = 1, baudrate: int = 19200, timeout_s: float = 0.15,
             attempts: int = 6, reconnect_timeout_s: float = 10.0, check: bool = True,
             local_echo: bool = False, late_reply_window_s: float | None = None) -> "Device":
        transport = RtuTransport(port, address=address, baudrate=baudrate, timeout_s=timeout_s,
                                 attempts=attempts, reconnect_timeout_s=reconnect_timeout_s, local_echo=local_echo,
                                 late_reply_window_s=late_reply_window_s)
        try:
            return cls(transport, check=check)
        except BaseException:
            transport.close()
            raise

    def close(self) -> None:
        self.transport.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------------------------- identity
    def check_identity(self) -> Identity:
        """Refuse a device that is not a trimeter, or whose firmware/register map differs from ours."""
        values = self.read_many("vendor_id", "model_id", "firmware_version_major", "firmware_version_minor",
                                "firmware_version_patch", "regmap_hash")
        identity = Identity(values["vendor_id"], values["model_id"],
                            (values["firmware_version_major"], values["firmware_version_minor"],
                             values["firmware_version_patch"]), values["regmap_hash"])
        if identity.vendor_id != regs.VENDOR_ID or identity.model_id != regs.MODEL_ID:
            raise DeviceError(f"the device is not a trimeter (vendor 0x{identity.vendor_id:04X}, model "
                              f"{identity.model_id}; expected 0x{regs.VENDOR_ID:04X}, {regs.MODEL_ID})")
        if identity.firmware_version[0] != regs.FIRMWARE_VERSION[0]:
            raise DeviceError("firmware {} is incompatible with this host (built for {}): update one of them".format(
                ".".join(map(str, identity.firmware_version)), ".".join(map(str, regs.FIRMWARE_VERSION))))
        if identity.regmap_hash != regs.REGMAP_HASH:
            raise DeviceError(f"register map mismatch: device 0x{identity.regmap_hash:08X}, host "
                              f"0x{regs.REGMAP_HASH:08X} (firmware and host were built from different "
                              "hardware/registers.toml): flash matching firmware or update the host")
        return identity

    # ----------------------------------------------------------------------------- read / write
    def read(self, name: str) -> Value:
        if name in DERIVED:
            return DERIVED[name](self)
        return self.read_many(name)[name]

    def read_many(self, *names: str) -> dict[str, Value]:
        """Read several items with as few requests as possible (one per table span)."""
        by_table: dict[str, list[regs.Register]] = {}
        for name in names:
            reg = _lookup(name)
            by_table.setdefault(reg.table, []).append(reg)
        out = {}
        self._after_reconnect()
        for table, items in by_table.items():
            out.update(self._read_spans(table, sorted(items, key=lambda r: r.address)))
        self._after_reconnect()
        return {name: out[name] for name in names}

    def _after_reconnect(self) -> None:
        """The transport reopened the port: whatever answers now may not be the device we checked."""
        stats = getattr(self.transport, "stats", None)
        if stats is not None and stats.reconnects != self._reconnects_checked:
            self._reconnects_checked = stats.reconnects
            if self.identity is not None:
                self.identity = self.check_identity()

    def _read_spans(self, table: str, pending: list[regs.Register]) -> dict[str, Value]:
        """`pending` (sorted by address) in requests of whole registers, each as long as the line carries now:
        a noisy line garbles a long reply far more often than a short one (record_words), so a request the link
        lost to garbled replies shrinks the next ones and its registers are asked for again, in shorter
        requests. A request lost to silence (a link that is gone) is a LinkError at once, as before."""
        out: dict[str, Value] = {}
        bits, losses = table in ("coil", "discrete_input"), 0
        while pending:
            limit = MAX_READ_BITS if bits else min(MAX_READ_WORDS, record_words(self.transport))
            size = 1
            while size < len(pending) and pending[size].address + pending[size].words - pending[0].address <= limit:
                size += 1
            garbled = self._garbled_replies()
            try:
                out.update(self._read_block(table, pending[:size]))
            except LinkError:
                losses += 1
                if size == 1 or losses > MAX_SPAN_LOSSES or self._garbled_replies() == garbled:
                    raise
                continue
            pending = pending[size:]
        return out

    def _garbled_replies(self) -> int | None:
        stats = getattr(self.transport, "stats", None)
        return getattr(stats, "garbled_replies", None)

    def _read_block(self, table: str, items: list[regs.Register]) -> dict[str, Value]:
        """One request for the span of `items` (sorted by address)."""
        lo, hi = items[0].address, max(r.address + r.words for r in items)
        if table in ("coil", "discrete_input"):
            data = [int(b) for b in self.transport.read_bits(table, lo, hi - lo)]
        else:
            data = self.transport.read_words(table, lo, hi - lo)
        return {r.name: decode(r, data[r.address - lo:r.address - lo + r.words]) for r in items}

    def write(self, name: str, value: object) -> None:
        reg = _lookup(name)
        if reg.access != "rw":
            raise InputError(f"{name} is read-only")
        words = encode(reg, value)
        try:
            if reg.table == "coil":
                self.transport.write_bits(reg.address, [bool(words[0])])
            else:
                self.transport.write_words(reg.address, words)
        except ModbusExceptionReply as exc:
            if exc.code == 3:
                raise InputError(f"{name}: the device refused {value!r} (out of range or inconsistent)") from None
            raise

    def write_many(self, values: dict) -> None:
        """Write several items, one request each, in the order given (each is range-checked first)."""
        for name, value in values.items():
            encode(_lookup(name), value)
        for name, value in values.items():
            self.write(name, value)

    def write_config(self, values: dict) -> None:
        """Set device configuration items (CONFIG_NAMES; the others keep their value) in one request,
        which the firmware cross-checks and takes or refuses whole (e.g. a slot inside the homing
        back-off): the configuration block has no holes (registers.toml; tests/device/test_backup.py
        keeps it so). Everything is range-checked before anything is sent."""
        unknown = [n for n in values if n not in CONFIG_NAMES]
        if unknown:
            raise InputError(f"not device configuration items: {', '.join(unknown)}")
        current = self.read_many(*CONFIG_NAMES)
        block = sorted((_lookup(n) for n in CONFIG_NAMES), key=lambda r: r.address)
        words = {r.name: encode(r, values.get(r.name, current[r.name])) for r in block}
        try:
            self.transport.write_words(block[0].address, [w for r in block for w in words[r.name]])
        except ModbusExceptionReply as exc:
            if exc.code == 3:
                changed = [r.name for r in block if words[r.name] != encode(r, current[r.name])]
                raise InputError(f"the device refused the new values of {', '.join(changed) or 'nothing'} as "
                                 f"inconsistent with the rest of its configuration (e.g. a slot inside the homing "
                                 f"back-off, a homing seek longer than its timeout); nothing was changed") from None
            raise

    # ---------------------------------------------------------------------------------- actions
    def command(self, action: str, argument: str | None = None) -> None:
        """`command("home")`, `command("goto_slot", "white")`, `command("clear_fault")`, `command("save_config")`."""
        if action in DESTRUCTIVE_COMMANDS:
            self._destructive_command(action)
            return
        if action == "goto_slot":
            if argument not in GOTO:
                raise InputError(f"goto_slot: slot {argument!r} is not one of {', '.join(GOTO)}")
            cmd: object = GOTO[argument]
        else:
            cmd = action
        self.write("command", cmd)

    def _erasing(self, seconds: float) -> AbstractContextManager[object]:
        """Context for a request the device answers only after a flash erase (transports without timeouts:
        nothing to do)."""
        slow_reply = getattr(self.transport, "slow_reply", None)
        return slow_reply(seconds) if slow_reply is not None else contextlib.nullcontext()

    def unlock(self) -> None:
        """Open the firmware's short window for ONE destructive command (sent next, as its own request)."""
        self.write("unlock", regs.Unlock.KEY)

    def _destructive_command(self, action: str) -> None:
        # A refusal as locked can be a window that closed while a lost request was retried: unlock once more.
        for attempt in (1, 2):
            self.unlock()
            try:
                with self._erasing(CONFIG_ERASE_S):  # save_config; load_defaults erases nothing but is as rare
                    self.write("command", DESTRUCTIVE_COMMANDS[action])
                return
            except ModbusExceptionReply as exc:
                if exc.code == 6:
                    raise DeviceError(f"{action}: {_ERASE_LIMITED}") from None
                if exc.code != 1:
                    raise
                if attempt == 2:
                    raise DeviceError(f"{action}: the device refused it right after an unlock (is the slider "
                                      "moving, or another master writing to it?)") from None

    def set_lights(self, *, panels: bool, collimated: bool, leds: bool = True) -> None:
        """Shutters for one of the set-ups, LEDs kept on (warm) — one FC 0x0F over coils 0..5."""
        self.transport.write_bits(0, light_coils(panels=panels, collimated=collimated, leds=leds))

    def wait_idle(self, timeout_s: float, *, poll_s: float = 0.01) -> None:
        """Poll `busy` until it clears; a latched fault or the timeout raise DeviceError."""
        deadline = self._clock() + timeout_s
        while True:
            busy, fault = self.read_many("busy", "fault").values()
            if fault:
                code = self.read("fault_code")
                name = code.name.lower() if isinstance(code, IntEnum) else code
                raise DeviceError(f"device fault: {name} (send clear_fault after fixing the cause)")
            if not busy:
                return
            if self._clock() >= deadline:
                raise DeviceError(f"device still busy after {timeout_s:g} s (slider or shutter stuck?)")
            self._sleep(poll_s)

    def goto(self, slot: str, timeout_s: float = 30.0) -> None:
        """Move to a slot and wait until it has arrived and settled; homes first after a reset."""
        if not self.read("homed"):
            self.command("home")
            self.wait_idle(timeout_s)
        self.command("goto_slot", slot)
        self.wait_idle(timeout_s)
        at = self.read("position_slot")
        if at != SLOT[slot]:
            raise DeviceError(f"slider did not reach the {slot} slot (device reports {getattr(at, 'name', at)})")

    def config(self) -> dict:
        return self.read_many(*CONFIG_NAMES)

    # ------------------------------------------------------------------------------ map tables
    def map_status(self) -> dict:
        names = [r.name for r in regs.REGISTERS if r.table == "input_register" and r.name.startswith("map_")]
        return self.read_many(*names)

    def flash_map(self, data: bytes, *, version: int, progress: Callable[[int, int], None] | None = None,
                  timeout_s: float = 30.0) -> regs.MapSlot:
        """Write a map table into the inactive slot, have the device verify it, and only then activate it.

        Resumable: if the device already holds an open write of exactly these bytes (same length and
        CRC-32), it continues from the device's progress counter instead of starting again. An
        interruption at any point leaves the previously active slot active."""
        if not data:
            raise InputError("map table is empty")
        if len(data) > regs.MAP_SLOT_CAPACITY_BYTES:
            raise InputError(f"map table is {len(data)} bytes; a device slot holds {regs.MAP_SLOT_CAPACITY_BYTES}")
        crc = zlib.crc32(data)
        padded = data + b"\0" * (len(data) % 2)
        status = self.map_status()
        start = 0
        same = self.read_many("map_expected_length", "map_expected_crc32")
        if (status["map_op_status"] == regs.MapOpStatus.WRITING and same["map_expected_length"] == len(data)
                and same["map_expected_crc32"] == crc):
            # Resume a record boundary below the device's high-water mark (the last frame may be partial).
            start = max(0, (status["map_op_bytes_written"] // 2 - MAX_FILE_RECORD_WORDS)) * 2
        else:
            if status["map_op_status"] == regs.MapOpStatus.WRITING:
                self.write("map_command", "abort")
            self._begin_write(len(data), crc, version)
        total = len(padded)
        offset = start
        while offset < total:
            record = offset // 2
            file_number, record_number = record // regs.MAP_RECORDS_PER_FILE + 1, record % regs.MAP_RECORDS_PER_FILE
            words = min(record_words(self.transport), regs.MAP_RECORDS_PER_FILE - record_number, (total - offset) // 2)
            self.transport.write_file_records(file_number, record_number, padded[offset:offset + 2 * words])
            offset += 2 * words
            if progress:
                progress(offset, total)
        self.write("map_command", "verify")
        result = self._wait_map_op(timeout_s)
        if result == regs.MapOpStatus.ERROR_TABLE:
            raise DeviceError("the device does not accept these bytes as a map table (its header: magic, version, "
                              "sizes, grid or sample set-up, or its own CRC-32); the old map stays active")
        if result != regs.MapOpStatus.VERIFY_OK:
            raise DeviceError(f"map verify failed on the device ({getattr(result, 'name', result)}); "
                              "the old map stays active")
        # The device's verify read the written flash back and checked its CRC-32. Where the firmware
        # also lets us read the not-yet-active slot, compare every byte before activating.
        old_active = self.read("map_active_slot")
        target = regs.MapSlot.B if old_active == regs.MapSlot.A else regs.MapSlot.A
        try:
            back = self.read_map(target, len(data))
        except ModbusExceptionReply:
            back = None  # this firmware serves only valid (activated) slots: check right after activation
        if back is not None and back != data:
            self.write("map_command", "abort")
            raise DeviceError(f"map read-back differs at byte {_first_difference(back, data)}; not activated, "
                              "the old map stays active")
        with self._erasing(CONFIG_ERASE_S):  # activate commits the storage record to a config sector
            result = self._unlocked_map_command("activate", timeout_s)
        active = self.read("map_active_slot")
        if result != regs.MapOpStatus.ACTIVATED or active != target:
            raise DeviceError(f"map activation failed ({getattr(result, 'name', result)}, active slot "
                              f"{getattr(active, 'name', active)})")
        status = self.map_status()
        key = target.name.lower()
        if status[f"map_slot_{key}_length"] != len(data) or status[f"map_slot_{key}_crc32"] != crc:
            raise DeviceError(f"slot {target.name} reports length {status[f'map_slot_{key}_length']} / CRC-32 "
                              f"0x{status[f'map_slot_{key}_crc32']:08X} after activation, expected {len(data)} / "
                              f"0x{crc:08X}")
        if back is None:
            back = self.read_map(target, len(data))
            if back != data:
                raise DeviceError(f"map read-back after activation differs at byte {_first_difference(back, data)}: "
                                  "flash the table again")
        return target

    def _begin_write(self, length: int, crc: int, version: int) -> None:
        # One FC 0x10 over 16..22: parameters first, the command last (hardware/registers.md).
        first = regs.BY_NAME["map_expected_length"].address
        words = [0] * (regs.BY_NAME["map_command"].address + 1 - first)
        for name, value in (("map_expected_length", length), ("map_expected_crc32", crc),
                            ("map_version", version), ("map_read_slot", 0), ("map_command", "begin_write")):
            reg = regs.BY_NAME[name]
            words[reg.address - first:reg.address - first + reg.words] = encode(reg, value)
        with self._erasing(MAP_ERASE_S):  # begin_write erases the slot's sector
            status = self._unlocked_map_command(lambda: self.transport.write_words(first, words))
        if status != regs.MapOpStatus.WRITING:
            raise DeviceError(f"device did not open a map write (status {getattr(status, 'name', status)})")

    def _unlocked_map_command(self, send: str | Callable[[], object], timeout_s: float = 0.0) -> Value:
        """Unlock, send a destructive map command (a map_command name, or a callable that writes it), and
        return map_op_status; refused as locked (the window closed while a request was retried): once more."""
        for _attempt in (1, 2):
            self.unlock()
            if callable(send):
                send()
            else:
                self.write("map_command", send)
            status = self._wait_map_op(timeout_s) if timeout_s else self.read("map_op_status")
            if status != regs.MapOpStatus.ERROR_LOCKED:
                break
        if status == regs.MapOpStatus.ERROR_BUSY:
            raise DeviceError(f"map flash: {_ERASE_LIMITED}; the old map stays active")
        if status == regs.MapOpStatus.ERROR_LOCKED:
            raise DeviceError("the device refused the map command as locked twice right after an unlock "
                              "(is another master writing to it?); the old map stays active")
        return status

    def _wait_map_op(self, timeout_s: float) -> Value:
        deadline = self._clock() + timeout_s
        while True:
            status = self.read("map_op_status")
            if status != regs.MapOpStatus.WRITING or self._clock() >= deadline:
                return status
            self._sleep(0.01)

    # ----------------------------------------------------------------------------- fit on the device
    @property
    def fit_capacity(self) -> int:
        """Bins the device fits in one run (the register map's max of fit_bin_count)."""
        return int(regs.BY_NAME["fit_bin_count"].max)

    def fit(self, I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike, rho_b: ArrayLike, rho_w: ArrayLike, *,
            thickness_mm: float, table: bytes | None = None,
            timeout_s: float = 30.0) -> DeviceFit:
        """Fit bins on the device with its active map table, in runs of at most `fit_capacity` bins.

        Any number of bins; NaN, negative or out-of-range values are the device's to flag (like the host's
        fit), not refused here. `thickness_mm` is the sample's: the device refuses a run unless it is its
        table's ℓ. `table` (a .tlut file's bytes): the device must have fitted with exactly that table.
        Raises InputError for unusable arguments or a thickness the table is not for, DeviceError when the
        device cannot fit (no inverse core, no table, another table than the one given, a table changed
        between runs)."""
        try:
            columns = [np.asarray(v, dtype=np.float64) for v in (I_b, I_w, I_c, rho_b, rho_w)]
        except (TypeError, ValueError):
            raise InputError("fit on the device: I_b, I_w, I_c, rho_b and rho_w must be arrays of numbers") from None
        n = columns[0].size
        if any(c.ndim != 1 or c.size != n for c in columns) or n == 0:
            raise InputError("fit on the device: I_b, I_w, I_c, rho_b and rho_w must be 1-D arrays of one length "
                             f"(got shapes {', '.join(str(c.shape) for c in columns)})")
        thickness_words = encode(regs.BY_NAME["fit_thickness_mm"], thickness_mm)  # range-checked before sending
        expected = None if table is None else table_own_crc32(table)
        bins = np.zeros(n, dtype=FIT_INPUT_DTYPE)
        for name, column in zip(FIT_INPUT_FIELDS, columns, strict=True):
            with np.errstate(over="ignore"):  # beyond float32: inf, which the device flags like any bad value
                bins[name] = column.astype(np.float32)
        results = np.zeros(n, dtype=FIT_OUTPUT_DTYPE)
        used = None
        for first in range(0, n, self.fit_capacity):
            chunk = bins[first:first + self.fit_capacity]
            self._write_fit_bins(chunk)
            crc = self._run_fit(len(chunk), thickness_words, thickness_mm, timeout_s)
            if expected is not None and crc != expected:
                raise DeviceError(f"the device fits with another map table (CRC-32 0x{crc:08X}) than the one given "
                                  f"(0x{expected:08X}): flash it (trimeter map flash TABLE --port PORT)")
            if used is not None and crc != used:
                raise DeviceError(f"the device's active map table changed during the fit (CRC-32 0x{used:08X}, "
                                  f"then 0x{crc:08X}): fit again")
            used = crc
            results[first:first + len(chunk)] = self._read_fit_results(len(chunk))
        assert used is not None  # n > 0 bins: at least one run
        return DeviceFit(alpha=results["alpha"].astype(np.float64), sigma_t=results["sigma_t"].astype(np.float64),
                         g=results["g"].astype(np.float64), flags=results["flags"].astype(np.int64),
                         table_crc32=int(used))

    def _write_fit_bins(self, bins: np.ndarray) -> None:
        stride = int(regs.FitInputWord.STRIDE)
        first = 0
        while first < len(bins):
            per_request = max(1, record_words(self.transport) // stride)
            try:
                self.transport.write_file_records(regs.FitFile.INPUT, first * stride,
                                                  bins[first:first + per_request].tobytes())
            except ModbusExceptionReply as exc:
                if exc.code == 6:
                    raise DeviceError("the device is busy with another fit (another master?): try again") from None
                raise
            first += per_request

    def _run_fit(self, count: int, thickness_words: list[int], thickness_mm: float, timeout_s: float) -> int:
        """One run over bins 0..count-1; returns the CRC-32 of the table it used."""
        # One FC 0x10 over 24..27: the parameters first, the command last (hardware/registers.md).
        first = regs.BY_NAME["fit_bin_count"].address
        words = [0] * (regs.BY_NAME["fit_command"].address + 1 - first)
        for name, value in (("fit_bin_count", encode(regs.BY_NAME["fit_bin_count"], count)),
                            ("fit_thickness_mm", thickness_words),
                            ("fit_command", encode(regs.BY_NAME["fit_command"], regs.FitCommand.RUN))):
            reg = regs.BY_NAME[name]
            words[reg.address - first:reg.address - first + reg.words] = value
        try:
            self.transport.write_words(first, words)
        except ModbusExceptionReply as exc:
            status = self.read("fit_status")
            if exc.code == 3 and status == regs.FitStatus.ERROR_GEOMETRY:
                raise InputError(f"the device's active map table is not for a {thickness_mm:g} mm sample: state the "
                                 "sample's thickness, or flash the table for it") from None
            if exc.code == 6:
                raise DeviceError("the device is busy with another fit (another master?): try again") from None
            if status in _FIT_REFUSALS:
                raise DeviceError(f"fit on the device: {_FIT_REFUSALS[status]}") from None
            raise
        deadline = self._clock() + timeout_s
        while True:
            values = self.read_many("fit_status", "fit_bins_done", "fit_table_crc32")
            status = values["fit_status"]
            if status == regs.FitStatus.DONE:
                return values["fit_table_crc32"]
            if status == regs.FitStatus.ERROR_CORE:
                raise DeviceError(f"the device's inverse core failed after {values['fit_bins_done']} of {count} bins")
            if status != regs.FitStatus.BUSY:
                why = _FIT_REFUSALS.get(status, f"unexpected fit_status {getattr(status, 'name', status)}")
                raise DeviceError(f"fit on the device: {why}")
            if self._clock() >= deadline:
                self.write("fit_command", regs.FitCommand.ABORT)
                raise DeviceError(f"the device fitted {values['fit_bins_done']} of {count} bins in {timeout_s:g} s; "
                                  "aborted")
            self._sleep(0.005)

    def standalone_result(self) -> StandaloneResult:
        """The last standalone press's result; DeviceError while a press runs or before any press."""
        setups = ("black", "white", "open")
        values = self.read_many("standalone_status", "standalone_bins", "standalone_sequence",
                                "white_reference_reflectance", "standalone_thickness_mm", "standalone_table_crc32",
                                "standalone_flagged_bins", *(f"standalone_integration_{k}_us" for k in setups),
                                *(f"standalone_lamp_{lamp}" for lamp in STANDALONE_LAMPS))
        status = values["standalone_status"]
        if status == regs.StandaloneStatus.BUSY:
            raise DeviceError("a standalone press is running on the device: wait for its status LED")
        if status == regs.StandaloneStatus.NONE or not values["standalone_bins"]:
            raise DeviceError("the device holds no standalone result: no press since it started")
        data = self._read_rows(regs.StandaloneFile.RESULT, int(values["standalone_bins"]),
                               int(regs.StandaloneWord.STRIDE))
        return StandaloneResult(regs.StandaloneStatus(status), int(values["standalone_sequence"]),
                                np.frombuffer(data, dtype=STANDALONE_DTYPE),
                                float(values["white_reference_reflectance"]), float(values["standalone_thickness_mm"]),
                                int(values["standalone_table_crc32"]), int(values["standalone_flagged_bins"]),
                                {k: int(values[f"standalone_integration_{k}_us"]) for k in setups},
                                {lamp: float(values[f"standalone_lamp_{lamp}"]) for lamp in STANDALONE_LAMPS})

    def _read_fit_results(self, count: int) -> np.ndarray:
        return np.frombuffer(self._read_rows(regs.FitFile.OUTPUT, count, int(regs.FitOutputWord.STRIDE)),
                             dtype=FIT_OUTPUT_DTYPE)

    def _read_rows(self, file_number: int, count: int, stride: int) -> bytes:
        """`count` rows of `stride` words from a file, as many whole rows per request as the line carries now."""
        out, first = bytearray(), 0
        while first < count:
            rows = min(max(1, record_words(self.transport) // stride), count - first)
            out += self.transport.read_file_records(file_number, first * stride, rows * stride)
            first += rows
        return bytes(out)

    def read_map(self, slot: regs.MapSlot | str, length: int | None = None, *, offset: int = 0,
                 progress: Callable[[int, int], None] | None = None,
                 time_budget_s: float = MAP_READ_BUDGET_S, on_data: Callable[[bytes], None] | None = None) -> bytes:
        """Read `length` bytes of a slot from `offset` (even) through file records (map_read_slot selects it).
        `on_data` is handed each record's bytes as they arrive, so a caller keeps them when the read fails (the
        last may carry a pad byte past an odd `length`).

        Resumable: a record the link loses (every transport attempt failed) is asked for again, from where the
        read stopped, for as long as `time_budget_s` allows; only then the LinkError is raised. Lost to silence,
        it is asked after the link is reopened and the slot selected again (the adapter may be wedged, the
        device reset); lost to garbled replies, at once (the line is there, only noisy, and the records shrank).
        A table is hundreds of records: on a noisy line, restarting it whole at each lost one would rarely
        finish."""
        slot = regs.MapSlot[slot.upper()] if isinstance(slot, str) else regs.MapSlot(slot)
        if offset % 2:
            raise InputError("map read offset must be even (16-bit records)")
        if length is None:
            length = self.read(f"map_slot_{slot.name.lower()}_length") - offset
        deadline = time.monotonic() + time_budget_s
        out = bytearray()
        total = length + length % 2
        selected = False
        try:
            while len(out) < total:
                record = (offset + len(out)) // 2
                file_number, record_number = record // regs.MAP_RECORDS_PER_FILE + 1, record % regs.MAP_RECORDS_PER_FILE
                words = unsuspected_record_words(self.transport, min(
                    record_words(self.transport), regs.MAP_RECORDS_PER_FILE - record_number, (total - len(out)) // 2))
                garbled = self._garbled_replies()
                try:
                    if not selected:
                        self.write("map_read_slot", slot)
                        selected = True
                    chunk = self.transport.read_file_records(file_number, record_number, words)
                except LinkError:
                    if time.monotonic() >= deadline:
                        raise
                    if (stats := getattr(self.transport, "stats", None)) is not None:
                        stats.resumed_reads += 1
                    if selected and garbled is not None and self._garbled_replies() != garbled:
                        continue  # lost to garbled replies: the line is there, only noisy; the records shrank
                    selected = False  # a reopened link may find a reset device: select the slot again
                    reopen = getattr(self.transport, "reopen", None)
                    if reopen is not None:
                        reopen()
                    continue
                out += chunk
                if on_data:
                    on_data(chunk)
                if progress:
                    progress(len(out), total)
        finally:
            if selected:
                with contextlib.suppress(LinkError):  # unselecting is tidiness; the read itself is done or raising
                    self.write("map_read_slot", regs.MapSlot.NONE)
        return bytes(out[:length])
