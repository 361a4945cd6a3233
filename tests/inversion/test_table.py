"""The map table format: exact round trip, size budget, refusal of every kind of damage."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trimeter.errors import MapFileError
from trimeter.maps.table import (HEADER_SIZE, MAX_TABLE_BYTES, TABLE_MAGIC, MapTable, build_from_map,
                                      describe_table, table_path_for)


@pytest.fixture(scope="module")
def table(ideal_map):
    return build_from_map(ideal_map)


def test_round_trip_is_byte_exact_and_fits_a_slot(table, ideal_map):
    data = table.to_bytes()
    assert len(data) == table.size_bytes <= MAX_TABLE_BYTES
    again = MapTable.from_bytes(data)
    assert again.to_bytes() == data
    assert again.source_checksum == ideal_map.checksum
    assert again.name == ideal_map.name
    # the refined grid passes through the map's own nodes (every other σt node)
    np.testing.assert_allclose(again.coefficients_grid[:, ::2, :, 0], ideal_map.A, atol=2e-5)
    np.testing.assert_allclose(again.coefficients_grid[:, ::2, :, 2], ideal_map.C, atol=2e-5)
    np.testing.assert_allclose(again.sigma_t[::2], ideal_map.sigma_t, rtol=1e-6)


def test_committed_table_matches_its_map(ideal_map):
    from trimeter.maps.device_table import DeviceTable

    table = DeviceTable.load(table_path_for(ideal_map.path))
    assert table.parent_sha256 == ideal_map.checksum


def test_describe_table(table, tmp_path):
    info = describe_table(table.to_bytes())
    assert info["kind"] == "map-table" and info["size_bytes"] == len(table.to_bytes())
    assert info["forward_grid"] == {"alpha": 25, "sigma_t": 47, "g": 13}  # σt refined 2× (exact map)
    assert info["crc32"] == f"{struct.unpack('<I', table.to_bytes()[-4:])[0]:08x}"
    path = table.save(tmp_path / "t.tlut")
    assert describe_table(path)["path"] == str(path)


def test_inverse_grid_is_the_maps_inverse(table, ideal_map):
    """Entries inside the gamut reproduce their own (√I_b, √I_w) through the forward map."""
    from trimeter.maps.table import _from_frame

    k = 10
    ns, ny, nx = table.inv_alpha_q.shape
    uu, vv = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    xy = _from_frame(table.inv_frame[k].astype(float), uu.ravel(), vv.ravel())
    from trimeter.model.grid import ForwardGrid

    grid = ForwardGrid.from_table(table)
    n = ny * nx
    I_b, I_w, _ = grid.intensities(table.inverse_alpha[k].ravel(), np.full(n, table.sigma_t[k]),
                                   table.inverse_g[k].ravel(), np.full(n, table.rho_b_ref), np.full(n, table.rho_w_ref))
    miss = np.hypot(np.sqrt(I_b) - xy[:, 0], np.sqrt(I_w) - xy[:, 1])
    assert np.mean(miss < 1e-4) > 0.4   # the gamut covers a good part of its frame …
    assert np.all(np.isfinite(miss))    # … and every entry is a valid material


def _recrc(data: bytearray) -> bytes:
    data[-4:] = struct.pack("<I", zlib.crc32(bytes(data[:-4])))
    return bytes(data)


@pytest.mark.parametrize("damage, message", [
    (lambda d: d[:-1], "header says"),
    (lambda d: d[:100], "truncated"),
    (lambda d: b"", "truncated"),
    (lambda d: d + b"\0", "header says"),
    (lambda d: b"XXXXXXXX" + d[8:], "bad magic"),
    (lambda d: d[:500] + bytes([d[500] ^ 1]) + d[501:], "CRC-32"),
    (lambda d: _recrc(bytearray(d[:8]) + struct.pack("<H", 2) + d[10:]), "version 2"),
    (lambda d: _recrc(bytearray(d[:72]) + struct.pack("<H", 26) + d[74:]), "do not match"),
    (lambda d: _recrc(bytearray(d[:48]) + struct.pack("<f", float("nan")) + d[52:]), "non-finite"),
    (lambda d: _recrc(bytearray(d[:52]) + struct.pack("<f", -1.0) + d[56:]), "impossible"),
])
def test_damaged_tables_are_refused(table, damage, message):
    with pytest.raises(MapFileError, match=message):
        MapTable.from_bytes(damage(table.to_bytes()))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_random_damage_never_crashes(table, data):
    raw = bytearray(table.to_bytes())
    mode = data.draw(st.sampled_from(["flip", "truncate", "garbage", "header"]))
    if mode == "flip":
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] ^= data.draw(st.integers(1, 255))
    elif mode == "truncate":
        raw = raw[:data.draw(st.integers(0, len(raw) - 1))]
    elif mode == "garbage":
        raw = bytearray(TABLE_MAGIC) + bytearray(data.draw(st.binary(min_size=0, max_size=400)))
    else:  # header fields rewritten with a valid CRC: only the decoder's own checks stand
        i = data.draw(st.integers(8, HEADER_SIZE - 1))
        raw[i] = data.draw(st.integers(0, 255))
        raw = bytearray(_recrc(raw))
    try:
        t = MapTable.from_bytes(bytes(raw))
    except MapFileError:
        return
    assert t.to_bytes() == bytes(raw)  # whatever decodes, re-encodes identically


def test_too_small_budget_is_refused(ideal_map):
    with pytest.raises(MapFileError, match="does not fit"):
        build_from_map(ideal_map, budget=40000)
