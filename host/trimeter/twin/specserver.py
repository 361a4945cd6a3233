"""The twin's spectrometer: a line-protocol server on its own pty (protocol: README.md of this package).

The light itself comes from an injected `expose(integration_time_us) -> (counts uint16, sim_time_end_s)`
callable, so the server is testable without the firmware or the optics.
"""

from __future__ import annotations

import base64
import json
import os
import select
import threading
from typing import Callable

import numpy as np

from trimeter import __version__
from trimeter.inversion.bands import BandWeights
from trimeter.twin._pty import open_raw_pty, read_some, write_all

MAX_LINE = 256


class SpectrometerServer:
    def __init__(self, description: dict, wavelengths_nm: np.ndarray,
                 expose: Callable[[int], tuple[np.ndarray, float]], integration_time_us: int = 100_000,
                 bands: BandWeights | None = None) -> None:
        """bands: a multichannel sensor's band weights, for `BANDS?` (None: a spectrometer, which has none)."""
        self.description = description
        self._bands = None if bands is None else json.dumps(
            {"wavelength_nm": bands.wavelength_nm.tolist(), "channels": list(bands.channels),
             **dict(zip(("diffuse", "collimated"), (d.tolist() for d in bands.densities()), strict=True))},
            separators=(",", ":"))
        self._wavelengths = ",".join(f"{x:.4f}" for x in wavelengths_nm)
        self._expose = expose
        self.integration_time_us = int(integration_time_us)
        self.last_time_s = 0.0
        self.acquisitions = 0
        self._master, self._slave, self.port = open_raw_pty()
        self._wake_r, wake_w = os.pipe()
        self._wake_w: int | None = wake_w  # None once closed
        self._thread = threading.Thread(target=self._serve, name="twin-spectrometer", daemon=True)
        self._thread.start()

    def handle(self, line: str) -> str:
        """One command line → one reply line (without the newline). Never raises for bad input."""
        parts = line.strip().split()
        if not parts:
            return "ERR empty command"
        cmd, args = parts[0].upper(), parts[1:]
        try:
            if cmd == "*IDN?" and not args:
                return f"OK trimeter-twin-spectrometer,{self.description['serial']},{__version__}"
            if cmd == "DESC?" and not args:
                return "OK " + json.dumps(self.description, separators=(",", ":"))
            if cmd == "WL?" and not args:
                return "OK " + self._wavelengths
            if cmd == "BANDS?" and not args:
                return "ERR no band weights: this is a spectrometer" if self._bands is None else "OK " + self._bands
            if cmd == "IT?" and not args:
                return f"OK {self.integration_time_us}"
            if cmd == "TIME?" and not args:
                return f"OK {self.last_time_s:.6f}"
            if cmd == "IT" and len(args) == 1:
                lo, hi = self.description["integration_time_us_limits"]
                if not args[0].isdigit() or not lo <= int(args[0]) <= hi:
                    return f"ERR IT must be an integer within {lo}..{hi} us, got {args[0][:20]!r}"
                self.integration_time_us = int(args[0])
                return "OK"
            if cmd == "ACQ" and not args:
                counts, self.last_time_s = self._expose(self.integration_time_us)
                self.acquisitions += 1
                data = np.asarray(counts, dtype="<u2").tobytes()
                return f"OK {len(counts)} " + base64.b64encode(data).decode("ascii")
        except Exception as exc:  # the optics failing must not kill the server: report it on the wire
            return f"ERR {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"[:200]
        return f"ERR unknown command or wrong arguments: {line.strip()[:40]!r}"

    def _serve(self) -> None:
        buffer, discarding = b"", False
        while True:
            ready, _, _ = select.select([self._master, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            data = read_some(self._master)
            if data is None:
                return
            buffer += data
            while b"\n" in buffer:
                raw, _, buffer = buffer.partition(b"\n")
                if discarding:  # the tail of an over-long line, already answered
                    discarding = False
                    continue
                reply = "ERR line too long" if len(raw) > MAX_LINE else self.handle(raw.decode("ascii", "replace"))
                write_all(self._master, reply.encode("ascii", "backslashreplace") + b"\n")
            if len(buffer) > MAX_LINE and not discarding:  # garbage without a newline: answer once, skip to "\n"
                buffer, discarding = b"", True
                write_all(self._master, b"ERR line too long\n")
            elif discarding:
                buffer = b""

    def close(self) -> None:
        if self._wake_w is None:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            os.close(fd)
        self._wake_w = None
