"""The spectrometer contract every backend fulfils, and the declarative description of a device.

Units are in the names (`wavelengths_nm`, `integration_time_us`). Integration time is settable *and*
readable: a backend reports what the device actually uses (rounded to its step), not what was asked.
"""

from __future__ import annotations

from typing import Any
from dataclasses import asdict, dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class SpectrometerDescription:
    """What a sequence needs to know about a spectrometer before it measures."""

    model: str
    serial: str
    pixels: int
    wavelength_range_nm: tuple[float, float]
    integration_time_us_limits: tuple[int, int]
    saturation_counts: float
    dark_pixels: tuple[int, ...] = ()
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["wavelength_range_nm"] = list(self.wavelength_range_nm)
        d["integration_time_us_limits"] = list(self.integration_time_us_limits)
        d["dark_pixels"] = list(self.dark_pixels)
        return d


@runtime_checkable
class Spectrometer(Protocol):
    """A spectrometer as trimeter's sequences use it."""

    @property
    def description(self) -> SpectrometerDescription: ...

    def wavelengths_nm(self) -> np.ndarray:
        """Centre wavelength of every pixel/channel, nm, shape (pixels,)."""

    def intensities(self) -> np.ndarray:
        """One exposure at the current integration time: raw counts (dark not subtracted), float64."""

    @property
    def integration_time_us(self) -> int: ...

    @integration_time_us.setter
    def integration_time_us(self, value: int) -> None: ...

    @property
    def integration_time_us_limits(self) -> tuple[int, int]: ...

    @property
    def saturation_counts(self) -> float: ...

    @property
    def dark_pixels(self) -> tuple[int, ...]: ...

    def close(self) -> None: ...


def check_integration_time(value: Any, limits: tuple[int, int]) -> int:
    """Validate a requested integration time against a device's limits (InputError naming the field)."""
    from trimeter.errors import InputError

    try:
        us = int(round(float(value)))
    except (TypeError, ValueError):
        raise InputError(f"integration_time_us must be a number, got {value!r}") from None
    if not np.isfinite(float(value)) or not limits[0] <= us <= limits[1]:
        raise InputError(f"integration_time_us must be within {limits[0]}..{limits[1]} µs, got {value!r}")
    return us
