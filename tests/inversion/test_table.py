"""The device table (.tlut) as the lut method and the instrument read it: exact round trip within a slot, the
inverse grid is the map's own inverse, and no damage decodes into something else."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trimeter.errors import MapFileError
from trimeter.formats.device_table import DeviceTable, HEADER_SIZE, MAGIC, MAX_BYTES, describe_table, table_path_for
from trimeter.inversion.table_builder import build_from_map
from trimeter.inversion.table_builder import _from_frame
from trimeter.model.grid import ForwardGrid


@pytest.fixture(scope="module")
def table(ideal_map):
    return build_from_map(ideal_map)


def test_round_trip_is_byte_exact_and_fits_a_slot(table, ideal_map):
    data = table.to_bytes()
    assert len(data) == table.size_bytes <= MAX_BYTES
    again = DeviceTable.from_bytes(data)
    assert again.to_bytes() == data
    assert again.parent_sha256 == ideal_map.checksum
    assert again.name == ideal_map.name
    # the compact model passes through the map's own nodes
    np.testing.assert_allclose(again.coefficients_grid[..., 0], ideal_map.A, atol=1e-4)
    np.testing.assert_allclose(again.coefficients_grid[..., 2], ideal_map.C, atol=1e-4)


def test_committed_table_matches_its_map(ideal_map):
    table = DeviceTable.load(table_path_for(ideal_map.path))
    assert table.parent_sha256 == ideal_map.checksum


def test_describe_table(table, tmp_path):
    data = table.to_bytes()
    info = describe_table(data)
    assert info["size_bytes"] == len(data)
    assert info["crc32"] == f"{struct.unpack('<I', data[-4:])[0]:08x}"
    path = table.save(tmp_path / "t.tlut")
    assert describe_table(path)["path"] == str(path)


def test_inverse_grid_is_the_maps_inverse(table):
    """Entries inside the gamut reproduce their own (√I_b, √I_w) through the table's forward model."""
    k = 10
    ns, ny, nx = table.inv_alpha_q.shape
    uu, vv = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    xy = _from_frame(table.inv_frame[k].astype(float), uu.ravel(), vv.ravel())
    grid = ForwardGrid.from_table(table)
    n = ny * nx
    rho_b, rho_w = table.reference_rhos
    I_b, I_w, _ = grid.intensities(table.inverse_alpha[k].ravel(), np.full(n, np.exp(table.log_sigma_t[k])),
                                   table.inverse_g[k].ravel(), np.full(n, rho_b), np.full(n, rho_w))
    miss = np.hypot(np.sqrt(I_b) - xy[:, 0], np.sqrt(I_w) - xy[:, 1])
    assert np.mean(miss < 1e-3) > 0.4   # the gamut covers a good part of its frame …
    assert np.all(np.isfinite(miss))    # … and every entry is a valid material


def _recrc(data: bytearray) -> bytes:
    data[-4:] = struct.pack("<I", zlib.crc32(bytes(data[:-4])))
    return bytes(data)


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
        raw = bytearray(MAGIC) + bytearray(data.draw(st.binary(min_size=0, max_size=400)))
    else:  # header fields rewritten with a valid CRC: only the decoder's own checks stand
        i = data.draw(st.integers(8, HEADER_SIZE - 1))
        raw[i] = data.draw(st.integers(0, 255))
        raw = bytearray(_recrc(raw))
    try:
        t = DeviceTable.from_bytes(bytes(raw))
    except MapFileError:
        return
    assert t.to_bytes() == bytes(raw)  # whatever decodes, re-encodes identically
