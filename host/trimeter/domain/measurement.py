"""A measurement: the samples it was built from ((thickness, map) pairs), what each capture gave, the
fitted parameters, and typed provenance.

measurement.json is `Measurement.record()` plus the writer's own keys; `Provenance.from_record` reads
any measurement.json back, old ones included (missing keys take their defaults, unknown keys are kept
and written again).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.calibration import Calibration
from trimeter.domain.capture import RawSample
from trimeter.domain.instrument import InstrumentInfo
from trimeter.domain.reflectances import Reflectances
from trimeter.errors import InputError


class BackgroundCoefficients(Protocol):
    """A map's background response I(ρ) = A + Bρ/(1 − Cρ), per material: the shot checks' floor."""

    @property
    def A(self) -> np.ndarray: ...
    @property
    def B(self) -> np.ndarray: ...
    @property
    def C(self) -> np.ndarray: ...


class MapRef(BackgroundCoefficients, Protocol):
    """What a measurement needs to know of an appearance map (trimeter.formats.appearance.AppearanceMap is one)."""

    @property
    def name(self) -> str: ...

    @property
    def thickness_mm(self) -> float: ...

    @property
    def checksum(self) -> str: ...


class SpectralColumns(Protocol):
    """What a material is read from: a fit's parameters, their columns from a file, or a material."""

    @property
    def wavelengths_nm(self) -> ArrayLike: ...
    @property
    def alpha(self) -> ArrayLike: ...
    @property
    def sigma_t(self) -> ArrayLike: ...
    @property
    def g(self) -> ArrayLike: ...


class Estimate(SpectralColumns, Protocol):
    """What a measurement needs of fitted parameters (trimeter.results.Parameters is one): read-only, as
    a frozen result is."""

    @property
    def wavelengths_nm(self) -> np.ndarray: ...
    @property
    def thickness_mm(self) -> float | None: ...
    @property
    def alpha(self) -> np.ndarray: ...
    @property
    def sigma_t(self) -> np.ndarray: ...
    @property
    def g(self) -> np.ndarray: ...
    @property
    def sigma_t_beer(self) -> np.ndarray: ...

    def columns(self) -> dict: ...

    def to_json(self) -> dict: ...


# A map of another ℓ than its sample's scales σt by their ratio: the two must agree to rounding.
THICKNESS_TOLERANCE = 1e-6


def thickness_matches(of_map_mm: float, declared_mm: ArrayLike) -> np.ndarray:
    """Whether a declared thickness (or each of an array of them) is a map's ℓ, to rounding (relative to ℓ,
    absolute below 1 mm). The one thickness match: trimeter.model.sample_setup.SampleSetup.matches_thickness."""
    return np.asarray(np.abs(np.asarray(declared_mm, dtype=float) - of_map_mm)
                      <= THICKNESS_TOLERANCE * max(1.0, of_map_mm))


@dataclass(frozen=True)
class MapIdentity:
    """A map as a measurement records it: enough to find it again and to tell it was not changed."""

    name: str
    thickness_mm: float
    checksum: str

    @classmethod
    def of(cls, amap: MapRef) -> MapIdentity:
        return cls(str(amap.name), float(amap.thickness_mm), str(amap.checksum))


@dataclass(frozen=True, eq=False)   # a map holds arrays: samples are told apart by identity
class Sample:
    """One sample of a measurement: its declared thickness and the map it is fitted with."""

    thickness_mm: float
    map: MapRef

    def __post_init__(self) -> None:
        try:
            thickness = float(self.thickness_mm)
        except (TypeError, ValueError):
            thickness = math.nan
        if not (thickness > 0 and math.isfinite(thickness)):
            raise InputError(f"thickness: {self.thickness_mm!r} mm is not a positive thickness")
        object.__setattr__(self, "thickness_mm", thickness)

    def check_map(self) -> None:
        """InputError unless the map is for this sample's thickness."""
        if not thickness_matches(self.map.thickness_mm, self.thickness_mm):
            raise InputError(f"map {self.map.name} is for ℓ = {self.map.thickness_mm:g} mm, not the declared "
                             f"{self.thickness_mm:g} mm")


@dataclass(frozen=True)
class DeviceTableCheck:
    """Is the map table active in the device the table this host fits with (trimeter.sequences.service)?"""

    slot: str | None                 # the active slot's name; None: no table active
    matches_fit_table: bool
    crc32: str | None = None         # the slot's, as "0x…"
    length: int | None = None
    version: int | None = None
    map: str | None = None           # the map it was compared with (only when a comparison was made)

    def to_json(self) -> dict:
        out: dict[str, Any] = {"slot": self.slot}
        if self.slot is not None:
            out.update(crc32=self.crc32, length=self.length, version=self.version)
        out["matches_fit_table"] = self.matches_fit_table
        if self.map is not None:
            out["map"] = self.map
        return out

    @classmethod
    def from_json(cls, value: Any) -> DeviceTableCheck | None:
        if not isinstance(value, dict) or "matches_fit_table" not in value:
            return None
        return cls(value.get("slot"), bool(value["matches_fit_table"]), value.get("crc32"), value.get("length"),
                   value.get("version"), value.get("map"))


# measurement.json keys the writer or Measurement.record() derive; a record read back drops them.
DERIVED_KEYS = ("maps", "declared_thicknesses_mm", "map_thicknesses_mm", "map_checksums", "calibration_created_utc",
                "written_utc", "thicknesses_mm", "figure", "medium")


@dataclass
class Provenance:
    """How a measurement came about, beyond its samples and calibration. `timing` and `link` are None when
    not measured (a re-fit); unknown keys of a record read back stay in `extra`."""

    method: str = ""
    label: str | None = None
    sample_name: str | None = None                       # "sample": what was measured, when named
    timing: dict[str, float] | None = None               # trimeter.sequences.steps.Timing.to_dict() + fit/write
    instrument: InstrumentInfo | None = None
    device_map_table: DeviceTableCheck | None = None
    noise_rel_measured: list[float | None] = field(default_factory=list)
    incomplete: str | None = None                        # why fewer samples were measured than asked
    advice: list[str] = field(default_factory=list)
    link: dict[str, float] | None = None                 # the device link's counters (transport stats)
    refit_of: str | None = None                          # the results directory this one was re-fitted from
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_record(cls, record: dict) -> Provenance:
        """From a measurement.json (any version); InputError when it is not an object."""
        if not isinstance(record, dict):
            raise InputError("measurement.json does not hold an object")
        known = {"method", "label", "sample", "timing", "device", "device_map_table", "noise_rel_measured",
                 "incomplete", "advice", "link", "refit_of"}
        advice = record.get("advice")
        noise = record.get("noise_rel_measured")
        return cls(method=str(record.get("method") or ""), label=record.get("label"),
                   sample_name=record.get("sample"), timing=record.get("timing"),
                   instrument=InstrumentInfo.from_json(record.get("device")),
                   device_map_table=DeviceTableCheck.from_json(record.get("device_map_table")),
                   noise_rel_measured=list(noise) if isinstance(noise, list) else [],
                   incomplete=record.get("incomplete"),
                   advice=[str(a) for a in advice] if isinstance(advice, list) else [],
                   link=record.get("link"), refit_of=record.get("refit_of"),
                   extra={k: v for k, v in record.items() if k not in known and k not in DERIVED_KEYS})


@dataclass
class SampleCapture:
    """One sample and what its capture gave."""

    sample: Sample
    raw: RawSample
    reflectances: Reflectances


@dataclass
class Measurement:
    """Everything one completed measurement produced; trimeter.results.write_measurement stores it."""

    calibration: Calibration
    captures: list[SampleCapture]
    parameters: Estimate                          # the (combined) estimate
    per_thickness: Sequence[Estimate] = field(default_factory=list)   # one per sample when there are several
    provenance: Provenance = field(default_factory=Provenance)

    @property
    def samples(self) -> list[Sample]:
        return [c.sample for c in self.captures]

    @property
    def thicknesses_mm(self) -> list[float]:
        return [c.sample.thickness_mm for c in self.captures]

    def record(self) -> dict:
        """measurement.json's content except the writer's own keys (written time, files)."""
        p = self.provenance
        maps = [MapIdentity.of(s.map) for s in self.samples]
        out: dict[str, Any] = {}
        if p.sample_name is not None:
            out["sample"] = p.sample_name
        out.update({"label": p.label, "method": p.method, "maps": [m.name for m in maps],
                    "declared_thicknesses_mm": self.thicknesses_mm,
                    "map_thicknesses_mm": [m.thickness_mm for m in maps],
                    "map_checksums": [m.checksum for m in maps]})
        if p.timing is not None:
            out["timing"] = p.timing
        out.update({"device": None if p.instrument is None else p.instrument.to_json(with_model=False),
                    "calibration_created_utc": self.calibration.created_utc,
                    "device_map_table": None if p.device_map_table is None else p.device_map_table.to_json(),
                    "noise_rel_measured": list(p.noise_rel_measured), "incomplete": p.incomplete})
        if p.refit_of is not None:
            out["refit_of"] = p.refit_of
        out["advice"] = list(p.advice)
        if p.link is not None:
            out["link"] = p.link
        out.update(p.extra)
        return out
