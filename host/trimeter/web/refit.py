"""Re-fitting a stored measurement with another map or method: a new results directory, the original untouched.

The capture is read back from the original's files (calibration, raw spectra, reflectances), fitted
again and written by the results writer like any measurement, so the new record is complete and
atomic; its measurement.json names the record it came from (`refit_of`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from trimeter.domain import Measurement, Provenance, Sample, SampleCapture
from trimeter.domain.measurement import MapRef
from trimeter.errors import InputError, MapFileError, OutputError, TrimeterError
from trimeter.inversion.flags import advice
from trimeter.formats.appearance import AppearanceMap
from trimeter.device.table_cache import SHA256_HEX, cache_dir
from trimeter.formats.device_table import DeviceTable, SUFFIX
from trimeter.results.reader import load
from trimeter.results.writer import write_measurement
from trimeter.sequences.measure import for_recorded_sensor, prepare_fit

# A `paper` re-fit triangulates the map's nodes once per distinct background pair before placing any bin; above
# this many nodes triangulated it is refused up front rather than run into the re-fit's time limit.
PAPER_MAX_TRIANGULATED_NODES = 2_000_000


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


def paper_refit_problem(directory: Path, maps: Sequence[MapRef]) -> str | None:
    """Why a `paper` re-fit of `directory` with `maps` is too large to run (None: it is not)."""
    from trimeter.inversion.paper import triangulated_nodes

    refls = load(directory).reflectances
    if len(maps) != len(refls):
        return None  # refit() says what is wrong
    work = sum(triangulated_nodes(amap, refl.rho_b, refl.rho_w)
               for amap, refl in zip(maps, refls, strict=True) if isinstance(amap, AppearanceMap))
    if work <= PAPER_MAX_TRIANGULATED_NODES:
        return None
    return (f"a paper re-fit of this record would triangulate {work:,} map nodes (one Delaunay triangulation of "
            f"the map per distinct background pair; the limit is {PAPER_MAX_TRIANGULATED_NODES:,}): re-fit with "
            f"another method, or a smaller map")


def refit(directory: Path, maps: Sequence[MapRef], method: str) -> Path:
    """Fit `directory`'s capture again with `maps` (appearance maps or instrument tables, one per thickness)
    and `method`; write a new results directory beside it and return its path."""
    stored = load(directory)
    calibration, raws, refls, meta = stored.calibration, stored.raw, stored.reflectances, stored.record
    declared = meta.get("declared_thicknesses_mm") or stored.thicknesses_mm
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
