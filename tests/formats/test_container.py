"""The map file: round trip, and a truncated / tampered / wrong-version file is refused whole."""

import struct

import numpy as np
import pytest

from trimeter.errors import MapFileError
from trimeter.formats.appearance import AppearanceMap
from trimeter.formats.container import write_container


def small_map() -> AppearanceMap:
    rng = np.random.default_rng(0)
    shape = (3, 4, 2)
    arrays = {name: rng.uniform(0, 0.5, shape) for name in ("A", "B", "C", "std_b", "std_w")}
    return AppearanceMap(recipe={"name": "t", "geometry": "ideal", "n": 1.5, "thickness_mm": 0.5},
                         alpha=np.array([0.0, 0.5, 0.9]), sigma_t=np.array([0.1, 1.0, 10.0, 50.0]),
                         g=np.array([0.0, 0.9]), provenance={"builder": "test"}, **arrays)


def test_round_trip_is_exact_to_float32(tmp_path):
    amap = small_map()
    path = tmp_path / "m.tmap"
    checksum = amap.save(path)
    back = AppearanceMap.load(path)
    assert back.checksum == checksum
    np.testing.assert_array_equal(back.sigma_t, amap.sigma_t)
    np.testing.assert_allclose(back.A, amap.A, rtol=1e-7)
    assert back.recipe == amap.recipe and back.provenance == amap.provenance


@pytest.mark.parametrize("cut", [1, 31, 32, 100, 5000])
def test_truncated_file_is_refused(tmp_path, cut):
    path = tmp_path / "m.tmap"
    small_map().save(path)
    data = path.read_bytes()
    path.write_bytes(data[: max(0, len(data) - cut)])
    with pytest.raises(MapFileError, match="truncated|checksum"):
        AppearanceMap.load(path)


@pytest.mark.parametrize("where", [0.2, 0.5, 0.9])
def test_tampered_byte_is_refused(tmp_path, where):
    path = tmp_path / "m.tmap"
    small_map().save(path)
    data = bytearray(path.read_bytes())
    data[int(len(data) * where)] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError):
        AppearanceMap.load(path)


def test_wrong_container_version_is_refused(tmp_path):
    path = tmp_path / "m.tmap"
    small_map().save(path)
    data = bytearray(path.read_bytes())
    data[8:12] = struct.pack("<I", 99)
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError, match="container version 99"):
        AppearanceMap.load(path)


def test_wrong_map_format_version_and_wrong_kind_are_refused(tmp_path):
    amap = small_map()
    arrays = {n: getattr(amap, n) for n in ("alpha", "sigma_t", "g", "A", "B", "C", "std_b", "std_w")}
    write_container(tmp_path / "v.tmap", "appearance-map", {"map_format_version": 2, "recipe": amap.recipe}, arrays)
    with pytest.raises(MapFileError, match="map format version 2"):
        AppearanceMap.load(tmp_path / "v.tmap")
    write_container(tmp_path / "k.tmap", "map-table", {}, {"x": np.zeros(3)})
    with pytest.raises(MapFileError, match="expected a 'appearance-map'"):
        AppearanceMap.load(tmp_path / "k.tmap")


def test_not_a_trimeter_file_is_refused(tmp_path):
    path = tmp_path / "x.tmap"
    path.write_bytes(b"hello, this is not a map at all" * 4)
    with pytest.raises(MapFileError, match="bad magic"):
        AppearanceMap.load(path)
