"""`i2c` backend: an ams AS7341 11-channel multispectral sensor on the host's I2C bus, through smbus2.

Register-level driver (datasheet DS000504): power on, integration time from ATIME/ASTEP
(t = (ATIME+1)·(ASTEP+1)·2.78 µs), gain AGAIN (0.5×…512×), and the SMUX, which routes the 8
spectral photodiode pairs (F1-F8), Clear and NIR onto the chip's six ADCs. Reading all channels
takes two measurements: SMUX → {F1-F4, Clear, NIR}, measure, SMUX → {F5-F8, Clear, NIR}, measure.
Each measurement polls STATUS2.AVALID with a timeout (a wedged chip gives a DeviceError, not a hang).

`intensities()` returns the nine spectral channels F1..F8, NIR in the order of `wavelengths_nm()`
(raw ADC counts, the two Clear readings averaged are in `last_clear`). The chip has no masked pixels:
dark correction is by a shuttered frame. The bus is injected (anything with smbus2.SMBus's methods),
as are the clock and sleep, so the driver is tested against a fake chip (tests/spectrometer/fake_as7341.py).
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Callable, Self

import numpy as np

from trimeter.errors import DeviceError, InputError
from trimeter.inversion.bands import BandWeights
from trimeter.spectrometer.base import SpectrometerDescription, check_integration_time

DEFAULT_ADDRESS = 0x39
STEP_US = 2.78

# Registers (bank 0x80+; the 0x60-0x74 bank is not used)
SMUX_RAM = 0x00          # 0x00-0x13: 20 bytes, one 4-bit ADC selector per photodiode half
ENABLE = 0x80
ENABLE_PON, ENABLE_SP_EN, ENABLE_SMUXEN = 0x01, 0x02, 0x10
ATIME = 0x81
ID = 0x92
ID_VALUE, ID_MASK = 0x24, 0xFC
ASTATUS = 0x94           # reading it latches CH0..CH5 (0x95-0xA0, little-endian u16 each)
ASTATUS_ASAT = 0x80
STATUS2 = 0xA3
STATUS2_AVALID = 0x40
CFG1 = 0xAA              # AGAIN in bits 4:0
CFG6 = 0xAF              # SMUX_CMD in bits 4:3
SMUX_CMD_WRITE = 2 << 3
ASTEP_L = 0xCA           # ASTEP_H = 0xCB

GAINS = (0.5, 1, 2, 4, 8, 16, 32, 64, 128, 256, 512)  # AGAIN code = index

# SMUX configurations (ams application note AN000666; the same bytes as Adafruit_AS7341):
# nibble value n routes that photodiode half to ADC n−1 (0 = disconnected).
SMUX_F1_F4 = bytes([0x30, 0x01, 0x00, 0x00, 0x00, 0x42, 0x00, 0x00, 0x50, 0x00,
                    0x00, 0x00, 0x20, 0x04, 0x00, 0x30, 0x01, 0x50, 0x00, 0x06])
SMUX_F5_F8 = bytes([0x00, 0x00, 0x00, 0x40, 0x02, 0x00, 0x10, 0x03, 0x50, 0x10,
                    0x03, 0x00, 0x00, 0x00, 0x24, 0x00, 0x00, 0x50, 0x00, 0x06])
ADC_CHANNELS = {SMUX_F1_F4: ("F1", "F2", "F3", "F4", "Clear", "NIR"),
                SMUX_F5_F8: ("F5", "F6", "F7", "F8", "Clear", "NIR")}
CHANNEL_NM = {"F1": 415.0, "F2": 445.0, "F3": 480.0, "F4": 515.0, "F5": 555.0, "F6": 590.0,
              "F7": 630.0, "F8": 680.0, "NIR": 910.0}


def _code_for_gain(gain: Any) -> int:
    try:
        return GAINS.index(float(gain))  # 64.0 == 64: exact values only, 64.5 is refused
    except (ValueError, TypeError):
        raise InputError(f"gain must be one of {', '.join(f'{g:g}' for g in GAINS)}, got {gain!r}") from None


class AS7341:
    def __init__(self, bus: Any, address: int = DEFAULT_ADDRESS, gain: float = 64, integration_time_us: int = 100_000,
                 valid_timeout_s: float | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, owns_bus: bool = False,
                 weights: str | None = None) -> None:
        """weights: a CSV of measured band weights (else the built-in model's; band_weights)."""
        self._bus, self.address, self._clock, self._sleep = bus, int(address), clock, sleep
        self._weights_path = weights or None
        self._owns_bus = owns_bus
        try:
            self._valid_timeout_s = None if valid_timeout_s is None else float(valid_timeout_s)
        except ValueError:
            raise InputError(f"valid_timeout_s must be a number of seconds, got {valid_timeout_s!r}") from None
        self.last_clear: float | None = None
        self.last_saturated = False
        chip_id = self._read(ID)
        if chip_id & ID_MASK != ID_VALUE:
            raise DeviceError(f"i2c device at 0x{self.address:02x} is not an AS7341 (ID register 0x{chip_id:02x})")
        self._write(ENABLE, ENABLE_PON)
        self.gain = gain
        self.integration_time_us = integration_time_us

    @classmethod
    def open(cls, bus_number: str, address: str = "0x39", **options: Any) -> AS7341:
        """`i2c:1` → /dev/i2c-1 (options from the URL query: address, gain)."""
        try:
            import smbus2
        except ImportError:
            raise DeviceError("the i2c backend needs smbus2 (pip install smbus2)") from None
        try:
            number, addr = int(bus_number), int(str(address), 0)
        except ValueError:
            raise InputError(f"i2c spectrometer must be i2c:<bus number>[?address=0x39], "
                             f"got i2c:{bus_number}") from None
        try:
            bus = smbus2.SMBus(number)
        except OSError as exc:
            raise DeviceError(f"cannot open /dev/i2c-{number}: {exc}") from None
        try:
            return cls(bus, addr, owns_bus=True, **options)
        except BaseException:
            bus.close()
            raise

    # ------------------------------------------------------------------------------- register I/O
    def _read(self, reg: int) -> int:
        try:
            return self._bus.read_byte_data(self.address, reg)
        except OSError as exc:
            raise DeviceError(f"AS7341 at 0x{self.address:02x}: read of register 0x{reg:02x} failed ({exc})") from None

    def _write(self, reg: int, value: int) -> None:
        try:
            self._bus.write_byte_data(self.address, reg, value & 0xFF)
        except OSError as exc:
            raise DeviceError(f"AS7341 at 0x{self.address:02x}: write of register 0x{reg:02x} failed ({exc})") from None

    def _read_block(self, reg: int, length: int) -> bytes:
        try:
            return bytes(self._bus.read_i2c_block_data(self.address, reg, length))
        except OSError as exc:
            raise DeviceError(f"AS7341 at 0x{self.address:02x}: block read at 0x{reg:02x} failed ({exc})") from None

    def _write_block(self, reg: int, data: bytes) -> None:
        try:
            self._bus.write_i2c_block_data(self.address, reg, list(data))
        except OSError as exc:
            raise DeviceError(f"AS7341 at 0x{self.address:02x}: block write at 0x{reg:02x} failed ({exc})") from None

    def _poll(self, ready: Callable[[], object], what: str, timeout_s: float) -> None:
        deadline = self._clock() + timeout_s
        while not ready():
            if self._clock() > deadline:
                raise DeviceError(f"AS7341 at 0x{self.address:02x}: {what} not done within {timeout_s:.3g} s")
            self._sleep(min(0.002, timeout_s / 10))

    # ---------------------------------------------------------------------------- configuration
    @property
    def gain(self) -> float:
        return GAINS[min(self._read(CFG1) & 0x1F, len(GAINS) - 1)]

    @gain.setter
    def gain(self, value: Any) -> None:
        code = _code_for_gain(value)
        self._write(CFG1, (self._read(CFG1) & ~0x1F) | code)

    def _atime_astep(self) -> tuple[int, int]:
        low, high = self._read_block(ASTEP_L, 2)
        return self._read(ATIME), low | high << 8

    @property
    def integration_time_us(self) -> int:
        atime, astep = self._atime_astep()
        return int(round((atime + 1) * (astep + 1) * STEP_US))

    @integration_time_us.setter
    def integration_time_us(self, value: Any) -> None:
        us = check_integration_time(value, self.integration_time_us_limits)
        # The fewest ATIME steps that let ASTEP (≤ 65534) reach the time: the finest resolution.
        atime = min(255, max(0, int(np.ceil(us / (STEP_US * 65535))) - 1))
        astep = min(65534, max(1, int(round(us / (STEP_US * (atime + 1)))) - 1))
        self._write(ATIME, atime)
        self._write_block(ASTEP_L, bytes([astep & 0xFF, astep >> 8]))

    @property
    def integration_time_us_limits(self) -> tuple[int, int]:
        return (6, int(256 * 65535 * STEP_US))

    @property
    def saturation_counts(self) -> float:
        atime, astep = self._atime_astep()
        return float(min(65535, (atime + 1) * (astep + 1)))

    @property
    def dark_pixels(self) -> tuple[int, ...]:
        return ()

    def wavelengths_nm(self) -> np.ndarray:
        return np.array(list(CHANNEL_NM.values()))

    def band_weights(self) -> BandWeights:
        """Each channel's band weights under the build's lamps: measured ones (the `weights` option, a
        CSV as `fit --bands` takes), else the datasheet's responses and the BOM's LEDs
        (trimeter.spectrometer.sensors)."""
        from trimeter.spectrometer.sensors import as7341_weights, read_band_weights

        if self._weights_path is None:
            return as7341_weights()
        return read_band_weights(self._weights_path, what="i2c spectrometer option weights").select(
            list(CHANNEL_NM), where=f"i2c spectrometer option weights {self._weights_path}")

    @property
    def description(self) -> SpectrometerDescription:
        return SpectrometerDescription(
            model="AS7341", serial=f"i2c-0x{self.address:02x}", pixels=len(CHANNEL_NM),
            wavelength_range_nm=(min(CHANNEL_NM.values()), max(CHANNEL_NM.values())),
            integration_time_us_limits=self.integration_time_us_limits, saturation_counts=self.saturation_counts,
            dark_pixels=(), extra={"channels": list(CHANNEL_NM), "gain": self.gain})

    # ------------------------------------------------------------------------------ measurement
    def _configure_smux(self, config: bytes) -> None:
        enable = self._read(ENABLE)
        self._write(ENABLE, enable & ~ENABLE_SP_EN)  # the SMUX must not change under a running measurement
        self._write(CFG6, SMUX_CMD_WRITE)
        self._write_block(SMUX_RAM, config)
        self._write(ENABLE, (enable & ~ENABLE_SP_EN) | ENABLE_PON | ENABLE_SMUXEN)
        self._poll(lambda: not self._read(ENABLE) & ENABLE_SMUXEN, "SMUX configuration", 0.1)

    def _measure(self, config: bytes) -> dict[str, int]:
        self._configure_smux(config)
        timeout = self._valid_timeout_s or 2.0 * self.integration_time_us * 1e-6 + 0.2
        self._write(ENABLE, ENABLE_PON | ENABLE_SP_EN)
        self._poll(lambda: self._read(STATUS2) & STATUS2_AVALID, "spectral measurement (AVALID)", timeout)
        raw = self._read_block(ASTATUS, 13)  # ASTATUS first: it latches the six channels read with it
        self._write(ENABLE, ENABLE_PON)
        self.last_saturated |= bool(raw[0] & ASTATUS_ASAT)
        counts = np.frombuffer(raw[1:], dtype="<u2")
        return dict(zip(ADC_CHANNELS[config], (int(c) for c in counts), strict=True))

    def intensities(self) -> np.ndarray:
        self.last_saturated = False
        low, high = self._measure(SMUX_F1_F4), self._measure(SMUX_F5_F8)
        self.last_clear = 0.5 * (low["Clear"] + high["Clear"])
        merged = {**low, **high, "NIR": 0.5 * (low["NIR"] + high["NIR"])}
        return np.array([float(merged[name]) for name in CHANNEL_NM])

    def close(self) -> None:
        with contextlib.suppress(DeviceError):
            self._write(ENABLE, 0)  # power down
        if self._owns_bus:
            self._bus.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
