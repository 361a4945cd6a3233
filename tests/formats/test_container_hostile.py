"""Crafted data files WITH VALID CHECKSUMS: the checksum does not save the reader, the schema does.

Every crafted header must give one clear MapFileError naming the offending field, from every entry
point: the Python loaders (AppearanceMap.load, InscatterTable.load, the MLP model metadata; DeviceTable.load
in tests/inversion/test_compact_table.py) and the CLI (`trimeter map info FILE`, `trimeter fit --map FILE`:
`trimeter: error: …`, exit 2, no traceback).
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trimeter.cli import main
from trimeter.errors import MapFileError
from trimeter.formats.appearance import AppearanceMap
from trimeter.formats.container import FORMAT_VERSION, MAGIC, MAX_CONTAINER_BYTES
from trimeter.formats.inscatter_file import load_inscatter, save_inscatter
from trimeter.model.inscatter_table import InscatterTable

from test_container import small_map


def craft(path, header, payload: bytes = b"", header_len: int | None = None):
    """A container with this header (a dict, or raw bytes) and payload, and a correct SHA-256."""
    raw = header if isinstance(header, bytes) else json.dumps(header).encode()
    body = struct.pack("<8sII", MAGIC, FORMAT_VERSION, len(raw) if header_len is None else header_len) + raw + payload
    path.write_bytes(body + hashlib.sha256(body).digest())
    return path


def split(path):
    """(header dict, payload bytes) of a container file."""
    data = path.read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)
    return json.loads(data[16:16 + length]), data[16 + length:-32]


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """A valid map's header and payload, to mutate."""
    path = tmp_path_factory.mktemp("valid") / "m.tmap"
    small_map().save(path)
    return split(path)


def _set(doc, dotted, value):
    *parents, last = dotted.split(".")
    for key in parents:
        doc = doc[key]
    if value is _DELETE:
        del doc[last]
    else:
        doc[last] = value


_DELETE = object()


def _payload_with(valid, name, values):
    """The payload with array `name` replaced by `values` (same dtype and byte count)."""
    header, payload = valid
    d = header["arrays"][name]
    data = bytearray(payload)
    data[d["offset"]:d["offset"] + d["nbytes"]] = np.asarray(values, dtype=d["dtype"]).tobytes()
    return bytes(data)


# (what is crafted, header field → value, the field the message must name)
HEADER_CASES = [
    ("zero thickness", "meta.recipe.thickness_mm", 0, "meta.recipe.thickness_mm"),
    ("negative thickness", "meta.recipe.thickness_mm", -0.4, "meta.recipe.thickness_mm"),
    ("thickness as text", "meta.recipe.thickness_mm", "0.4", "meta.recipe.thickness_mm"),
    ("thickness as bool", "meta.recipe.thickness_mm", True, "meta.recipe.thickness_mm"),
    ("absurd thickness", "meta.recipe.thickness_mm", 1e300, "meta.recipe.thickness_mm"),
    ("n out of [1, 3]", "meta.recipe.n", 5.0, "meta.recipe.n"),
    ("n below 1", "meta.recipe.n", 0.5, "meta.recipe.n"),
    ("missing n", "meta.recipe.n", _DELETE, "n"),
    ("missing recipe", "meta.recipe", _DELETE, "recipe"),
    ("recipe is a list", "meta.recipe", [1, 2], "meta.recipe"),
    ("geometry not text", "meta.recipe.geometry", {"a": 1}, "meta.recipe.geometry"),
    ("black background as white", "meta.recipe.reference_rho_b", 1.0, "reference_rho_b"),
    ("cover slide index as text", "meta.recipe.geometry_params", {"cover_slides": True, "cover_slide_n": "x"},
     "meta.recipe.geometry_params.cover_slide_n"),
    ("cover slides without index", "meta.recipe.geometry_params", {"cover_slides": True}, "cover_slide_n"),
    ("deep provenance", "meta.provenance", json.loads("[" * 12 + "]" * 12), "meta.provenance"),
    ("format version as text", "meta.map_format_version", "1", "map format version"),
    ("complex dtype", "arrays.A.dtype", "<c8", "header.arrays.A.dtype"),
    ("object dtype", "arrays.A.dtype", "|O", "header.arrays.A.dtype"),
    ("structured dtype", "arrays.A.dtype", [["x", "<f4"]], "header.arrays.A.dtype"),
    ("big-endian dtype", "arrays.alpha.dtype", ">f8", "header.arrays.alpha.dtype"),
    ("integer dtype for coefficients", "arrays.A.dtype", "<i4", "arrays.A.dtype"),
    ("shape mismatch", "arrays.A.shape", [3, 2, 4], "arrays.A.shape"),
    ("huge declared shape", "arrays.A.shape", [2**31, 2**31, 2], "A"),
    ("shape overflowing int64", "arrays.A.shape", [2**31] * 8, "arrays.A.shape"),
    ("negative dimension", "arrays.A.shape", [-3, 4, 2], "header.arrays.A.shape[0]"),
    ("bool dimension", "arrays.g.shape", [True, True], "header.arrays.g.shape[0]"),
    ("float offset", "arrays.A.offset", 1.5, "header.arrays.A.offset"),
    ("huge nbytes", "arrays.A.nbytes", 2**62, "A"),
    ("offset past the payload", "arrays.A.offset", 10**9, "A"),
    ("missing offset", "arrays.A.offset", _DELETE, "offset"),
    ("missing array", "arrays.std_w", _DELETE, "std_w"),
    ("unexpected array", "arrays.extra", {"dtype": "<f8", "shape": [1], "offset": 0, "nbytes": 8}, "extra"),
    ("extra descriptor field", "arrays.A.fortran", True, "header.arrays.A.fortran"),
    ("meta is a number", "meta", 3, "header.meta"),
    ("kind is a number", "kind", 7, "header.kind"),
    ("kind of another file", "kind", "inscatter-table", "expected a 'appearance-map'"),
]


@pytest.mark.parametrize("what, field, value, named", HEADER_CASES, ids=[c[0] for c in HEADER_CASES])
def test_crafted_header_is_refused_naming_the_field(tmp_path, valid, capsys, what, field, value, named):
    header = copy.deepcopy(valid[0])
    _set(header, field, value)
    path = craft(tmp_path / "m.tmap", header, valid[1])
    _refused_everywhere(path, named, capsys)


ARRAY_CASES = [
    ("α axis up to 5", "alpha", [0.0, 0.5, 5.0], "arrays.alpha"),
    ("negative α", "alpha", [-0.5, 0.5, 0.9], "arrays.alpha"),
    ("non-monotonic σt", "sigma_t", [0.1, 10.0, 1.0, 50.0], "arrays.sigma_t"),
    ("zero σt", "sigma_t", [0.0, 1.0, 10.0, 50.0], "arrays.sigma_t"),
    ("NaN in the g axis", "g", [0.0, np.nan], "arrays.g"),
    ("g of 1", "g", [0.0, 1.0], "arrays.g"),
    ("infinite coefficient", "A", np.full((3, 4, 2), np.inf), "arrays.A"),
    ("C of 1 (I(ρ = 1) infinite)", "C", np.ones((3, 4, 2)), "arrays.C"),
    ("negative std-error", "std_b", -np.ones((3, 4, 2)), "arrays.std_b"),
]


@pytest.mark.parametrize("what, name, values, named", ARRAY_CASES, ids=[c[0] for c in ARRAY_CASES])
def test_crafted_array_values_are_refused_naming_the_array(tmp_path, valid, capsys, what, name, values, named):
    path = craft(tmp_path / "m.tmap", valid[0], _payload_with(valid, name, values))
    _refused_everywhere(path, named, capsys)


RAW_CASES = [
    ("header not JSON", b"{not json", None, "unreadable header"),
    ("header is a list", b"[1, 2, 3]", None, "header must be a table"),
    ("NaN in the header", b'{"kind": "appearance-map", "meta": {"x": NaN}, "arrays": {}}', None, "NaN"),
    ("5000-deep header", b"[" * 5000 + b"]" * 5000, None, "nested"),
    ("60-digit dimension", b'{"kind": "appearance-map", "meta": {}, "arrays": {"A": {"dtype": "<f4", "shape": ['
     + b"9" * 60 + b'], "offset": 0, "nbytes": 4}}}', None, "shape[0]"),
    ("header length past the end", b"{}", 2**31, "header length"),
]


@pytest.mark.parametrize("what, raw, header_len, named", RAW_CASES, ids=[c[0] for c in RAW_CASES])
def test_crafted_raw_header_is_refused(tmp_path, capsys, what, raw, header_len, named):
    path = craft(tmp_path / "m.tmap", raw, header_len=header_len)
    _refused_everywhere(path, named, capsys)


def test_oversized_file_is_refused_before_it_is_read(tmp_path, capsys):
    path = tmp_path / "huge.tmap"
    with open(path, "wb") as f:  # sparse: no disk used, and a reader that read it would take seconds
        f.truncate(MAX_CONTAINER_BYTES + 1)
    _refused_everywhere(path, "larger than any trimeter data file", capsys)


def test_not_a_regular_file_is_refused(tmp_path):
    fifo = tmp_path / "pipe.tmap"
    os.mkfifo(fifo)
    with pytest.raises(MapFileError, match="not a regular file"):
        AppearanceMap.load(fifo)


def _refused_everywhere(path, named, capsys):
    """The loader, `map info` and `fit --map` all refuse the file with one line naming `named`."""
    with pytest.raises(MapFileError) as err:
        AppearanceMap.load(path)
    assert named in str(err.value) and str(path) in str(err.value)
    csv = path.parent / "meas.csv"
    csv.write_text("wavelength_nm,I_b,I_w,I_c\n500,0.1,0.4,0.3\n")
    for argv in (["map", "info", str(path)], ["fit", "--map", str(path), "--input", str(csv)]):
        capsys.readouterr()
        assert main(argv) == 2
        err_text = capsys.readouterr().err
        assert err_text.startswith("trimeter: error: ") and named in err_text and "Traceback" not in err_text
        assert len(err_text) < 600  # a hostile value is not echoed back whole


# ---------------------------------------------------------------------------------- hypothesis
_json = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=False)
                     | st.text(max_size=20),
                     lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                 max_size=4),
                     max_leaves=12)
_FIELDS = ["kind", "meta", "meta.recipe", "meta.recipe.n", "meta.recipe.thickness_mm", "meta.recipe.geometry",
           "meta.recipe.reference_rho_w", "meta.recipe.geometry_params", "meta.provenance", "meta.map_format_version",
           "arrays", "arrays.A", "arrays.A.dtype", "arrays.A.shape", "arrays.A.offset", "arrays.A.nbytes",
           "arrays.alpha.shape", "arrays.g.dtype"]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(_FIELDS), value=_json)
def test_any_json_in_any_field_is_a_map_file_error_or_a_valid_map(tmp_path, valid, field, value):
    header = copy.deepcopy(valid[0])
    _set(header, field, value)
    path = craft(tmp_path / "h.tmap", header, valid[1])
    try:
        amap = AppearanceMap.load(path)
    except MapFileError:
        return
    assert amap.thickness_mm > 0 and 1 <= amap.n <= 3 and amap.A.shape == (3, 4, 2)


# ------------------------------------------------------------------ the map's in-scatter table
def _inscatter_header(tmp_path):
    amap = small_map()
    L = np.zeros((3, 3, 2))
    table = InscatterTable(L, u_max=6.9, tau_max=10.0, v_max=2.3, n=amap.n, thickness_mm=amap.thickness_mm,
                           geometry_params={})
    save_inscatter(table, tmp_path / "valid.tins")
    return split(tmp_path / "valid.tins")


INSCATTER_CASES = [
    ("zero u_max (division by zero)", "meta.u_max", 0.0, "meta.u_max"),
    ("tau_max as text", "meta.tau_max", "10", "meta.tau_max"),
    ("missing v_max", "meta.v_max", _DELETE, "v_max"),
    ("n of 7", "meta.n", 7, "meta.n"),
    ("format 2", "meta.format_version", 2, "in-scatter table format version 2"),
    ("L as complex", "arrays.L.dtype", "<c16", "header.arrays.L.dtype"),
    ("L of one dimension", "arrays.L.shape", [18], "arrays.L.shape"),
]


@pytest.mark.parametrize("what, field, value, named", INSCATTER_CASES, ids=[c[0] for c in INSCATTER_CASES])
def test_crafted_inscatter_table_is_refused(tmp_path, capsys, what, field, value, named):
    header, payload = _inscatter_header(tmp_path)
    _set(header, field, value)
    tins = craft(tmp_path / "m.tins", header, payload)
    with pytest.raises(MapFileError, match="m.tins") as err:
        load_inscatter(tins)
    assert named in str(err.value)
    small_map().save(tmp_path / "m.tmap")  # the map is fine; the table next to it is not
    capsys.readouterr()
    assert main(["map", "info", str(tmp_path / "m.tmap")]) == 2
    err_text = capsys.readouterr().err
    assert err_text.startswith("trimeter: error: ") and named in err_text


def test_inscatter_table_with_nan_is_refused(tmp_path):
    header, payload = _inscatter_header(tmp_path)
    tins = craft(tmp_path / "m.tins", header, np.full(18, np.nan).tobytes())
    with pytest.raises(MapFileError, match="arrays.L holds NaN"):
        load_inscatter(tins)


# the device table (.tlut): tests/inversion/test_compact_table.py crafts every header field and section


# ------------------------------------------------------------------------------- the MLP model
@pytest.mark.parametrize("key, value, named", [
    ("trimeter.kind", "x" * 10_000, "trimeter.kind"),
    ("trimeter.features", "sqrt_I_b", "trimeter.features"),
    ("trimeter.format", "3", "trimeter.format"),
])
def test_crafted_mlp_metadata_is_refused(tmp_path, key, value, named):
    onnx = pytest.importorskip("onnx")
    from trimeter.inversion.mlp import MlpInverter
    from trimeter.paths import MAPS_DIR

    model = onnx.load(MAPS_DIR / "ideal-n1.5-l0.5.onnx")
    props = {p.key: p.value for p in model.metadata_props}
    props[key] = value
    onnx.helper.set_model_props(model, props)
    path = tmp_path / "m.onnx"
    onnx.save(model, path)
    with pytest.raises(MapFileError, match=named) as err:
        MlpInverter(path.read_bytes(), path, "", (0.0, 1.0), (0.0, 1.0), (0.0, 0.9))
    assert len(str(err.value)) < 400


def test_oversized_mlp_model_is_refused_before_it_is_read(tmp_path):
    from trimeter.inversion.artifacts import load_mlp

    path = tmp_path / "m.onnx"
    with open(path, "wb") as f:
        f.truncate(2**30)
    with pytest.raises(MapFileError, match="larger than any MLP model"):
        load_mlp(path, small_map())
