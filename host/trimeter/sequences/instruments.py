"""Several instruments on one host: the host config's `instruments`, their ports and buses, one Service each.

Instruments on different ports run fully side by side; instruments on one port share it as an RS-485 bus
(trimeter.device.bus: one open port, one lock, requests in turn). Each instrument is a copy of the host
settings with its own port, address, spectrometer and name — its calibration and its measurements' tag
follow the name (HostSettings.calibration_path, measurement.json's "instrument").
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from trimeter.device.bus import SharedBus, probe_address
from trimeter.errors import DeviceError, InputError
from trimeter.sequences.service import POLL_S, Event, Service
from trimeter.sequences.settings import HostSettings

if TYPE_CHECKING:
    from trimeter.device import Device
    from trimeter.spectrometer import Spectrometer


@dataclass(frozen=True)
class Instrument:
    name: str
    port: str
    address: int
    spectrometer: str


def instruments_of(settings: HostSettings) -> list[Instrument]:
    """The instruments `serve` takes (already checked by the settings schema: names unique, no two at one address of
    one port); none configured: the one of `port`/`address`/`spectrometer` (named `name`, or "instrument")."""
    if settings.instruments:
        return [Instrument(str(i["name"]), str(i["port"]), int(i["address"]), str(i["spectrometer"]))
                for i in settings.instruments]
    return [Instrument(settings.name or "instrument", settings.port, settings.address, settings.spectrometer)]


def settings_for(settings: HostSettings, instrument: Instrument) -> HostSettings:
    """The host settings as this instrument sees them."""
    own = copy.deepcopy(settings)
    own.update({"name": instrument.name, "port": instrument.port, "address": instrument.address,
                "spectrometer": instrument.spectrometer, "instruments": []}, source=f"instrument {instrument.name}")
    return own


class Lab:
    """The buses (one SharedBus per port, opened on first use) and a device/spectrometer factory per instrument."""

    def __init__(self, settings: HostSettings, *, open_bus: Callable[..., SharedBus] | None = None,
                 open_spectrometer: Callable[[HostSettings], Spectrometer] | None = None) -> None:
        self.settings = settings
        self.instruments = instruments_of(settings)
        if not all(i.port for i in self.instruments):
            raise InputError("port: no instrument port given (use --port, or [[instruments]] in the host config)")
        self._open_bus = open_bus or (lambda port: SharedBus(
            port, baudrate=settings.baudrate, timeout_s=settings.timeout_s, attempts=settings.attempts,
            local_echo=bool(settings.local_echo)))
        self._open_spectrometer = open_spectrometer
        self.buses: dict[str, SharedBus] = {}

    def bus(self, port: str) -> SharedBus:
        if port not in self.buses:
            self.buses[port] = self._open_bus(port)
        return self.buses[port]

    def by_name(self, name: str) -> Instrument:
        for instrument in self.instruments:
            if instrument.name == name:
                return instrument
        raise InputError(f"no instrument named {name!r} ({', '.join(i.name for i in self.instruments)})")

    def check_buses(self) -> None:
        """Before serving: on each port with more than one instrument, exactly one device answers at each address
        (DeviceError naming the first collision, or an instrument that does not answer)."""
        ports: dict[str, list[Instrument]] = {}
        for instrument in self.instruments:
            ports.setdefault(instrument.port, []).append(instrument)
        for port, members in ports.items():
            if len(members) < 2:
                continue
            for instrument in members:
                try:
                    probe_address(self.bus(port), instrument.address)
                except DeviceError as exc:
                    raise DeviceError(f"instrument {instrument.name!r}: {exc}") from None

    def open_device(self, instrument: Instrument) -> Device:
        from trimeter.device import Device

        return Device(self.bus(instrument.port).member(instrument.address))

    def open_spectrometer(self, instrument: Instrument) -> Spectrometer:
        if self._open_spectrometer is not None:
            return self._open_spectrometer(settings_for(self.settings, instrument))
        from trimeter.spectrometer import open_spectrometer

        if not instrument.spectrometer:
            raise InputError(f"instrument {instrument.name!r}: no spectrometer given ([[instruments]] spectrometer)")
        return open_spectrometer(instrument.spectrometer)

    def service(self, instrument: Instrument, *, on_event: Callable[[Event], None] | None = None,
                **kwargs: Any) -> Service:
        """A Service for one instrument, its own settings, device and spectrometer. Its button poll is slower by
        the number of instruments on its bus, so their polls together load the bus as one instrument's would."""
        service = Service(lambda: self.open_device(instrument), lambda: self.open_spectrometer(instrument),
                          settings_for(self.settings, instrument), on_event=on_event, **kwargs)
        service.poll_s = POLL_S * sum(i.port == instrument.port for i in self.instruments)
        return service

    def close(self) -> None:
        for bus in self.buses.values():
            bus.close()
        self.buses.clear()
