"""Client of the firmware sim's plant-control socket (JSON lines; firmware/ports/sim/README.md)."""

from __future__ import annotations

import json
import socket
import threading

from trimeter.errors import DeviceError


class PlantClient:
    def __init__(self, path: str, timeout_s: float = 5.0) -> None:
        self.path = path
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        try:
            self._sock.connect(path)
        except OSError as exc:
            self._sock.close()
            raise DeviceError(f"cannot connect to the firmware plant socket {path}: {exc}") from None
        self._file = self._sock.makefile("rb")
        self._lock = threading.Lock()

    def request(self, **message: object) -> dict:
        """Send one command, return its reply; DeviceError if the plant refuses it or is gone."""
        with self._lock:
            try:
                self._sock.sendall(json.dumps(message).encode() + b"\n")
                line = self._file.readline()
            except OSError as exc:
                raise DeviceError(f"plant socket {self.path}: {exc}") from None
        if not line:
            raise DeviceError(f"plant socket {self.path} closed (firmware sim exited?)")
        try:
            reply = json.loads(line)
        except ValueError:
            raise DeviceError(f"plant socket {self.path}: malformed reply {line[:80]!r}") from None
        if not reply.get("ok"):
            raise DeviceError(f"plant refused {message.get('cmd')!r}: {reply.get('error', 'no reason given')}")
        return reply

    def state(self) -> dict:
        return self.request(cmd="state")

    def close(self) -> None:
        try:
            self._file.close()
        finally:
            self._sock.close()
