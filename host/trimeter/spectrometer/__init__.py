"""Spectrometer backends behind one Protocol, chosen by URL — never by global state.

    open_spectrometer("sim:/dev/pts/5")   # the twin's spectrometer (line protocol, see README.md)
    open_spectrometer("i2c:1")            # an AS7341 on /dev/i2c-1 (`i2c:1?address=0x39&gain=64`)
    open_spectrometer("seabreeze:")       # the first Ocean spectrometer (`seabreeze:SERIAL` for one)
    open_spectrometer("mcu:/dev/ttyUSB0") # the instrument's own C12880MA, read by its firmware over Modbus
"""

from __future__ import annotations

from typing import Any
from trimeter.errors import InputError
from trimeter.spectrometer.base import Spectrometer, SpectrometerDescription

__all__ = ["Spectrometer", "SpectrometerDescription", "open_spectrometer", "BACKENDS"]

BACKENDS = ("sim", "i2c", "seabreeze", "mcu")
OPTIONS = {"sim": ("timeout_s",), "i2c": ("address", "gain", "integration_time_us", "valid_timeout_s", "weights"),
           "seabreeze": ("integration_time_us",), "mcu": ("address", "frames", "gain", "linearity", "timeout_s")}


def open_spectrometer(url: str, **options: Any) -> Spectrometer:
    """Open the spectrometer named by `url` (`<backend>:<address>[?key=value&...]`)."""
    if not isinstance(url, str) or ":" not in url:
        raise InputError(f"spectrometer must be '<backend>:<address>' with backend one of {', '.join(BACKENDS)}, got "
                         f"{url!r}")
    backend, _, rest = url.partition(":")
    address, _, query = rest.partition("?")
    for item in filter(None, query.split("&")):
        key, eq, value = item.partition("=")
        if not eq:
            raise InputError(f"spectrometer option {item!r} in {url!r} must be key=value")
        options.setdefault(key, value)
    unknown = sorted(set(options) - set(OPTIONS.get(backend, options)))
    if unknown:
        raise InputError(f"spectrometer option {unknown[0]!r} is not one of {backend}'s: {', '.join(OPTIONS[backend])}")
    if backend == "sim":
        from trimeter.spectrometer.sim import SimSpectrometer

        return SimSpectrometer(address, **options)
    if backend == "i2c":
        from trimeter.spectrometer.i2c import AS7341

        return AS7341.open(address, **options)
    if backend == "seabreeze":
        from trimeter.spectrometer.seabreeze import SeaBreezeSpectrometer

        return SeaBreezeSpectrometer(address or None, **options)
    if backend == "mcu":
        from trimeter.spectrometer.mcu import McuSpectrometer

        return McuSpectrometer(address, **options)
    raise InputError(f"spectrometer backend must be one of {', '.join(BACKENDS)}, got {backend!r} in {url!r}")
