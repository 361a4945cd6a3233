"""Host configuration: a TOML file in the platformdirs config directory (`trimeter config … --host`).

The device's own configuration lives in the device (holding registers, `save_config`); this file
holds what only the host knows: where the instrument and spectrometer are, where results go, the
sequence parameters. `TRIMETER_CONFIG_DIR` / `TRIMETER_DATA_DIR` override the directories (tests,
the demo, several instruments on one host).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from trimeter.atomic import atomic_write
from trimeter.errors import InputError
from trimeter.geometry import load_geometry
from trimeter.paths import config_dir, data_dir

CONFIG_FILE_NAME = "config.toml"


@dataclass
class HostSettings:
    port: str = ""                     # serial port of the instrument (e.g. /dev/ttyUSB0)
    address: int = 1                   # Modbus slave address
    baudrate: int = 19200
    timeout_s: float = 0.15            # per Modbus request, on top of its frames' time on the wire (transport.py)
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
        return data_dir() / "calibration"

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
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: not valid TOML ({exc}); fix or delete it") from None
        settings = cls()
        for key, value in data.items():
            settings.set(key, value, source=str(path))
        return settings

    def set(self, key: str, value: Any, source: str = "host config") -> None:
        types = {f.name: str(f.type) for f in fields(self)}  # postponed annotations: already the names
        if key not in types:
            raise InputError(f"{key}: no such host setting ({', '.join(types)})")
        kind = {"str": str, "int": int, "float": float}[types[key]]
        try:
            if kind is int and isinstance(value, float) and not value.is_integer():
                raise ValueError
            if isinstance(value, (dict, list, bool)) or value is None:  # str() would take any of them
                raise TypeError
            converted = kind(value) if kind is not int else int(float(value))
        except (TypeError, ValueError, OverflowError):  # OverflowError: an int setting given 1e400
            raise InputError(f"{key}: {value!r} is not a {kind.__name__} ({source})") from None
        if kind is float and not math.isfinite(converted):
            raise InputError(f"{key}: {value!r} is not a finite number ({source})")
        if key in ("frames", "attempts") and converted < 1 or key == "hdr_decades" and not 0 <= converted <= 4:
            raise InputError(f"{key}: {value!r} is out of range ({source})")
        if key in ("timeout_s", "warmup_interval_s", "warmup_timeout_s", "warmup_threshold", "thickness_mm",
                   "calibration_max_age_s", "swap_timeout_s") and converted <= 0:
            raise InputError(f"{key}: must be > 0, got {value!r} ({source})")
        if key == "second_thickness_mm" and converted < 0:
            raise InputError(f"{key}: must be ≥ 0 (0: one sample), got {value!r} ({source})")
        setattr(self, key, converted)

    def save(self) -> Path:
        """Write only what differs from the defaults, so new defaults reach old installs."""
        path = self.path()
        defaults = asdict(HostSettings())
        lines = ["# trimeter host configuration (`trimeter config set --host KEY VALUE`)"]
        for key, value in asdict(self).items():
            if value != defaults[key]:
                lines.append(f"{key} = {_toml_value(value)}")
        return atomic_write(path, "\n".join(lines) + "\n")

    def as_dict(self) -> dict:
        return asdict(self)


def _toml_value(value: object) -> str:
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)
