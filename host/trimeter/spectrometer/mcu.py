"""The instrument's own micro-spectrometer (a Hamamatsu C12880MA read by the firmware), over the device's
Modbus link: `mcu:/dev/ttyUSB0` (`mcu:PORT?address=1&frames=4&gain=1`).

The firmware captures (firmware/core/c12880.h): it integrates, checks each frame's EOS and saturation and
averages `frames` frames; this backend starts a capture (spectro_command), waits for it and reads the
288 averaged pixels from file spectro_light (mean counts × 16). What it adds on the host:
- wavelengths: the unit's test-sheet polynomial, read from the device (spectro_wl_*: what `trimeter config
  set` stored there), so a host never assumes a typical unit's;
- linearity: counts above LINEARITY_KNEE_COUNTS are corrected by the unit's quadratic coefficient
  (`linearity=`; 0 by default: the twin's chip is linear up to saturation, a real unit's sheet or a bench
  measurement gives its own);
- a saturated capture (the firmware's flag: some frame reached full scale) reports its brightest pixel at
  full scale, so the sequences' saturation checks and auto-exposure see it whatever the average says;
- dark: `dark()` captures with every shutter closed by the firmware (capture_dark); the sequences take
  their own dark frames through the shutters as for every backend, which is what their rates use.
The integration time is the ST pulse's: set in µs, rounded by the device to whole CLK periods, and
read back as the device will use it.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from trimeter import registers as regs
from trimeter.device.transport import record_words
from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer.base import SpectrometerDescription, check_integration_time
from trimeter.spectrometer.sensors import C12880_FWHM_NM, C12880_PIXELS, c12880_wavelengths_nm

COEFFICIENTS = ("spectro_wl_a0", "spectro_wl_b1", "spectro_wl_b2", "spectro_wl_b3", "spectro_wl_b4", "spectro_wl_b5")
ADC_FULL_SCALE = 4095.0
RECORD_SCALE = 16.0          # file records: mean counts × 16
RECORDS_PER_READ = 120       # one FC 0x14 sub-request's worth (≤ 125 words in a reply)
INTEGRATION_EXTRA_CLOCKS = 48  # integration = ST high + 48 CLK (datasheet)
ST_HIGH_MIN_CLOCKS = 6
FRAME_OVERHEAD_CLOCKS = 378  # ST low: the readout up to EOS
LINEARITY_KNEE_COUNTS = 2000.0
CAPTURE_MARGIN_S = 2.0       # on top of the frames' own time: the link and the main loop
POLL_S = 0.005


class McuSpectrometer:
    """The C12880MA behind the firmware, as a trimeter.spectrometer.Spectrometer."""

    def __init__(self, port: str, *, address: Any = 1, frames: Any = 4, gain: Any = 1, linearity: Any = 0.0,
                 timeout_s: Any = 0.15, device: Any = None) -> None:
        """device: an open trimeter.device.Device to use (tests, or a caller sharing its link); else one is
        opened on `port` (the instrument's Modbus port)."""
        try:
            self._frames, self._gain = int(frames), int(gain)
            self._linearity, address = float(linearity), int(address)
        except (TypeError, ValueError):
            raise InputError(f"mcu: frames, gain, address must be integers and linearity a number, got "
                             f"frames={frames!r} gain={gain!r} address={address!r} linearity={linearity!r}") from None
        if not 1 <= self._frames <= int(regs.BY_NAME["spectro_frames"].max):
            raise InputError(f"mcu: frames must be within 1..{int(regs.BY_NAME['spectro_frames'].max)}, got {frames!r}")
        if self._gain not in regs.BY_NAME["spectro_gain"].allowed:
            raise InputError(f"mcu: gain must be one of {list(regs.BY_NAME['spectro_gain'].allowed)}, got {gain!r}")
        if not np.isfinite(self._linearity) or abs(self._linearity) > 1e-3:
            raise InputError(f"mcu: linearity must be a small quadratic coefficient (|c| ≤ 1e-3), got {linearity!r}")
        self._owns_device = False
        if device is None:
            from trimeter.device import Device
            from trimeter.device.transport import live_transport

            if not port:
                raise InputError("mcu: give the instrument's Modbus port, e.g. mcu:/dev/ttyUSB0")
            shared = live_transport(port, address)  # the instrument's link, already open in this process
            if shared is not None:
                device = Device(shared, check=False)
            else:
                device = Device.open(port, address=address, timeout_s=float(timeout_s))
                self._owns_device = True
        self.device = device
        try:
            self._setup(port)
        except BaseException:
            self.close()
            raise

    def _setup(self, port: str) -> None:
        d = self.device
        info = d.read_many("spectro_pixels", "spectro_clock_hz", "spectro_integration_us", *COEFFICIENTS)
        if info["spectro_pixels"] != C12880_PIXELS or not info["spectro_clock_hz"]:
            raise DeviceError(f"mcu:{port}: the device has no micro-spectrometer (spectro_pixels "
                              f"{info['spectro_pixels']}, CLK {info['spectro_clock_hz']} Hz)")
        self.clock_hz = int(info["spectro_clock_hz"])
        self.coefficients = tuple(float(info[c]) for c in COEFFICIENTS)
        self._wavelengths = c12880_wavelengths_nm(self.coefficients)
        if not np.all(np.diff(self._wavelengths) > 0):  # the firmware refuses such a polynomial: a link error
            raise DeviceError(f"mcu:{port}: the device's wavelength polynomial is not increasing")
        lo = int(np.ceil((ST_HIGH_MIN_CLOCKS + INTEGRATION_EXTRA_CLOCKS) * 1e6 / self.clock_hz))
        self._limits = (max(lo, int(regs.BY_NAME["spectro_integration_us"].min)),
                        int(regs.BY_NAME["spectro_integration_us"].max))
        d.write_many({"spectro_frames": self._frames, "spectro_gain": self._gain})
        self._integration_us = int(info["spectro_integration_us"])
        if not self._limits[0] <= self._integration_us <= self._limits[1]:
            self.integration_time_us = self._limits[0]
        self._description = SpectrometerDescription(
            model="C12880MA", serial=f"mcu:{port}", pixels=C12880_PIXELS,
            wavelength_range_nm=(float(self._wavelengths[0]), float(self._wavelengths[-1])),
            integration_time_us_limits=self._limits, saturation_counts=ADC_FULL_SCALE,
            extra={"clock_hz": self.clock_hz, "frames_on_device": self._frames, "gain": self._gain,
                   "coefficients": list(self.coefficients), "fwhm_nm": C12880_FWHM_NM})
        self.last_capture_s = 0.0

    # ------------------------------------------------------------------------------- the Protocol
    @property
    def description(self) -> SpectrometerDescription:
        return self._description

    def wavelengths_nm(self) -> np.ndarray:
        return self._wavelengths.copy()

    @property
    def integration_time_us(self) -> int:
        return self._integration_us

    @integration_time_us.setter
    def integration_time_us(self, value: int) -> None:
        us = check_integration_time(value, self._limits)
        self.device.write("spectro_integration_us", us)
        # what the device integrates: whole CLK periods
        clocks = round(us * self.clock_hz / 1e6)
        self._integration_us = int(round(clocks * 1e6 / self.clock_hz))

    @property
    def integration_time_us_limits(self) -> tuple[int, int]:
        return self._limits

    @property
    def saturation_counts(self) -> float:
        return ADC_FULL_SCALE

    @property
    def dark_pixels(self) -> tuple[int, ...]:
        return ()

    def intensities(self) -> np.ndarray:
        """One capture: `frames` frames averaged by the firmware, counts (dark not subtracted)."""
        return self._capture("capture", regs.SpectroFile.LIGHT)

    def dark(self) -> np.ndarray:
        """A capture with every shutter closed by the firmware (they stay closed), counts."""
        return self._capture("capture_dark", regs.SpectroFile.DARK)

    def close(self) -> None:
        if self._owns_device:
            self.device.close()

    # ------------------------------------------------------------------------------------ capture
    def frame_s(self) -> float:
        clocks = self._integration_us * self.clock_hz / 1e6 - INTEGRATION_EXTRA_CLOCKS + FRAME_OVERHEAD_CLOCKS
        return clocks / self.clock_hz

    def _capture(self, command: str, file: int) -> np.ndarray:
        d = self.device
        t0 = time.monotonic()
        d.write("spectro_command", regs.SpectroCommand[command.upper()])
        deadline = t0 + self._frames * self.frame_s() + CAPTURE_MARGIN_S + (2.0 if command == "capture_dark" else 0)
        while True:
            status = regs.SpectroStatus(d.read("spectro_status"))
            if status != regs.SpectroStatus.BUSY:
                break
            if time.monotonic() > deadline:
                d.write("spectro_command", regs.SpectroCommand.ABORT)
                raise DeviceError(f"the micro-spectrometer's capture did not end within {deadline - t0:.1f} s")
            time.sleep(POLL_S)
        if status == regs.SpectroStatus.ERROR_NO_EOS:
            raise DeviceError("the micro-spectrometer's frame ended without EOS (wiring, CLK or a dead chip)")
        if status not in (regs.SpectroStatus.DONE, regs.SpectroStatus.SATURATED):
            raise DeviceError(f"the micro-spectrometer's capture ended {status.name.lower()}")
        words = np.empty(C12880_PIXELS, dtype=np.float64)
        first = 0
        while first < C12880_PIXELS:
            n = min(RECORDS_PER_READ, record_words(d.transport), C12880_PIXELS - first)
            data = d.transport.read_file_records(int(file), first, n)
            words[first:first + n] = np.frombuffer(data, dtype=">u2")
            first += n
        counts = words / RECORD_SCALE
        if self._linearity:
            over = np.maximum(counts - LINEARITY_KNEE_COUNTS, 0.0)
            counts = counts + self._linearity * over * over
        if status == regs.SpectroStatus.SATURATED:
            counts[int(np.argmax(counts))] = ADC_FULL_SCALE
        self.last_capture_s = time.monotonic() - t0
        return counts
