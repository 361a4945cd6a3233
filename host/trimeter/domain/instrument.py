"""The instrument a capture or calibration was taken on."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class InstrumentInfo:
    """Identity of the instrument: vendor and model (None where a record did not keep them), firmware
    version and register-map hash."""

    firmware: tuple[int, ...]
    regmap_hash: int
    vendor_id: int | None = None
    model_id: int | None = None

    @classmethod
    def of(cls, identity: Any) -> InstrumentInfo:
        """From a device's identity (trimeter.device.client.Identity)."""
        return cls(tuple(int(v) for v in identity.firmware_version), int(identity.regmap_hash),
                   int(identity.vendor_id), int(identity.model_id))

    def same_model(self, other: InstrumentInfo) -> bool:
        """False only when both name their vendor/model and those differ."""
        return all(a is None or b is None or a == b for a, b in ((self.vendor_id, other.vendor_id),
                                                                 (self.model_id, other.model_id)))

    def to_json(self, *, with_model: bool = True) -> dict:
        """calibration.json's "device" (with the model), measurement.json's (without)."""
        out: dict[str, Any] = {}
        if with_model:
            out.update({key: value for key, value in (("vendor_id", self.vendor_id), ("model_id", self.model_id))
                        if value is not None})
        out.update(firmware=list(self.firmware), regmap_hash=f"0x{self.regmap_hash:08X}")
        return out

    @classmethod
    def from_json(cls, value: Any) -> InstrumentInfo | None:
        """None when `value` is not an instrument record (empty in a calibration taken without one)."""
        try:
            vendor, model = value.get("vendor_id"), value.get("model_id")
            return cls(tuple(int(v) for v in value["firmware"]), int(str(value["regmap_hash"]), 16),
                       None if vendor is None else int(vendor), None if model is None else int(model))
        except (AttributeError, KeyError, TypeError, ValueError):
            return None
