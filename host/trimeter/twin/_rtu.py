"""A minimal Modbus RTU master over a pty, below the device client: for the twin's own tests and benchmark.

(The host's real client is trimeter.device over pymodbus; this exists so the twin is measured and tested
without it.)
"""

from __future__ import annotations

import os
import struct
import time
import tty
from trimeter.crc import crc16_modbus_bytes as crc16


class RtuMaster:
    def __init__(self, port: str, address: int = 1, timeout_s: float = 1.0, gap_s: float = 0.005) -> None:
        self.address, self.timeout_s, self.gap_s = address, timeout_s, gap_s
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)

    def transact(self, pdu: bytes, reply_len: int) -> bytes | None:
        """Send one request; the reply PDU, or None on timeout / bad CRC / wrong length."""
        frame = bytes([self.address]) + pdu
        os.write(self.fd, frame + crc16(frame))
        data, deadline = b"", time.monotonic() + self.timeout_s
        while len(data) < reply_len + 3 and time.monotonic() < deadline:
            try:
                data += os.read(self.fd, 256)
            except BlockingIOError:
                time.sleep(0.0002)
        if self.gap_s:
            time.sleep(self.gap_s)  # inter-frame silence, so the next request is seen as new
        if len(data) != reply_len + 3 or crc16(data[:-2]) != data[-2:]:
            return None
        return data[1:-2]

    def read_input(self, address: int, count: int) -> list[int] | None:
        reply = self.transact(struct.pack(">BHH", 4, address, count), 2 + 2 * count)
        return list(struct.unpack(f">{count}H", reply[2:])) if reply else None

    def write_coils(self, address: int, values: list[bool]) -> bool:
        bits = sum(int(v) << i for i, v in enumerate(values))
        nbytes = (len(values) + 7) // 8
        pdu = struct.pack(">BHHB", 15, address, len(values), nbytes) + bits.to_bytes(nbytes, "little")
        return self.transact(pdu, 5) is not None

    def close(self) -> None:
        os.close(self.fd)
