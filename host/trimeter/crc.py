"""CRC-16/MODBUS for the Python side's own raw-frame code (the twin's minimal RTU master, test
fixtures, the fuzz-corpus generator). The device client itself goes through pymodbus."""

from __future__ import annotations

import struct


def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def crc16_modbus_bytes(data: bytes) -> bytes:
    """The CRC as it goes on the wire: low byte first."""
    return struct.pack("<H", crc16_modbus(data))
