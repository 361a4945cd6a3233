"""GET /api/maps: besides the maps a refit may name, the tables read from instruments into this host's cache
(trimeter.device.table_cache.cached_tables), described from their headers alone; a cache file that is no
readable table is listed with a note saying why, and the listing never fails over it."""

from __future__ import annotations

import hashlib
import struct
from dataclasses import replace

import pytest

from conftest import idle_web
from hil_support import HIL_MAP
from trimeter.errors import MapFileError
from trimeter.device.table_cache import cached_tables
from trimeter.formats.device_table import DeviceTable, HEADER_SIZE, SECTIONS, read_header

GEOMETRY_ENTRY = HEADER_SIZE - 12 - 8  # the directory's last (offset, length) pair, before the reserved bytes


@pytest.fixture(scope="module")
def table():
    """The HIL map's table (an ideal map's carries no geometry: given one here, as a device map's would)."""
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.table_builder import build_from_map

    built = build_from_map(AppearanceMap.load(HIL_MAP))
    geometry = {"description": "a test's", "detector": {"distance_mm": 150.0}, "cover_slides": True}
    return DeviceTable.from_bytes(replace(built, geometry=geometry).to_bytes())


def _cache_file(directory, data: bytes, name: str | None = None) -> str:
    file = f"{name or hashlib.sha256(data).hexdigest()}.tlut"
    (directory / file).write_bytes(data)
    return file


@pytest.fixture(scope="module")
def cache(tmp_path_factory, table):
    """The cache directory with one good table and, by file name, what each broken one should be noted for."""
    root = tmp_path_factory.mktemp("cache")
    directory = root / "device-tables"
    directory.mkdir()
    data = table.to_bytes()
    geometry_at = struct.unpack_from("<I", data, GEOMETRY_ENTRY)[0]
    retired = bytearray(data)
    struct.pack_into("<H", retired, 8, 1)
    bad_geometry = bytearray(data)
    bad_geometry[geometry_at] = 0xFF
    broken = {
        _cache_file(directory, data[:-100]): "total_size",
        _cache_file(directory, b"not a table " * 40): "not a trimeter map table",
        _cache_file(directory, bytes(retired)): "format 1 is retired",
        _cache_file(directory, bytes(bad_geometry)): "geometry: not UTF-8 JSON",
        _cache_file(directory, data, name="renamed"): "not named by a SHA-256",
        _cache_file(directory, b""): "total_size",
    }
    (directory / "notes.txt").write_text("not a table file: not listed")
    return root, _cache_file(directory, data), broken


@pytest.fixture(scope="module")
def web(tmp_path_factory, cache):
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TRIMETER_CACHE_DIR", str(cache[0]))
        with idle_web(tmp_path_factory.mktemp("maps-listing")) as instrument:
            yield instrument


def test_the_listing_names_each_cached_table_from_its_header(web, cache, table):
    _, good, broken = cache
    answer = web.call("GET", "/api/maps")
    assert answer.status == 200, answer.body
    listing = answer.json
    assert set(listing) == {"maps", "methods", "instrument_tables"}
    entries = {entry["file"]: entry for entry in listing["instrument_tables"]}
    assert set(entries) == {good, *broken}  # notes.txt is no cache entry
    assert entries[good] == {
        "file": good, "sha256": table.sha256, "source": "instrument cache", "name": table.name,
        "parent_map_sha256": table.parent_sha256, "n": table.n, "thickness_mm": table.thickness_mm,
        "cover_slide_n": table.cover_slide_n, "geometry": table.geometry, "size_bytes": table.size_bytes}
    assert table.name and len(table.parent_sha256) == 64 and table.geometry  # a real identity, not blanks


def test_a_corrupt_cache_file_is_listed_with_a_note_not_a_failure(web, cache):
    _, _, broken = cache
    entries = {entry["file"]: entry for entry in web.call("GET", "/api/maps").json["instrument_tables"]}
    for file, why in broken.items():
        entry = entries[file]
        assert entry["source"] == "instrument cache" and entry["note"].startswith("skipped: "), entry
        assert why in entry["note"], (file, entry["note"])
        assert "name" not in entry and "parent_map_sha256" not in entry  # nothing read from a bad header


def test_the_header_alone_gives_what_the_whole_table_gives(tmp_path, table):
    path = table.save(tmp_path / "t.tlut")
    loaded = DeviceTable.load(path)
    assert read_header(path) == {"name": loaded.name, "parent_map_sha256": loaded.parent_sha256, "n": loaded.n,
                                 "thickness_mm": loaded.thickness_mm, "cover_slide_n": loaded.cover_slide_n,
                                 "geometry": loaded.geometry, "size_bytes": loaded.size_bytes}
    # headers only: a damaged array (the CRC-32 then fails) does not change what the listing says
    data = bytearray(path.read_bytes())
    data[HEADER_SIZE + 1] ^= 0xFF
    path.write_bytes(bytes(data))
    assert read_header(path)["name"] == table.name
    with pytest.raises(MapFileError, match="crc32"):
        DeviceTable.load(path)


def test_no_cache_directory_is_an_empty_listing(tmp_path):
    assert cached_tables(tmp_path / "nothing-here") == []
    assert SECTIONS[-1] == "geometry"  # GEOMETRY_ENTRY above reads the last section's directory entry
