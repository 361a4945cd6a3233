"""Re-fitting a stored measurement with another map or method: a new results directory, the original untouched.

The capture is read back from the original's files (calibration, raw spectra, reflectances), fitted
again and written by the results writer like any measurement, so the new record is complete and
atomic; its measurement.json names the record it came from (`refit_of`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from trimeter.domain import (Calibration, Capture, Measurement, Provenance, RawSample, Reflectances, Sample,
                             SampleCapture)
from trimeter.domain.measurement import MapRef
from trimeter.errors import InputError, MapFileError, OutputError, TrimeterError
from trimeter.inversion.flags import advice
from trimeter.maps.appearance import AppearanceMap
from trimeter.maps.device_table import SHA256_HEX, SUFFIX, DeviceTable, cache_dir
from trimeter.results.writer import file_tags, write_measurement
from trimeter.sequences.measure import for_recorded_sensor, prepare_fit

SETUPS = ("black", "white", "collimated")


def read_columns(path: Path) -> dict[str, np.ndarray]:
    """A results CSV (one header line of names, then numbers) as columns."""
    try:
        with open(path) as f:
            names = f.readline().strip().split(",")
            table = np.loadtxt(f, delimiter=",", ndmin=2)
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path.name}: cannot be read back ({exc})") from None
    if table.shape[1] != len(names):
        raise InputError(f"{path.name}: {table.shape[1]} columns for {len(names)} names")
    return {name: table[:, i] for i, name in enumerate(names)}


def _capture(columns: dict) -> Capture:
    times = [int(n[len("signal_"):-2]) for n in columns if n.startswith("signal_") and n.endswith("us")]
    rate = columns["rate_counts_per_s"]
    return Capture(rate=rate, saturated=np.zeros(rate.shape, bool), integration_times_us=np.asarray(times, float),
                   signals=np.stack([columns[f"signal_{t}us"] for t in times]),
                   darks=np.stack([columns[f"dark_{t}us"] for t in times]))


def _reflectances(columns: dict) -> Reflectances:
    return Reflectances(columns["wavelength_nm"], columns["I_b"], columns["I_w"], columns["I_c"], columns["rho_b"],
                        columns["rho_w"], columns["capture_flags"].astype(np.int32),
                        *(columns.get(name) for name in ("I_b_std", "I_w_std", "I_c_std")))


def load_capture(directory: Path) -> tuple[Calibration, list[RawSample], list[Reflectances], dict]:
    """(calibration, raw samples, reflectances, measurement.json) of a results directory."""
    try:
        meta = json.loads((directory / "measurement.json").read_text())
        thicknesses = [float(t) for t in meta["thicknesses_mm"]]
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise InputError(f"{directory.name}: its measurement.json cannot be read ({exc})") from None
    calibration = Calibration.load(directory)
    raws, refls = [], []
    try:
        for tag in file_tags(thicknesses):
            captures = {s: _capture(read_columns(directory / f"raw_{s}{tag}.csv")) for s in SETUPS}
            refl = _reflectances(read_columns(directory / f"reflectances{tag}.csv"))
            raws.append(RawSample(refl.wavelengths_nm, black=captures["black"], white=captures["white"],
                                  collimated=captures["collimated"]))
            refls.append(refl)
    except KeyError as exc:
        raise InputError(f"{directory.name}: a capture file lacks the column {exc}") from None
    return calibration, raws, refls, meta


def cached_table(sha256: str) -> DeviceTable | None:
    """The instrument table with this SHA-256 from the host's table cache, or None (not there, or damaged)."""
    if not SHA256_HEX.fullmatch(sha256):  # a record's text never becomes a path
        return None
    path = cache_dir() / f"{sha256}{SUFFIX}"
    try:
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != sha256:
            return None
        return DeviceTable.from_bytes(data, source=str(path))
    except (OSError, MapFileError):
        return None


def recorded_maps(meta: dict, catalog: dict[str, Path], instrument_table: Callable[[], DeviceTable]
                  ) -> list[MapRef]:
    """The maps or tables a measurement was fitted with, by the identity its measurement.json records
    (`maps` and `map_checksums`): an instrument's table from the host cache or, failing that, from the
    instrument if it still carries it; a map of the catalog whose checksum is the recorded one. A record
    without checksums is matched by map name alone. InputError when one is nowhere here."""
    names = meta.get("maps")
    checksums = meta.get("map_checksums")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise InputError("the measurement.json names no maps; name one to re-fit with (GET /api/maps)")
    if not isinstance(checksums, list) or len(checksums) != len(names):
        checksums = [None] * len(names)
    device: DeviceTable | None = None
    found: list[MapRef] = []
    for name, checksum in zip(names, checksums, strict=True):
        if not isinstance(checksum, str) or not checksum:  # an older record: the map of that name
            if name not in catalog:
                raise InputError(f"the measurement's map {name!r} is not known here; name one (GET /api/maps)")
            found.append(AppearanceMap.load(catalog[name]))
            continue
        table = cached_table(checksum)
        if table is None and name in catalog:
            amap = AppearanceMap.load(catalog[name])
            if amap.checksum == checksum:
                found.append(amap)
                continue
        if table is None:
            if device is None:
                try:
                    device = instrument_table()
                except TrimeterError:
                    device = None
            if device is not None and device.sha256 == checksum:
                table = device
        if table is None:
            raise InputError(f"the measurement was fitted with {name} (checksum {checksum[:12]}…), which is neither "
                             f"in this host's table cache, nor the instrument's active table, nor a map here; name a "
                             f"map to re-fit with (GET /api/maps)")
        found.append(table)
    return found


def refit(directory: Path, maps: Sequence[MapRef], method: str) -> Path:
    """Fit `directory`'s capture again with `maps` (appearance maps or instrument tables, one per thickness)
    and `method`; write a new results directory beside it and return its path."""
    calibration, raws, refls, meta = load_capture(directory)
    declared = meta.get("declared_thicknesses_mm") or meta["thicknesses_mm"]
    if len(maps) != len(refls) or len(declared) != len(refls):
        raise InputError(f"{len(maps)} map(s) for {len(refls)} measured thickness(es)")
    prepared = for_recorded_sensor(prepare_fit([Sample(float(t), amap) for t, amap in zip(declared, maps, strict=True)],
                                               method), calibration.spectrometer)
    captures = [SampleCapture(sample, raw, refl) for sample, raw, refl in zip(prepared.samples, raws, refls,
                                                                               strict=True)]
    combined, per = prepared.fit(captures)
    original = Provenance.from_record(meta)
    provenance = replace(original, method=method, timing=None, link=None, refit_of=directory.name,
                         advice=advice(combined.flags, len(maps)))
    try:
        return write_measurement(directory.parent, Measurement(calibration, captures, combined, per, provenance),
                                 label=original.label or None)
    except OSError as exc:
        raise OutputError(f"the re-fit could not be written to {directory.parent} ({exc})") from None
