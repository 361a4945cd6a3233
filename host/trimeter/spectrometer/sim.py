"""`sim` backend: the twin's spectrometer over its own serial port (pty), as a line-protocol client.

Protocol (ASCII, one command per line, exactly one reply line `OK[ payload]` or `ERR message`):
`*IDN?`, `DESC?` (one-line JSON description), `WL?` (comma-separated nm), `IT <us>`, `IT?`,
`ACQ` (`<n> <base64 of n little-endian uint16 counts>`), `TIME?`, `BANDS?` (a multichannel sensor's
band weights as one-line JSON; a spectrometer answers ERR). Full table:
host/trimeter/twin/README.md § "Spectrometer line protocol". The server is trimeter.twin.specserver.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Self, TypeVar
import base64
import json
import time

import numpy as np

from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer.base import SpectrometerDescription, check_integration_time

T = TypeVar("T")

if TYPE_CHECKING:
    from trimeter.inversion.bands import BandWeights

# A reply must come within this much wall time plus the exposure itself (at time scale 1).
REPLY_TIMEOUT_S = 5.0


class SimSpectrometer:
    def __init__(self, port: str, timeout_s: float = REPLY_TIMEOUT_S) -> None:
        import serial  # pyserial: a pty opens like any serial port

        if not port:
            raise DeviceError("sim spectrometer needs a port: sim:/dev/pts/N")
        try:  # exclusive (flock), as pymodbus opens the instrument's port: two programs on one port garble both
            self._serial = serial.Serial(port, 115200, timeout=0.05, exclusive=True)
        except (OSError, serial.SerialException) as exc:
            in_use = "exclusively lock" in str(exc)
            raise DeviceError(f"cannot open sim spectrometer at {port}: "
                              f"{'it is in use by another program (serve?)' if in_use else exc}") from None
        self.port = port
        try:
            self._timeout_s = float(timeout_s)
        except ValueError:
            self._serial.close()
            raise InputError(f"spectrometer option timeout_s must be a number, got {timeout_s!r}") from None
        self._buffer = b""
        self._owed = 0  # replies owed by the server to commands that timed out
        self._serial.reset_input_buffer()
        try:
            self._description = self._describe()
            self._wavelengths = np.array([float(x) for x in self._command("WL?").split(",")])
            self._it_us = int(self._command("IT?"))
        except Exception:
            self._serial.close()
            raise
        if len(self._wavelengths) != self._description.pixels:
            self._serial.close()
            raise DeviceError(f"sim spectrometer at {port}: WL? gave {len(self._wavelengths)} values, "
                              f"DESC? says {self._description.pixels} pixels")

    # ------------------------------------------------------------------------------ transport
    def _command(self, line: str, extra_timeout_s: float = 0.0) -> str:
        # The server answers every command exactly once, in order: replies still owed to commands that
        # timed out are skipped, so a late reply is never taken as the answer to this command.
        self._port_io(lambda: self._serial.write(line.encode("ascii") + b"\n"), line)
        deadline = time.monotonic() + self._timeout_s + extra_timeout_s
        while True:
            while b"\n" not in self._buffer:
                if time.monotonic() > deadline:
                    self._owed += 1
                    raise DeviceError(f"sim spectrometer at {self.port}: no reply to {line.split()[0]!r} "
                                      f"within {self._timeout_s + extra_timeout_s:.1f} s")
                self._buffer += self._port_io(lambda: self._serial.read(max(1, self._serial.in_waiting)), line)
            reply, _, self._buffer = self._buffer.partition(b"\n")
            if not self._owed:
                break
            self._owed -= 1
        text = reply.decode("ascii", errors="replace").strip()
        if text.startswith("ERR"):
            raise DeviceError(f"sim spectrometer refused {line.split()[0]!r}: {text[3:].strip()}")
        if not text.startswith("OK"):
            raise DeviceError(f"sim spectrometer at {self.port}: malformed reply {text[:60]!r}")
        return text[2:].strip()

    def _port_io(self, io: Callable[[], T], line: str) -> T:
        """One read or write of the port; a port closed under it (another thread closed the instrument mid-command:
        pyserial then fails with a TypeError or AttributeError as often as with an OSError) is a DeviceError."""
        try:
            return io()
        except (OSError, TypeError, ValueError, AttributeError) as exc:
            raise DeviceError(f"sim spectrometer at {self.port}: the port failed during {line.split()[0]!r} "
                              f"({type(exc).__name__}: it was closed or lost)") from None

    def _describe(self) -> SpectrometerDescription:
        try:
            d = json.loads(self._command("DESC?"))
            first_nm, last_nm = d["wavelength_range_nm"]  # exactly two each, or a bad reply
            shortest_us, longest_us = d["integration_time_us_limits"]
            return SpectrometerDescription(
                model=str(d["model"]), serial=str(d["serial"]), pixels=int(d["pixels"]),
                wavelength_range_nm=(float(first_nm), float(last_nm)),
                integration_time_us_limits=(int(shortest_us), int(longest_us)),
                saturation_counts=float(d["saturation_counts"]),
                dark_pixels=tuple(int(i) for i in d["dark_pixels"]), extra=dict(d.get("extra") or {}))
        except (ValueError, KeyError, TypeError) as exc:
            raise DeviceError(f"sim spectrometer at {self.port}: bad DESC? reply ({exc})") from None

    # ------------------------------------------------------------------------------- protocol
    @property
    def description(self) -> SpectrometerDescription:
        return self._description

    def wavelengths_nm(self) -> np.ndarray:
        return self._wavelengths.copy()

    def band_weights(self) -> BandWeights | None:
        """A multichannel sensor's band weights (what each channel reads a weighted mean of), None for
        a spectrometer."""
        from trimeter.inversion.bands import band_weights

        if not self._description.extra.get("channels"):
            return None
        try:
            d = json.loads(self._command("BANDS?"))
            return band_weights(d["wavelength_nm"], d["channels"], d["diffuse"], d["collimated"],
                                where=f"sim spectrometer at {self.port}: BANDS?")
        except (ValueError, KeyError, TypeError) as exc:
            raise DeviceError(f"sim spectrometer at {self.port}: bad BANDS? reply ({exc})") from None

    @property
    def integration_time_us(self) -> int:
        return self._it_us

    @integration_time_us.setter
    def integration_time_us(self, value: Any) -> None:
        us = check_integration_time(value, self.integration_time_us_limits)
        self._command(f"IT {us}")
        self._it_us = int(self._command("IT?"))

    @property
    def integration_time_us_limits(self) -> tuple[int, int]:
        return self._description.integration_time_us_limits

    @property
    def saturation_counts(self) -> float:
        return self._description.saturation_counts

    @property
    def dark_pixels(self) -> tuple[int, ...]:
        return self._description.dark_pixels

    def intensities(self) -> np.ndarray:
        payload = self._command("ACQ", extra_timeout_s=self._it_us * 1e-6)
        try:
            n_text, data = payload.split(" ", 1)
            counts = np.frombuffer(base64.b64decode(data, validate=True), dtype="<u2")
        except (ValueError, TypeError) as exc:
            raise DeviceError(f"sim spectrometer at {self.port}: malformed ACQ payload ({exc})") from None
        if len(counts) != int(n_text) or len(counts) != self._description.pixels:
            raise DeviceError(f"sim spectrometer at {self.port}: ACQ gave {len(counts)} counts, expected "
                              f"{self._description.pixels}")
        return counts.astype(np.float64)

    def sim_time_s(self) -> float:
        """Simulated seconds at the end of the last exposure (twin only: tells exposure from overhead)."""
        return float(self._command("TIME?"))

    def close(self) -> None:
        self._serial.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
