"""The instrument over Modbus RTU: `transport` (the one pymodbus adapter) and `client` (the typed API)."""

from trimeter.device.client import Device, Identity

__all__ = ["Device", "Identity"]
