"""The stds of the instrument's fit from a device table (trimeter.inversion.table_std.TableStds): the readings'
stds and the table's own model error propagated through its compact model, as a map fit propagates them; and
their coverage on held-out materials (`trimeter bench uncertainty --sources table`)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from trimeter.formats.appearance import AppearanceMap
from trimeter.formats.device_table import DeviceTable
from trimeter.inversion import native
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.paths import MAPS_DIR

NAME = "device-n1.5-l0.4"

pytestmark = pytest.mark.skipif(not native.available(), reason="the table fit needs the compiled kernel")


@pytest.fixture(scope="module")
def table() -> DeviceTable:
    return DeviceTable.load(MAPS_DIR / f"{NAME}.tlut")


@pytest.fixture(scope="module")
def materials():
    amap = AppearanceMap.load(MAPS_DIR / f"{NAME}.tmap")
    rng = np.random.default_rng(11)
    n = 400
    alpha, sigma_t, g = rng.uniform(0.3, 0.98, n), np.exp(rng.uniform(np.log(1.0), np.log(20.0), n)), \
        rng.uniform(0.0, 0.8, n)
    rb, rw = (np.full(n, r) for r in amap.reference_rhos)
    I_b, I_w, _ = amap.query(alpha, sigma_t, g, rb, rw)
    I_c = amap.collimated_measured(alpha, sigma_t, g)
    return I_b, I_w, I_c, rb, rw


def _table_fit(table, I_b, I_w, I_c, rb, rw, **kw):
    from trimeter.inversion.table_std import TableStds

    fitted = native.TableFitter(table.to_bytes()).fit(I_b, I_w, I_c, rb, rw)
    return fitted, TableStds(table).result(fitted, I_b, I_w, I_c, rb, rw, **kw)


def test_the_table_fits_stds_are_the_lut_fits_on_the_same_table(table, materials):
    """Parameters and flags are the instrument's fit's, untouched but for the std flags; its stds agree with
    the lut fit on the table's refined model (same readings' noise model, same model error, the Jacobian of
    the compact model instead of the refined grid's)."""
    from trimeter.inversion.api import fit
    from trimeter.inversion.table_model import DeviceTableModel

    fitted, got = _table_fit(table, *materials)
    for i, name in enumerate(("alpha", "sigma_t", "g")):
        np.testing.assert_array_equal(getattr(got, name), fitted[i])
    std_flags = int(FitFlag.UNDERDETERMINED | FitFlag.STD_APPROXIMATE)
    np.testing.assert_array_equal(got.flags & ~std_flags, fitted[3] & ~std_flags)
    lut = fit(DeviceTableModel(table), *materials[:3], method="lut")
    for name in ("alpha_std", "sigma_t_std", "g_std"):
        a, b = getattr(got, name), getattr(lut, name)
        ok = np.isfinite(a) & np.isfinite(b)
        assert ok.mean() > 0.9, name
        ratio = a[ok] / b[ok]
        assert 0.95 < np.median(ratio) < 1.05, name
        assert np.mean(np.abs(ratio - 1) < 0.2) > 0.8, name
    np.testing.assert_allclose(got.sigma_t_std, lut.sigma_t_std, rtol=1e-3)
    # the same bins are STD_APPROXIMATE, but for a few judged on the other model
    approx = lambda r: (r.flags & int(FitFlag.STD_APPROXIMATE)) != 0  # noqa: E731
    assert approx(got).sum() > 0 and np.mean(approx(got) != approx(lut)) < 0.05


def test_the_readings_stds_and_the_tables_own_error_both_enter(table, materials):
    I_b, I_w, I_c, rb, rw = materials
    _, default = _table_fit(table, *materials)
    # the fit's noise model handed as given stds: the same stds
    model = [0.005 * x + 2e-4 for x in (I_b, I_w, I_c)]
    _, same = _table_fit(table, *materials, I_b_std=model[0], I_w_std=model[1], I_c_std=model[2])
    np.testing.assert_allclose(same.alpha_std, default.alpha_std, rtol=1e-12)
    # noise-free readings: what is left on α and g is the table's own error (model_std)
    _, exact = _table_fit(table, *materials, I_b_std=0.0, I_w_std=0.0, I_c_std=0.0)
    ok = (exact.flags & int(UNUSABLE | FitFlag.G_UNDEFINED)) == 0
    assert np.all(exact.alpha_std[ok] > 0) and np.all(exact.g_std[ok] > 0)
    assert np.all(exact.alpha_std[ok] < default.alpha_std[ok])
    # without the table's error the noise-free stds all but vanish (the in-scattering correction's is left):
    # it is the model_std section that gave them
    blank = DeviceTable.from_bytes(table.to_bytes())
    object.__setattr__(blank, "model_std", np.zeros_like(table.model_std))
    object.__setattr__(blank, "scales", table.scales.copy())
    blank.scales[3:5, 0] = 0.0
    _, none = _table_fit(blank, *materials, I_b_std=0.0, I_w_std=0.0, I_c_std=0.0)
    assert np.median(none.alpha_std[ok] / exact.alpha_std[ok]) < 0.05
    assert np.median(none.g_std[ok] / exact.g_std[ok]) < 0.05
    # larger readings' noise, larger stds; a NaN std is the noise model's for that bin
    _, noisy = _table_fit(table, *materials, I_b_std=0.02, I_w_std=0.02)
    assert np.all(noisy.alpha_std[ok] > default.alpha_std[ok])
    partial = np.full(len(I_b), np.nan)
    _, nan_std = _table_fit(table, *materials, I_b_std=partial, I_w_std=partial, I_c_std=partial)
    np.testing.assert_allclose(nan_std.alpha_std, default.alpha_std, rtol=1e-12)
    # the thickness's std widens σt's std alone
    _, thick = _table_fit(table, *materials, thickness_rel_std=0.02)
    np.testing.assert_array_equal(thick.alpha_std, default.alpha_std)
    np.testing.assert_allclose(thick.sigma_t_std, np.hypot(default.sigma_t_std, 0.02 * default.sigma_t), rtol=1e-12)


def test_flagged_bins_get_the_map_fits_stds_conventions(table):
    nan = float("nan")
    I_b = np.array([nan, 0.05, 0.1, 0.02])
    I_w = np.array([0.5, 0.5, 0.5, 0.021])
    I_c = np.array([0.3, 0.3, 1e-7, 0.3])
    rb, rw = np.full(4, table.rho_b_ref), np.full(4, table.rho_w_ref)
    fitted, got = _table_fit(table, I_b, I_w, I_c, rb, rw)
    assert got.flags[0] & int(FitFlag.NONFINITE_INPUT)
    assert np.isnan([got.alpha_std[0], got.sigma_t_std[0], got.g_std[0]]).all()
    assert got.flags[2] & int(FitFlag.IC_BELOW_FLOOR) and np.isinf(got.sigma_t_std[2])
    assert np.isfinite(got.alpha_std[1]) and np.isfinite(got.g_std[1])
    undefined = (got.flags & int(FitFlag.G_UNDEFINED)) != 0
    assert np.isnan(got.g_std[undefined]).all()
    from trimeter.errors import InputError
    from trimeter.inversion.table_std import TableStds

    with pytest.raises(InputError, match="same bins"):
        TableStds(table).result(fitted, I_b[:3], I_w, I_c, rb, rw)


def test_table_fit_coverage_on_held_out_materials(capsys):
    """The table's ±1σ / ±2σ cover the held-out truths about as often as they should (the bench's table rows)."""
    from trimeter.bench import uncertainty

    args = argparse.Namespace(maps=[NAME], noise="0.005", draws=2, thickness_rel_std=0.0, modes="given",
                              part="scored", out=None, seed=0, sources="table")
    report = uncertainty.measure(args)
    assert [r["case"] for r in report["rows"]] == [f"{NAME} table"]
    row = report["rows"][0]
    for p in ("alpha", "sigma_t", "g"):
        assert 0.6 <= row[p]["within_1sigma"] <= 0.8, (p, row[p])
        assert 0.9 <= row[p]["within_2sigma"] <= 0.99, (p, row[p])
    args.sources = "maps"
    with pytest.raises(Exception, match="--sources"):
        uncertainty.measure(args)


def test_the_c_evaluation_of_the_table_model_is_the_numpy_one(table, monkeypatch, materials):
    """native.TableModel (tm_table_eval, what the stds take their Jacobian from) evaluates CompactForward, clamped
    to the box, NaN as the box's lower end; the stds from the numpy model are the same."""
    from trimeter.inversion import table_std

    model = native.TableModel(table.to_bytes())
    forward = table.forward()
    rng = np.random.default_rng(2)
    n = 500
    ls_lo, ls_hi = float(table.log_sigma_t[0]), float(table.log_sigma_t[-1])
    alpha, ls, g = rng.uniform(-0.1, 1.1, n), rng.uniform(ls_lo - 0.5, ls_hi + 0.5, n), rng.uniform(-0.2, 1.0, n)
    got, want = model.evaluate(alpha, ls, g), forward.evaluate(alpha, np.clip(ls, ls_lo, ls_hi), g)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    nan_point = model.evaluate([np.nan], [np.nan], [np.nan])
    corner = forward.evaluate(table.alpha[:1], table.log_sigma_t[:1], table.g[:1])
    np.testing.assert_allclose(nan_point[0], corner[0], rtol=1e-9)
    _, with_c = _table_fit(table, *materials)
    monkeypatch.setattr(table_std.native, "available", lambda: False)
    _, with_numpy = _table_fit(table, *materials)
    assert not isinstance(table_std.CompactGrid(table).compact, native.TableModel)
    for name in ("alpha_std", "sigma_t_std", "g_std"):
        np.testing.assert_allclose(getattr(with_numpy, name), getattr(with_c, name), rtol=1e-7)
    np.testing.assert_array_equal(with_numpy.flags, with_c.flags)


@pytest.mark.parametrize("name", ["device-n1.5-l0.4", "device-n1.5-l0.8"])
def test_the_shipped_tables_carry_their_maps_error_at_the_shipped_scale(name):
    """The table stds take the map's error from the table: a shipped table built before LEAVE_ONE_OUT_SCALE
    (or its map) changed would give other stds than its map's fit; rebuild it with the map pipeline then."""
    from trimeter.formats.appearance import map_model_variance

    amap = AppearanceMap.load(MAPS_DIR / f"{name}.tmap")
    table = DeviceTable.load(MAPS_DIR / f"{name}.tlut")
    assert table.parent_sha256 == amap.checksum
    want = np.sqrt(map_model_variance(amap)[0])
    np.testing.assert_allclose(np.sqrt(table.model_variance()), want, rtol=0, atol=float(table.scales[3:5, 1].max()))
