"""Uncertainty that means what it says: the machinery of the stds (given intensity stds, the map's own
error, the thickness's and the in-scattering correction's uncertainty), C against numpy, bad input,
and `trimeter bench uncertainty`'s coverage count. No statistical threshold at small N here: the
coverage figures themselves come from the benchmark."""

import numpy as np
import pytest
from scipy.stats import norm

import trimeter
from trimeter.bench.uncertainty import coverage, mean_signed_z
from trimeter.cli import main
from trimeter.errors import InputError
from trimeter.inversion import api, finish, native
from trimeter.model.grid import ForwardGrid, node_model_variance
from trimeter.model.sample_setup import SampleSetup
from trimeter.paths import MAPS_DIR

DEVICE = MAPS_DIR / "device-n1.5-l0.4.tmap"


def _materials(amap, n=400, seed=0):
    """Clean, well-conditioned bins of the map: intensities from its own forward model."""
    from trimeter.inversion.artifacts import load_artifacts

    rng = np.random.default_rng(seed)
    alpha, g = rng.uniform(0.5, 0.97, n), rng.uniform(0.1, 0.8, n)
    sigma_t = np.exp(rng.uniform(np.log(0.5), np.log(5), n))
    return load_artifacts(amap).grid.intensities(alpha, sigma_t, g, *amap.reference_rhos)


def test_coverage_counts_the_share_within_one_and_two_sigma():
    # estimates placed at known multiples of their std: the exact Gaussian shares, by construction
    z = norm.ppf(np.linspace(0.0005, 0.9995, 1000))
    std = np.linspace(0.5, 2.0, 1000)
    truth = np.linspace(-1, 1, 1000)
    c1, c2, n = coverage(truth + z * std, std, truth, np.ones(1000, bool))
    assert n == 1000 and c1 == pytest.approx(0.6827, abs=0.002) and c2 == pytest.approx(0.9545, abs=0.002)
    # a NaN estimate or std covers nothing; an infinite std (σt only bounded) covers; masked bins do not count
    est, s = truth + z * std, std.copy()
    est[:10], s[10:20], s[20:30] = np.nan, np.nan, np.inf
    mask = np.ones(1000, bool)
    mask[-100:] = False
    c1b, _, nb = coverage(est, s, truth, mask)
    inside = np.abs(z[30:900]) <= 1
    assert nb == 900 and c1b == pytest.approx((inside.sum() + 10) / 900)


def test_mean_signed_z_is_the_offset_the_estimates_share():
    z = norm.ppf(np.linspace(0.0005, 0.9995, 1000))  # symmetric: mean 0
    std, truth = np.linspace(0.5, 2.0, 1000), np.linspace(-1, 1, 1000)
    everything = np.ones(1000, bool)
    assert mean_signed_z(truth + z * std, std, truth, everything) == pytest.approx(0.0, abs=1e-9)
    assert mean_signed_z(truth + (z - 0.3) * std, std, truth, everything) == pytest.approx(-0.3, abs=1e-9)
    # masked, NaN and infinite-σ bins do not count; nothing left to score is NaN
    est, s = truth + (z + 0.5) * std, std.copy()
    est[:10], s[10:20] = np.nan, np.inf
    assert mean_signed_z(est, s, truth, everything) == pytest.approx(0.5 + np.mean(z[20:]), abs=1e-9)
    assert np.isnan(mean_signed_z(est, s, truth, np.zeros(1000, bool)))


def test_the_map_error_is_its_mc_error_where_the_splines_are_exact():
    """Leave-one-out is exact for what the splines reproduce (cubic along α and ln σt, linear along g
    for PCHIP): only the MC std-error is left. A curved map has interpolation error on top."""
    alpha, ls, g = np.linspace(0, 1, 9), np.linspace(-2, 3, 8), np.linspace(0, 0.9, 6)
    A, S, G = np.meshgrid(alpha, ls, g, indexing="ij")
    exact = np.stack([A**3 - S**2 + 0.5 * G, 0.2 * A * S + G], axis=-1)
    mc = np.full(exact.shape, 1e-4)
    np.testing.assert_allclose(node_model_variance(exact, mc, alpha, ls, g), 1e-8, rtol=1e-6)
    curved = exact + np.exp(3 * S)[..., None] * 1e-3
    assert np.all(node_model_variance(curved, mc, alpha, ls, g)[:, 2:-2] > 1e-8 * 1.5)


def test_given_stds_set_the_uncertainty_and_thickness_widens_sigma_t_only():
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.artifacts import load_artifacts

    amap = AppearanceMap.load(DEVICE)
    I_b, I_w, I_c = _materials(amap)
    small = trimeter.fit(amap, I_b, I_w, I_c, I_b_std=1e-4, I_w_std=1e-4, I_c_std=1e-5)
    large = trimeter.fit(amap, I_b, I_w, I_c, I_b_std=4e-3, I_w_std=4e-3, I_c_std=4e-4)
    ok = (small.flags == 0) & (large.flags == 0)
    assert ok.mean() > 0.5
    for name in ("alpha_std", "sigma_t_std", "g_std"):
        assert np.all(getattr(large, name)[ok] > getattr(small, name)[ok]), name
    # the estimate itself does not depend on the stds given (only where the polish stops, to < its tolerance)
    np.testing.assert_allclose(large.alpha[ok], small.alpha[ok], atol=1e-3)
    # a NaN std is the noise model's there; thickness: σt's std grows by σt·std/ℓ in quadrature, α's and g's not
    model = trimeter.fit(amap, I_b, I_w, I_c)
    nan_given = trimeter.fit(amap, I_b, I_w, I_c, I_b_std=np.full(len(I_b), np.nan))
    np.testing.assert_allclose(nan_given.alpha_std, model.alpha_std, rtol=1e-12)
    thick = trimeter.fit(amap, I_b, I_w, I_c, thickness_std_mm=0.02)
    np.testing.assert_allclose(thick.alpha_std, model.alpha_std, rtol=1e-12)
    np.testing.assert_allclose(thick.g_std, model.g_std, rtol=1e-12)
    ell = load_artifacts(amap).setup.thickness_mm  # the fit's one set-up: the table's (f32) ℓ
    expected = np.hypot(model.sigma_t_std, model.sigma_t * 0.02 / ell)
    np.testing.assert_allclose(thick.sigma_t_std, expected, rtol=1e-9)
    # the in-scattering correction's uncertainty reaches σt (and α, g) where the correction moved it
    none = trimeter.fit(amap, I_b, I_w, I_c, inscatter_rel_std=0.0)
    assert np.all(model.sigma_t_std >= none.sigma_t_std)
    assert np.any(model.sigma_t_std > none.sigma_t_std * (1 + 1e-6))


def test_the_maps_own_error_enters_the_stds():
    from trimeter.inversion.kernel import NumpyKernel
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.artifacts import ArtifactCache

    amap = AppearanceMap.load(DEVICE)
    I_b, I_w, I_c = _materials(amap)
    detached = ArtifactCache().get(amap)
    assert detached.grid.model_var is not None
    with_map = trimeter.fit(amap, I_b, I_w, I_c, I_b_std=1e-5, I_w_std=1e-5, I_c_std=1e-6)
    # the numpy path with the map's error detached: the stds of the given noise alone
    detached.grid.attach_model_variance(None, None, None, None)
    noise_only = api.fit(detached, I_b, I_w, I_c, I_b_std=1e-5, I_w_std=1e-5, I_c_std=1e-6, kernel=NumpyKernel())
    ok = (with_map.flags == 0) & (noise_only.flags == 0)
    assert np.median(with_map.alpha_std[ok] / noise_only.alpha_std[ok]) > 1.5  # the interpolation error dominates


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("method", ["lut", "mlp"])
def test_c_and_numpy_agree_with_given_stds_and_thicknesses(monkeypatch, method):
    from trimeter.inversion.kernel import NumpyKernel
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(DEVICE)
    I_b, I_w, I_c = _materials(amap, n=600, seed=4)
    rng = np.random.default_rng(1)
    stds = dict(I_b_std=rng.uniform(1e-4, 5e-3, 600), I_w_std=rng.uniform(1e-4, 5e-3, 600),
                I_c_std=np.where(rng.random(600) < 0.2, np.nan, rng.uniform(1e-5, 1e-3, 600)), thickness_std_mm=0.01)
    compiled = trimeter.fit(amap, I_b, I_w, I_c, method=method, **stds)
    reference = trimeter.fit(amap, I_b, I_w, I_c, method=method, kernel=NumpyKernel(), **stds)
    np.testing.assert_array_equal(compiled.flags, reference.flags)
    for name in ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std"):
        np.testing.assert_allclose(getattr(compiled, name), getattr(reference, name), rtol=1e-6, atol=1e-11,
                                   err_msg=name)
    for name in ("alpha_std", "g_std"):  # the conditioning stds (None: the stds themselves)
        c, r = (getattr(x, f"conditioning_{name}") for x in (compiled, reference))
        c, r = (getattr(x, name) if v is None else v for x, v in ((compiled, c), (reference, r)))
        np.testing.assert_allclose(c, r, rtol=1e-6, atol=1e-11, err_msg=f"conditioning_{name}")


@pytest.mark.parametrize("native_kernel", [True, False])
def test_underdetermined_is_judged_at_no_less_than_the_noise_model(monkeypatch, native_kernel):
    """Dark, optically thick bins (σt·ℓ = 4) with a near-noiseless capture: their reported stds are
    the capture's (small), yet they stay UNDERDETERMINED — that is the map's conditioning at the
    instrument's usual noise; given stds above the noise model are judged as given. One thickness
    and two alike."""
    from trimeter.inversion.flags import FitFlag
    from trimeter.inversion.kernel import NativeKernel, NumpyKernel
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.artifacts import load_artifacts

    kernel = NativeKernel() if native_kernel else NumpyKernel()
    fit = lambda *args, **kw: trimeter.fit(*args, kernel=kernel, **kw)  # noqa: E731
    amap = AppearanceMap.load(DEVICE)
    n = 40
    grid = load_artifacts(amap).grid
    I_b, I_w, I_c = grid.intensities(np.full(n, 0.2), np.full(n, 4 / amap.thickness_mm), np.linspace(0.1, 0.8, n),
                                     *amap.reference_rhos)
    quiet = fit(amap, I_b, I_w, I_c, I_b_std=1e-7, I_w_std=1e-7, I_c_std=1e-7)
    default = fit(amap, I_b, I_w, I_c)
    under = int(FitFlag.UNDERDETERMINED)
    assert np.count_nonzero(default.flags & under) >= n // 2
    np.testing.assert_array_equal(quiet.flags & under, default.flags & under)
    # the capture's own, smaller stds are what is reported (the map's error alone), on some bins below the
    # thresholds: those are the bins the capture alone would have let through
    assert np.median(quiet.alpha_std / default.alpha_std) < 0.5
    hidden = (quiet.flags & under != 0) & (quiet.alpha_std <= finish.UNDERDETERMINED_ALPHA_STD) & ~(
        quiet.g_std > finish.UNDERDETERMINED_G_STD)
    assert hidden.sum() >= 10
    loud = fit(amap, I_b, I_w, I_c, I_b_std=0.05, I_w_std=0.05, I_c_std=0.05)
    assert np.all(loud.flags & under)
    both = fit([amap, amap], np.stack([I_b, I_b]), np.stack([I_w, I_w]), np.stack([I_c, I_c]),
               I_b_std=1e-7, I_w_std=1e-7, I_c_std=1e-7)
    both_default = fit([amap, amap], np.stack([I_b, I_b]), np.stack([I_w, I_w]), np.stack([I_c, I_c]))
    np.testing.assert_array_equal(both.flags & under, both_default.flags & under)


def test_bad_stds_are_clear_errors(tmp_path, capsys):
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(DEVICE)
    with pytest.raises(InputError, match="I_b_std must not be negative"):
        trimeter.fit(amap, [0.2], [0.5], [0.1], I_b_std=[-1e-3])
    with pytest.raises(InputError, match="I_w_std must be"):
        trimeter.fit(amap, [0.2, 0.3], [0.5, 0.6], [0.1, 0.2], I_w_std=[1e-3, 1e-3, 1e-3])
    with pytest.raises(InputError, match="must be finite"):
        trimeter.fit(amap, [0.2], [0.5], [0.1], I_c_std=[np.inf])
    with pytest.raises(InputError, match="one per map"):
        trimeter.fit(amap, [0.2], [0.5], [0.1], thickness_std_mm=[0.01, 0.02])
    with pytest.raises(InputError, match="thickness_std_mm"):
        trimeter.fit(amap, [0.2], [0.5], [0.1], thickness_std_mm=-0.01)
    csv = tmp_path / "m.csv"
    csv.write_text("wavelength_nm,I_b,I_w,I_c,I_b_std\n500,0.2,0.5,0.1,abc\n")
    assert main(["fit", "--map", str(DEVICE), "--input", str(csv)]) == 2
    assert "column I_b_std" in capsys.readouterr().err
    csv.write_text("wavelength_nm,I_b,I_w,I_c,thickness_std_mm\n500,0.2,0.5,0.1,0.01\n510,0.2,0.5,0.1,0.02\n")
    assert main(["fit", "--map", str(DEVICE), "--input", str(csv)]) == 2
    assert "one sample, one std" in capsys.readouterr().err
    for bad in ("nan", "inf", ""):  # a NaN std is refused, never read as an exact thickness (0)
        csv.write_text(f"wavelength_nm,I_b,I_w,I_c,thickness_std_mm\n500,0.2,0.5,0.1,{bad}\n")
        for output in ([], ["--json"]):  # streamed CSV out, and the whole input at once
            assert main(["fit", "--map", str(DEVICE), "--input", str(csv), *output]) == 2
            assert "thickness_std_mm is not a finite number for a sample" in capsys.readouterr().err
    csv.write_text("wavelength_nm,I_b,I_w,I_c,thickness_std_mm\n500,0.2,0.5,0.1,0.01\n510,0.2,0.5,0.1,inf\n")
    assert main(["fit", "--map", str(DEVICE), "--input", str(csv)]) == 2
    assert "not a finite number" in capsys.readouterr().err


def test_the_fit_cli_takes_std_columns(tmp_path, capsys):
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(DEVICE)
    I_b, I_w, I_c = (x[:3] for x in _materials(amap, n=3))
    rows = ["wavelength_nm,I_b,I_w,I_c,I_b_std,I_w_std,I_c_std,thickness_std_mm"]
    rows += [f"{500 + i},{I_b[i]},{I_w[i]},{I_c[i]},0.002,0.002,0.0002,0.01" for i in range(3)]
    csv = tmp_path / "m.csv"
    csv.write_text("\n".join(rows) + "\n")
    assert main(["fit", "--map", str(DEVICE), "--input", str(csv), "--json"]) == 0
    import json

    doc = json.loads(capsys.readouterr().out)
    expected = trimeter.fit(amap, I_b, I_w, I_c, I_b_std=0.002, I_w_std=0.002, I_c_std=0.0002, thickness_std_mm=0.01)
    np.testing.assert_allclose(doc["columns"]["sigma_t_std"], expected.sigma_t_std, rtol=1e-8)


def test_bench_uncertainty_prints_its_table(tmp_path, capsys):
    assert main(["bench", "uncertainty", "--map", str(DEVICE), "--noise", "0.01", "--draws", "1",
                 "--thickness-rel-std", "0", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "device-n1.5-l0.4" in out and "given" in out and "fixed" in out and "UNDERDETERMINED" in out
    assert "mean signed" in out
    import json

    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert all(np.isfinite(r[p]["mean_z"]) for r in rows for p in ("alpha", "sigma_t", "g"))
    assert main(["bench", "uncertainty", "--noise", "2"]) == 2
    assert "--noise" in capsys.readouterr().err


def test_the_held_out_split_keeps_columns_whole_and_parts_apart():
    from trimeter.bench.heldout import CALIBRATION_EVERY, heldout_for, heldout_part
    from trimeter.formats.appearance import AppearanceMap

    _, _, h = heldout_for(AppearanceMap.load(DEVICE))
    cal, scored = heldout_part(h, "calibration"), heldout_part(h, "scored")
    assert len(cal["alpha"]) + len(scored["alpha"]) == len(h["alpha"])
    pairs = {k: {tuple(x) for x in np.column_stack([part["sigma_t"], part["g"]])} for k, part in
             (("cal", cal), ("scored", scored))}
    assert not pairs["cal"] & pairs["scored"]  # a (σt, g) column is in one part only
    all_pairs = len({tuple(x) for x in np.column_stack([h["sigma_t"], h["g"]])})
    assert len(pairs["cal"]) == -(-all_pairs // CALIBRATION_EVERY)
    with pytest.raises(InputError, match="held-out part must be one of scored, calibration"):
        heldout_part(h, "all")


def test_bench_uncertainty_sweeps_the_map_error_scale_on_the_calibration_part(tmp_path, capsys):
    from trimeter.model import grid

    shipped = grid.LEAVE_ONE_OUT_SCALE
    assert main(["bench", "uncertainty", "--map", str(DEVICE), "--noise", "0.002", "--draws", "1",
                 "--thickness-rel-std", "0", "--modes", "given", "--part", "calibration",
                 "--leave-one-out-scale", "0,1", "--out", str(tmp_path)]) == 0
    assert shipped == grid.LEAVE_ONE_OUT_SCALE  # restored
    out = capsys.readouterr().out
    assert "held-out materials (calibration part): device-n1.5-l0.4 80" in out
    assert "LEAVE_ONE_OUT_SCALE 0 " in out and "← nearest" in out
    import json

    sweep = json.loads((tmp_path / "results.json").read_text())["sweep"]
    assert [r["leave_one_out_scale"] for r in sweep] == [0.0, 1.0]
    # a larger scale widens the σ, so more truths fall within them
    assert sweep[1]["rows"][0]["alpha"]["within_1sigma"] > sweep[0]["rows"][0]["alpha"]["within_1sigma"]
    assert main(["bench", "uncertainty", "--leave-one-out-scale", "x"]) == 2


def test_forward_grid_without_model_variance_reports_zero():
    grid = ForwardGrid(np.linspace(0, 1, 3), np.linspace(0, 1, 3), np.linspace(0, 0.9, 3), np.zeros((3, 3, 3, 3)),
                       setup=SampleSetup(1.5, 0.4))
    assert np.all(grid.model_variance(np.array([0.5]), grid.sigma_cell(np.array([1.5])), np.array([0.3])) == 0)


def test_std_approximate_marks_where_first_order_fails():
    """Held-out materials of the device map at 1 % noise: the bins the re-fit check flags are those
    whose truth falls outside ±2σ far more often; those it keeps are near 95 %. Bins whose α and g
    stds are under the check's thresholds are never flagged (they are not checked)."""
    from trimeter.bench.uncertainty import Case
    from trimeter.inversion.finish import STD_CHECK_ALPHA, STD_CHECK_G
    from trimeter.inversion.flags import FitFlag
    from trimeter.formats.appearance import AppearanceMap

    case = Case(AppearanceMap.load(DEVICE), draws=4)
    (I_b, I_w, I_c), (sb, sw, sc) = case.draw(0.01, np.random.default_rng(5))
    r = trimeter.fit(case.amap, I_b, I_w, I_c, I_b_std=sb, I_w_std=sw, I_c_std=sc)
    approx = (r.flags & int(FitFlag.STD_APPROXIMATE)) != 0
    flagged, kept = approx & ((r.flags & ~int(FitFlag.STD_APPROXIMATE)) == 0), r.flags == 0
    assert flagged.sum() > 50 and kept.sum() > 400
    z = np.abs(r.g - case.truth["g"]) / r.g_std
    assert np.mean(z[flagged] <= 2) < np.mean(z[kept] <= 2) - 0.05
    assert np.mean(z[kept] <= 2) > 0.9
    assert not np.any(approx & (r.alpha_std <= STD_CHECK_ALPHA) & (r.g_std <= STD_CHECK_G))
