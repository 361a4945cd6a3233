"""Host configuration: a TOML file in the platformdirs config directory (`trimeter config … --host`).

The device's own configuration lives in the device (holding registers, `save_config`); this file
holds what only the host knows: where the instrument and spectrometer are, where results go, the
sequence parameters. `TRIMETER_CONFIG_DIR` / `TRIMETER_DATA_DIR` override the directories (tests,
the demo, several instruments on one host).

Several instruments on one host (`trimeter serve` takes them all; one page shows them all): one
`[[instruments]]` table each, after the plain settings. Instruments on one serial port share it as an
RS-485 bus, each at its own Modbus address (the device's `modbus_address`, saved in it); two at one
address of one port are refused here, two devices answering at one address when `serve` starts:

    [[instruments]]
    name = "left"                 # the page, the history and its calibration know it by this
    port = "/dev/ttyUSB0"
    address = 1
    spectrometer = "seabreeze:"
    [[instruments]]
    name = "right"
    port = "/dev/ttyUSB0"         # the same bus
    address = 2
    spectrometer = "i2c:1"

Every other setting applies to each instrument alike. `--port`/`--address` on `serve` take one alone.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Callable, Collection
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from trimeter import registers as regs
from trimeter.atomic import atomic_write
from trimeter.errors import InputError
from trimeter.geometry import load_geometry
from trimeter.paths import config_dir, data_dir
from trimeter.toml_text import toml_table

CONFIG_FILE_NAME = "config.toml"


@dataclass
class HostSettings:
    name: str = ""                     # the instrument's name (its measurements and calibration are kept under it)
    port: str = ""                     # serial port of the instrument (e.g. /dev/ttyUSB0)
    address: int = 1                   # Modbus slave address
    baudrate: int = 19200
    timeout_s: float = 0.15            # per Modbus request beyond its frames' wire time; reads: at most (transport.py)
    attempts: int = 6                  # per Modbus request (a lost one costs ~2 × its timeout)
    local_echo: int = 0                # 1: the RS-485 adapter echoes what it sends (pymodbus strips it)
    spectrometer: str = ""             # spectrometer URL (sim:/dev/pts/N, seabreeze:, i2c:1)
    results_dir: str = ""              # default: <data dir>/results
    white_reference_reflectance: float = 0.0  # 0 = hardware/geometry.toml's value
    warmup_threshold: float = 0.001    # relative lamp change per warmup_interval_s that counts as stable
    warmup_interval_s: float = 10.0
    warmup_timeout_s: float = 900.0
    calibration_max_age_s: float = 1800.0  # device seconds; older calibrations are redone by `serve`
    frames: int = 2                    # exposures averaged per spectrum
    hdr_decades: int = 2               # extra exposures ×10, ×100 … for I_c
    method: str = "lut"                # inversion method (trimeter.fit)
    thickness_mm: float = 0.4          # default sample thickness for `serve`
    map: str = ""                      # appearance map name/path; empty = the shipped map of that thickness
    # `serve` with two samples (the paper's procedure; thick samples need it for α and g): after the
    # first sample the status LED double-blinks until the second is in and the button pressed
    second_thickness_mm: float = 0.0   # 0: one sample per press
    second_map: str = ""               # its map; empty = the shipped map of that thickness
    swap_timeout_s: float = 600.0      # no press for the second sample within this: the first is written alone
    instruments: list[dict[str, Any]] = field(default_factory=list)  # `serve` with several ([[instruments]], above)

    # ---------------------------------------------------------------------------------------
    @property
    def white_reference(self) -> float:
        if self.white_reference_reflectance > 0:
            return self.white_reference_reflectance
        return float(load_geometry("device")["calibration"]["white_reference_reflectance"])

    @property
    def serve_samples(self) -> list[tuple[float, str | None]]:
        """(thickness, map or None for the shipped one) per sample `serve` measures on a press."""
        samples = [(self.thickness_mm, self.map or None)]
        if self.second_thickness_mm > 0:
            samples.append((self.second_thickness_mm, self.second_map or None))
        return samples

    @property
    def results_path(self) -> Path:
        return Path(self.results_dir) if self.results_dir else data_dir() / "results"

    @property
    def calibration_path(self) -> Path:
        """One calibration per instrument: by its name when it has one, else by its Modbus address (address 1
        where every single-instrument host has always kept it)."""
        base = data_dir() / "calibration"
        if self.name:
            return base / "instruments" / self.name
        return base if self.address == 1 else base / f"address-{self.address}"

    @classmethod
    def path(cls) -> Path:
        return config_dir() / CONFIG_FILE_NAME

    @classmethod
    def load(cls) -> "HostSettings":
        path = cls.path()
        if not path.exists():
            return cls()
        try:
            data = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise InputError(f"{path}: not valid TOML ({exc}); fix or delete it") from None
        except OSError as exc:
            raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None
        settings = cls()
        settings.update(data, source=str(path))
        return settings

    def set(self, key: str, value: Any, source: str = "host config") -> None:
        """Set one setting from any source (TOML file, command line, API): converted and checked by SCHEMA."""
        setattr(self, key, checked(key, value, source))

    def update(self, values: dict[str, Any], source: str = "host config") -> None:
        """Set several: every value checked first, so a bad one leaves all as they were."""
        converted = {key: checked(key, value, source) for key, value in values.items()}
        for key, value in converted.items():
            setattr(self, key, value)

    def save(self) -> Path:
        """Write only what differs from the defaults, so new defaults reach old installs."""
        defaults = asdict(HostSettings())
        changed = {key: value for key, value in asdict(self).items() if value != defaults[key]}
        instruments = changed.pop("instruments", [])
        text = toml_table(changed, "trimeter host configuration (`trimeter config set --host KEY VALUE`)")
        for instrument in instruments:
            text += "\n[[instruments]]\n" + toml_table(instrument)
        return atomic_write(self.path(), text)

    def as_dict(self) -> dict:
        return asdict(self)



# ------------------------------------------------------------------------------------ the schema
@dataclass(frozen=True)
class Rule:
    """What one host setting may hold: its type and range (`low`/`high`, `low` excluded when
    `low_open`), or one of `choices()`; a string holds no control character (it is a path or a name)."""
    kind: type
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: Callable[[], Collection] | None = None
    meaning: str = ""
    check: Callable[[Any, str], Any] | None = None  # a structured value's own checker (value, source) → value

    def describe(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(map(str, self.choices()))
        if self.low is None or self.high is None:
            return f"a {self.kind.__name__}"
        return f"within {'(' if self.low_open else '['}{self.low:g}, {self.high:g}]" + (f" ({self.meaning})"
                                                                                          if self.meaning else "")


def _methods() -> Collection[str]:
    from trimeter.inversion.methods import METHODS  # a plug-in registers its method on import: read it now
    return list(METHODS)


def _baudrates() -> Collection[int]:
    return regs.BY_NAME["modbus_baud"].allowed or ()


DAY_S = 86400.0
MAX_THICKNESS_MM = 100.0
MAX_TEXT = 4096
SCHEMA: dict[str, Rule] = {
    "name": Rule(str, meaning="an instrument name", check=lambda value, source: checked_name("name", value, source)),
    "port": Rule(str), "spectrometer": Rule(str), "results_dir": Rule(str), "map": Rule(str), "second_map": Rule(str),
    "address": Rule(int, 1, 247, meaning="a Modbus slave address"),
    "baudrate": Rule(int, choices=_baudrates),
    "timeout_s": Rule(float, 0, 60, low_open=True),
    "attempts": Rule(int, 1, 100),
    "local_echo": Rule(int, 0, 1),
    "white_reference_reflectance": Rule(float, 0, 1, meaning="0: hardware/geometry.toml's value"),
    "warmup_threshold": Rule(float, 0, 1, low_open=True),
    "warmup_interval_s": Rule(float, 0, 3600, low_open=True),
    "warmup_timeout_s": Rule(float, 0, DAY_S, low_open=True),
    "calibration_max_age_s": Rule(float, 0, 365 * DAY_S, low_open=True),
    "frames": Rule(int, 1, 1000),
    "hdr_decades": Rule(int, 0, 4),
    "method": Rule(str, choices=_methods),
    "thickness_mm": Rule(float, 0, MAX_THICKNESS_MM, low_open=True),
    "second_thickness_mm": Rule(float, 0, MAX_THICKNESS_MM, meaning="0: one sample"),
    "swap_timeout_s": Rule(float, 0, DAY_S, low_open=True),
    "instruments": Rule(list, meaning="[[instruments]] tables", check=lambda value, source: checked_instruments(
        value, source)),
}
# One instrument of `instruments`: where it is (port + Modbus address: several on one RS-485 bus share a port),
# its spectrometer, and the name the page and the history know it by.
INSTRUMENT_SCHEMA: dict[str, Rule] = {
    "name": Rule(str), "port": Rule(str), "spectrometer": Rule(str),
    "address": Rule(int, 1, 247, meaning="a Modbus slave address"),
}
MAX_INSTRUMENTS = 64
_INSTRUMENT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,39}")


def checked_name(key: str, value: Any, source: str = "host config", *, required: bool = False) -> str:
    """An instrument name (a path component and a URL segment: 1..40 of A-Z a-z 0-9 . _ -, a letter or digit
    first), or "" when not `required`."""
    text = _checked_by(Rule(str), key, value, source)
    if (text or required) and not _INSTRUMENT_NAME.fullmatch(text):
        raise InputError(f"{key}: {text!r} is not an instrument name (1..40 of A-Z a-z 0-9 . _ -, a letter or "
                         f"digit first) ({source})")
    return text


def checked_instruments(value: Any, source: str = "host config") -> list[dict[str, Any]]:
    """The `instruments` list, each entry checked by INSTRUMENT_SCHEMA, or InputError: a missing name or port, a
    name twice, or two instruments at one address of one port (an address collision on the bus)."""
    if not isinstance(value, list) or len(value) > MAX_INSTRUMENTS:
        raise InputError(f"instruments: must be a list of at most {MAX_INSTRUMENTS} [[instruments]] tables ({source})")
    out: list[dict[str, Any]] = []
    seen_names: dict[str, int] = {}
    seen_addresses: dict[tuple[str, int], str] = {}
    for number, entry in enumerate(value, start=1):
        where = f"instruments[{number}]"
        if not isinstance(entry, dict):
            raise InputError(f"{where}: must be a table {{name, port, address, spectrometer}} ({source})")
        unknown = sorted(set(entry) - set(INSTRUMENT_SCHEMA))
        if unknown:
            raise InputError(f"{where}.{unknown[0]}: no such instrument setting ({', '.join(INSTRUMENT_SCHEMA)}) "
                             f"({source})")
        item: dict[str, Any] = {"name": "", "port": "", "address": 1, "spectrometer": ""}
        for key, raw in entry.items():
            item[key] = _checked_by(INSTRUMENT_SCHEMA[key], f"{where}.{key}", raw, source)
        checked_name(f"{where}.name", item["name"], source, required=True)
        if not item["port"]:
            raise InputError(f"{where}.port: instrument {item['name']!r} names no serial port ({source})")
        if item["name"] in seen_names:
            raise InputError(f"{where}.name: {item['name']!r} is already instruments[{seen_names[item['name']]}] "
                             f"({source})")
        bus_address = (item["port"], item["address"])
        if bus_address in seen_addresses:
            raise InputError(f"{where}: address collision on the bus {item['port']}: {item['name']!r} and "
                             f"{seen_addresses[bus_address]!r} are both at Modbus address {item['address']} "
                             f"(give each instrument on one port its own address) ({source})")
        seen_names[item["name"]] = number
        seen_addresses[bus_address] = item["name"]
        out.append(item)
    return out


def checked(key: str, value: Any, source: str = "host config") -> Any:
    """`value` as host setting `key` holds it (a str from the command line converted), or InputError naming
    the key, the value and the source. Booleans are no numbers; integers take only integral values."""
    rule = SCHEMA.get(key)
    if rule is None:
        raise InputError(f"{key}: no such host setting ({', '.join(SCHEMA)}) ({source})")
    if rule.check is not None:
        return rule.check(value, source)
    return _checked_by(rule, key, value, source)


def _checked_by(rule: Rule, key: str, value: Any, source: str) -> Any:
    shown = repr(value) if len(repr(value)) <= 80 else repr(value)[:77] + "..."
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise InputError(f"{key}: {shown} is not a {rule.kind.__name__} ({source})")
    if rule.kind is str:
        if not isinstance(value, str):
            raise InputError(f"{key}: {shown} is not text ({source})")
        if len(value) > MAX_TEXT or any(ord(c) < 0x20 or ord(c) == 0x7F or 0xD800 <= ord(c) <= 0xDFFF for c in value):
            raise InputError(f"{key}: {shown} holds a control character or is too long ({source})")
        converted: Any = value
    else:
        try:
            number = float(value)  # a command line's text too; a large int beyond a float's range overflows
        except (ValueError, OverflowError):
            raise InputError(f"{key}: {shown} is not a {rule.kind.__name__} ({source})") from None
        if not math.isfinite(number):
            raise InputError(f"{key}: {shown} is not a finite number ({source})")
        if rule.kind is int:
            if not number.is_integer() or isinstance(value, str) and not _INTEGER.fullmatch(value.strip()):
                raise InputError(f"{key}: {shown} is not an integer ({source})")
            converted = int(number)  # exact: every integer setting's range is far below 2**53
        else:
            converted = number
    if rule.choices is not None:
        if converted not in rule.choices():
            raise InputError(f"{key}: {shown} is not {rule.describe()} ({source})")
    elif rule.low is not None and rule.high is not None:
        low_ok = converted > rule.low if rule.low_open else converted >= rule.low
        if not (low_ok and converted <= rule.high):
            raise InputError(f"{key}: {shown} is not {rule.describe()} ({source})")
    return converted


_INTEGER = re.compile(r"[+-]?\d{1,18}(?:\.0*)?")
