"""What the instrument commands share: host settings + command-line overrides, opening the device and
the spectrometer, and a rich progress bar for long work."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from trimeter.errors import InputError
from trimeter.sequences.settings import HostSettings

if TYPE_CHECKING:
    from trimeter.device import Device
    from trimeter.spectrometer import Spectrometer


def add_instrument_args(parser: argparse.ArgumentParser, *, spectrometer: bool = True) -> None:
    parser.add_argument("--port", help="serial port of the instrument (default: host config `port`)")
    parser.add_argument("--address", type=int, help="Modbus address (default: host config `address`, 1)")
    if spectrometer:
        parser.add_argument("--spectrometer", help="spectrometer URL, e.g. sim:/dev/pts/5 (default: host config)")


def settings_from(args: argparse.Namespace) -> HostSettings:
    settings = HostSettings.load()
    for key in ("port", "address", "spectrometer"):
        value = getattr(args, key, None)
        if value not in (None, ""):
            settings.set(key, value, source=f"--{key}")
    return settings


def open_device(settings: HostSettings) -> Device:
    from trimeter.device import Device

    if not settings.port:
        raise InputError("port: no instrument port given (use --port or `trimeter config set --host port PATH`)")
    return Device.open(settings.port, address=settings.address, baudrate=settings.baudrate,
                       timeout_s=settings.timeout_s, attempts=settings.attempts, local_echo=bool(settings.local_echo))


def open_spectrometer(settings: HostSettings) -> Spectrometer:
    from trimeter.spectrometer import open_spectrometer as open_url

    if not settings.spectrometer:
        raise InputError("spectrometer: none given (use --spectrometer or `trimeter config set --host spectrometer "
                         "URL`)")
    return open_url(settings.spectrometer)


@contextlib.contextmanager
def progress_bar(description: str = "working") -> Iterator[Callable[[float, str], None]]:
    """Yields on_progress(fraction, message) driving a rich progress bar (plain lines when not a TTY)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description:<44}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeElapsedColumn(), transient=False) as progress:
        task = progress.add_task(description, total=1.0)

        def update(fraction: float, message: str) -> None:
            progress.update(task, completed=max(0.0, min(1.0, fraction)), description=message[:44])

        yield update
        progress.update(task, completed=1.0)
