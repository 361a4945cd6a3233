"""The C fit from a device table alone (native.TableFitter, table_fit.c; the source the firmware links
as tr_fit_bins): agreement with the numpy reference (tools/device_table_study.py's fit with the compact model
on the fly), in double and in single precision, the issue's accuracy on the l0.4 held-out set, and
every bad table or input refused or flagged, never a crash."""

from __future__ import annotations

import importlib.util
import inspect
import shutil
import struct
import sys
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from trimeter.errors import MapFileError
from trimeter.inversion import api, native
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.native import invert_h

ROOT = Path(__file__).resolve().parents[2]
# the flag the table fit never sets (it returns no stds to qualify)
NOT_SET = int(FitFlag.STD_APPROXIMATE)

pytestmark = pytest.mark.skipif(not native.available(), reason="the compiled kernel is not built (make native)")


def _tool():
    spec = importlib.util.spec_from_file_location("device_table_tool", ROOT / "tools" / "device_table_study.py")
    tool = importlib.util.module_from_spec(spec)
    sys.modules["device_table_tool"] = tool
    spec.loader.exec_module(tool)
    return tool


@pytest.fixture(scope="module")
def heldout():
    """The l0.4 map's v2 table, its held-out set's intensities and truth, and the numpy reference fit."""
    from trimeter.bench.fit_scoring import error_budget
    from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities
    from trimeter.formats.appearance import AppearanceMap, find_map

    tool = _tool()
    amap = AppearanceMap.load(find_map("device-n1.5-l0.4"))
    table = tool.build(amap)
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    I_b, I_w = heldout_intensities(h, rb, rw)
    I_c = heldout_collimated(amap, h)
    reference = tool.fit_table(table, tool.on_the_fly_inverter(table), I_b, I_w, I_c)
    return SimpleNamespace(data=table.to_bytes(), I=(I_b, I_w, I_c), truth=(h["alpha"], h["sigma_t"], h["g"]),
                           budget=error_budget(amap, h, rb, rw), reference=reference)


@pytest.fixture(scope="module")
def single_library(tmp_path_factory):
    """The kernel compiled with -DTR_SINGLE: the table fit in float, as the MCU runs it."""
    from trimeter.bench._firmware import single_precision_library

    if not (shutil.which("cc") or shutil.which("gcc")):
        pytest.skip("no C compiler")
    return single_precision_library(tmp_path_factory.mktemp("single"))


def _differences(fit, reference):
    alpha, sigma_t, g, flags = fit
    assert np.array_equal(np.isnan(alpha), np.isnan(reference.alpha))
    assert np.array_equal(np.isnan(g), np.isnan(reference.g))
    with np.errstate(invalid="ignore"):
        return (np.nan_to_num(np.abs(alpha - reference.alpha)), np.nan_to_num(np.abs(sigma_t / reference.sigma_t - 1)),
                np.nan_to_num(np.abs(g - reference.g)))


def test_the_fit_s_settings_are_fit_s_defaults():
    defaults = {k: v.default for k, v in inspect.signature(api.fit).parameters.items()}
    c_side = {"noise_rel": invert_h.TABLE_FIT_NOISE_REL, "noise_abs": invert_h.TABLE_FIT_NOISE_ABS,
              "ic_floor": invert_h.TABLE_FIT_IC_FLOOR, "alpha_min_g": invert_h.TABLE_FIT_ALPHA_MIN_G,
              "polish_tol": invert_h.TABLE_FIT_POLISH_TOL}
    assert c_side == {k: defaults[k] for k in c_side}
    assert invert_h.TABLE_FIT_POLISH == 8  # the lut method's default polish (its bench variant p≤8)
    constants = {"POLISH_TOL_STD": invert_h.TABLE_FIT_POLISH_TOL_STD,
                 "INSCATTER_REL_STD": invert_h.TABLE_FIT_INSCATTER_REL_STD,
                 "UNDERDETERMINED_ALPHA_STD": invert_h.TABLE_FIT_UNDERDETERMINED_ALPHA_STD,
                 "UNDERDETERMINED_G_STD": invert_h.TABLE_FIT_UNDERDETERMINED_G_STD}
    assert constants == {k: getattr(api, k) for k in constants}


def test_double_precision_agrees_with_the_numpy_reference_bin_for_bin(heldout):
    fit = native.TableFitter(heldout.data).fit(*heldout.I)
    da, ds, dg = _differences(fit, heldout.reference)
    assert da.max() <= 1e-9 and ds.max() <= 1e-9 and dg.max() <= 1e-9, (da.max(), ds.max(), dg.max())
    assert np.array_equal(fit[3], heldout.reference.flags & ~NOT_SET)


@pytest.mark.parametrize("cover_slide_n", [None, 1.52])
def test_a_synthetic_table_with_or_without_cover_slides_agrees_too(cover_slide_n):
    """Another model, random inverse codes, and both Fresnel stacks (the shipped map has cover slides)."""
    from test_compact_table import small_table

    tool = _tool()
    table = small_table(cover_slide_n=cover_slide_n)
    rng = np.random.default_rng(1)
    I_b = rng.uniform(0.01, 0.4, 200)
    I = (I_b, I_b + rng.uniform(0.01, 0.4, 200), rng.uniform(0.001, 0.9, 200))
    reference = tool.fit_table(table, tool.on_the_fly_inverter(table), *I)
    fit = native.TableFitter(table.to_bytes()).fit(*I)
    assert max(d.max() for d in _differences(fit, reference)) <= 1e-9
    assert np.array_equal(fit[3], reference.flags & ~NOT_SET)


def test_single_precision_agrees_within_the_device_tolerances(heldout, single_library):
    """The issue's on-device tolerances (|Δα| ≤ 1e-3, |Δσt|/σt ≤ 1e-3, |Δg| ≤ 2e-3) over every bin; the
    bins the fit calls determined far inside them (float only moves the underdetermined ones, along
    what their data cannot tell apart)."""
    fit = native.TableFitter(heldout.data, library=single_library).fit(*heldout.I)
    da, ds, dg = _differences(fit, heldout.reference)
    assert da.max() <= 1e-3 and ds.max() <= 1e-3 and dg.max() <= 2e-3, (da.max(), ds.max(), dg.max())
    determined = (fit[3] & int(FitFlag.UNDERDETERMINED)) == 0
    assert determined.sum() > 100
    assert da[determined].max() <= 1e-4 and dg[determined].max() <= 1e-4
    # inputs rounded to float can make I_b = I_w (optically thick bins): the only flag that may differ
    either = int(FitFlag.BLACK_NOT_BELOW_WHITE) | NOT_SET
    assert np.array_equal(fit[3] & ~either, heldout.reference.flags & ~either)


def test_the_table_alone_meets_the_accuracy_targets_on_the_held_out_set(heldout):
    from trimeter.bench.fit_scoring import error_figures

    alpha, sigma_t, g, flags = native.TableFitter(heldout.data).fit(*heldout.I)
    res = SimpleNamespace(alpha=alpha, sigma_t=sigma_t, g=g, flags=flags, alpha_std=np.full_like(alpha, np.nan))
    st = error_figures(res, heldout.truth, heldout.budget)
    assert st["alpha_p95"] <= 0.01 and st["sigma_rel_p95"] <= 0.01 and st["g_p95"] <= 0.015, st


# ----------------------------------------------------------------------------------- bad input
def _resealed(data: bytes, offset: int, new: bytes) -> bytes:
    body = data[:offset] + new + data[offset + len(new):-4]
    return body + struct.pack("<I", zlib.crc32(body))


@pytest.mark.parametrize("offset, new", [
    (0, b"\x89TRMAP\r\n"),                   # magic
    (8, struct.pack("<H", 1)),               # format version
    (12, struct.pack("<I", 1000)),           # total size
    (84, struct.pack("<f", float("nan"))),   # thickness
    (96, struct.pack("<f", 0.001)),          # ρ_w below ρ_b
    (116, struct.pack("<H", 3)),             # n_alpha below 4
    (118, struct.pack("<H", 60000)),         # n_sigma: sections past the end
    (156, struct.pack("<I", 260)),           # alpha's offset
    (250, b"\x01"),                          # reserved
    (256, struct.pack("<ff", 0.5, 0.1)),     # α axis not increasing
])
def test_a_table_the_core_cannot_use_is_refused(heldout, offset, new):
    with pytest.raises(MapFileError, match="not a format-2 table"):
        native.TableFitter(_resealed(heldout.data, offset, new))


def _section(data: bytes, index: int) -> int:
    """The byte offset of section `index` (the header's directory: offset, size per section)."""
    return struct.unpack_from("<I", data, 156 + 8 * index)[0]


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
@pytest.mark.parametrize("where", ["alpha first", "alpha middle", "alpha last", "g last", "frame first",
                                   "frame middle", "frame last"])
def test_a_non_finite_axis_node_or_frame_value_is_refused_wherever_it_is(heldout, value, where):
    """The axes are checked as finite ends and strictly increasing steps, the frame by one sum: a
    non-finite value anywhere in either is refused all the same."""
    data = heldout.data
    na, ns, ng = struct.unpack_from("<HHH", data, 116)
    name, place = where.split()
    start, count = {"alpha": (_section(data, 0), na), "g": (_section(data, 2), ng),
                    "frame": (_section(data, 7), ns * 6)}[name]
    index = {"first": 0, "middle": count // 2, "last": count - 1}[place]
    with pytest.raises(MapFileError, match="not a format-2 table"):
        native.TableFitter(_resealed(data, start + 4 * index, struct.pack("<f", value)))


def test_bins_outside_the_map_s_box_agree_with_the_reference_too(heldout):
    """Bins whose solution lies past the box (g held at an edge, α crawling or held too: the polish's
    clamps keep it where it was), against the numpy reference bin for bin."""
    from trimeter.formats.device_table import DeviceTable

    tool = _tool()
    table = DeviceTable.from_bytes(heldout.data)
    I_b = np.array([0.02, 0.40, 0.60, 0.15, 0.30, 0.01])
    I_w = np.array([0.05, 0.70, 0.62, 0.90, 0.31, 0.99])
    I_c = np.array([0.001, 0.40, 0.002, 0.85, 0.0005, 0.9])
    reference = tool.fit_table(table, tool.on_the_fly_inverter(table), I_b, I_w, I_c)
    fit = native.TableFitter(heldout.data).fit(I_b, I_w, I_c)
    assert (reference.flags & int(FitFlag.NOT_CONVERGED)).sum() >= 3  # the case this is about
    assert max(d.max() for d in _differences(fit, reference)) <= 1e-9
    assert np.array_equal(fit[3], reference.flags & ~NOT_SET)


def test_a_corrupt_or_truncated_table_is_refused(heldout):
    flipped = bytearray(heldout.data)
    flipped[300] ^= 1
    for data in (bytes(flipped), heldout.data[:-10], b"", b"\x89TRLUT"):
        with pytest.raises(MapFileError, match="crc32"):
            native.TableFitter(data)


def test_random_damage_is_refused_or_fitted_never_a_crash(heldout):
    """Resealed random byte changes anywhere: the reader refuses the table or the fit returns values
    or flagged NaN bins (the C fuzzer does the same at scale)."""
    rng = np.random.default_rng(7)
    I = [np.array([x[0], x[100], x[200]]) for x in heldout.I]
    for _ in range(60):
        data = bytearray(heldout.data)
        for offset in rng.integers(0, len(data) - 4, 4):
            data[offset] = rng.integers(0, 256)
        try:
            fitter = native.TableFitter(_resealed(bytes(data), 0, b""))
        except MapFileError:
            continue
        alpha, sigma_t, g, flags = fitter.fit(*I)
        assert alpha.shape == (3,) and flags.dtype == np.int64


def test_bad_inputs_are_flagged_bins_with_nan_values(heldout):
    fitter = native.TableFitter(heldout.data)
    nan, inf = float("nan"), float("inf")
    I_b = np.array([nan, 0.1, -0.5, 0.1, 0.1, 0.1, inf])
    I_w = np.array([0.5, 0.5, 0.5, 1.5, 0.5, 0.5, 0.5])
    I_c = np.array([0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1])
    rho_b = np.array([0.02, 0.5, 0.02, 0.02, 0.02, 0.02, 0.02])
    rho_w = np.array([0.9, 0.2, 0.9, 0.9, 0.9, 0.9, 0.9])
    alpha, sigma_t, g, flags = fitter.fit(I_b, I_w, I_c, rho_b, rho_w)
    expected = [FitFlag.NONFINITE_INPUT, FitFlag.BAD_BACKGROUND, FitFlag.NEGATIVE_INPUT, FitFlag.ABOVE_ONE]
    for i, flag in enumerate(expected):
        assert flags[i] & int(flag) and np.isnan(alpha[i]) and np.isnan(sigma_t[i]) and np.isnan(g[i])
    assert flags[6] & int(FitFlag.NONFINITE_INPUT) and np.isnan(alpha[6])
    assert not flags[4] & int(UNUSABLE) and np.isfinite(alpha[4]) and np.isfinite(sigma_t[4])
    below = fitter.fit(0.1, 0.5, 0.0)
    assert below[3] & int(FitFlag.IC_BELOW_FLOOR) and np.isfinite(below[1])
    assert fitter.fit([], [], [])[0].shape == (0,)


def test_the_bench_prints_the_table_fit_s_figures_and_names_bad_arguments(heldout, tmp_path, capsys):
    from trimeter.cli import main

    path = tmp_path / "l04.tlut"
    path.write_bytes(heldout.data)
    assert main(["bench", "table-fit", "--table", str(path), "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("table alone", "map lut"))]
    assert len(rows) == 3 and all(" met " in row for row in rows), out
    assert main(["bench", "table-fit", "--table", str(path), "--library", str(tmp_path / "none.so")]) == 2
    assert "trimeter: error: --library: no such file" in capsys.readouterr().err
