"""`seabreeze` backend (optional extra `trimeter[seabreeze]`): Ocean Optics/Insight spectrometers.

python-seabreeze is imported only when this backend is opened; without it the error says how to get it.
Its integration time cannot be read back from the device, so this wrapper keeps the last value it set
(after validating it against the device's limits) and reports that.
"""

from __future__ import annotations

from typing import Any, Self
import numpy as np

from trimeter.errors import DeviceError
from trimeter.spectrometer.base import SpectrometerDescription, check_integration_time


def _import_seabreeze() -> tuple[Any, Any]:
    try:
        from seabreeze.spectrometers import Spectrometer, list_devices
    except ImportError:
        raise DeviceError("the seabreeze backend needs python-seabreeze: pip install 'trimeter[seabreeze]'") from None
    return Spectrometer, list_devices


class SeaBreezeSpectrometer:
    def __init__(self, serial: str | None = None, integration_time_us: int = 100_000) -> None:
        Spectrometer, list_devices = _import_seabreeze()
        try:
            self._spec = Spectrometer.from_serial_number(serial) if serial else Spectrometer.from_first_available()
        except Exception as exc:  # seabreeze raises its own exception types per backend
            found = ", ".join(str(d) for d in list_devices()) or "none"
            raise DeviceError(f"no Ocean spectrometer {serial or ''} (found: {found}): {exc}") from None
        self._wavelengths = np.asarray(self._spec.wavelengths(), dtype=float)
        lo, hi = self._spec.integration_time_micros_limits
        self._limits = (int(lo), int(hi))
        try:
            self._dark = tuple(int(i) for i in self._spec.f.spectrometer.get_electric_dark_pixel_indices())
        except Exception:  # not every model exposes its electrically dark pixels
            self._dark = ()
        self._it_us = 0
        self.integration_time_us = max(self._limits[0], min(self._limits[1], int(float(integration_time_us))))

    @property
    def description(self) -> SpectrometerDescription:
        return SpectrometerDescription(model=str(self._spec.model), serial=str(self._spec.serial_number),
                                       pixels=len(self._wavelengths),
                                       wavelength_range_nm=(float(self._wavelengths[0]), float(self._wavelengths[-1])),
                                       integration_time_us_limits=self._limits,
                                       saturation_counts=float(self._spec.max_intensity), dark_pixels=self._dark)

    def wavelengths_nm(self) -> np.ndarray:
        return self._wavelengths.copy()

    def intensities(self) -> np.ndarray:
        return np.asarray(self._spec.intensities(correct_dark_counts=False, correct_nonlinearity=False), dtype=float)

    @property
    def integration_time_us(self) -> int:
        return self._it_us

    @integration_time_us.setter
    def integration_time_us(self, value: Any) -> None:
        us = check_integration_time(value, self._limits)
        self._spec.integration_time_micros(us)
        self._it_us = us

    @property
    def integration_time_us_limits(self) -> tuple[int, int]:
        return self._limits

    @property
    def saturation_counts(self) -> float:
        return float(self._spec.max_intensity)

    @property
    def dark_pixels(self) -> tuple[int, ...]:
        return self._dark

    def close(self) -> None:
        self._spec.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
