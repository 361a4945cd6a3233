"""The compiled kernel (trimeter.inversion.native, its C sources) against the numpy kernel it mirrors:
same initial guess, Newton polish, residual, Jacobian and propagated uncertainty, to rounding, on
random and edge inputs. `make test` builds the library first, so here it must be available."""

import os

import numpy as np
import pytest

import trimeter
from trimeter.inversion import native
from trimeter.inversion.kernel import NativeKernel, NumpyKernel
from trimeter.inversion.lut import TableInverter
from trimeter.inversion.artifacts import load_artifacts
from trimeter.formats.device_table import DeviceTable
from trimeter.model.grid import ForwardGrid
from trimeter.paths import MAPS_DIR

TABLE = MAPS_DIR / "device-n1.5-l0.4.tlut"


def test_the_library_is_built_and_loads():
    if os.environ.get("TRIMETER_NATIVE") == "0":
        pytest.skip("TRIMETER_NATIVE=0: the numpy kernel is what runs")
    assert native.available(), native.status()


def _inputs(rng, n=4000):
    I_b = rng.uniform(0.0, 0.6, n)
    I_w = I_b + rng.uniform(0.0, 0.9, n)
    sigma_t = np.exp(rng.uniform(np.log(0.02), np.log(80.0), n))  # past both ends of the grid
    rho_b = rng.uniform(0.0, 0.1, n)
    rho_w = rng.uniform(0.8, 1.0, n)
    # edges: NaN and infinite σt, σt = 0, intensities at and beyond [0, 1]
    sigma_t[:6] = [np.nan, np.inf, 0.0, 1e-300, 1e300, 0.05]
    I_b[6:10], I_w[6:10] = [0.0, 1.0, -0.5, 2.0], [0.0, 1.0, 3.0, -1.0]
    # non-finite intensities (fit() flags them first; the solver itself must still not crash on them)
    I_b[10:13], I_w[10:13] = [np.nan, np.inf, -np.inf], [0.5, np.nan, np.inf]
    return I_b, I_w, sigma_t, rho_b, rho_w


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("polish", [0, 1, 4])
def test_table_inversion_matches_the_numpy_kernel(monkeypatch, polish):
    table = DeviceTable.load(TABLE)
    args = _inputs(np.random.default_rng(polish))
    compiled = NativeKernel().invert(TableInverter(table), *args, iterations=polish)
    expected = NumpyKernel().invert(TableInverter(table), *args, iterations=polish)
    for got, want, name in zip(compiled, expected, ("alpha", "g", "residual", "J"), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12, err_msg=name)
    finite = np.isfinite(args[0]) & np.isfinite(args[1])
    assert np.all(np.isfinite(compiled[0][finite])) and np.all(np.isfinite(compiled[1][finite]))


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_polish_from_a_given_guess_and_the_propagated_uncertainty_match(monkeypatch):
    table = DeviceTable.load(TABLE)
    rng = np.random.default_rng(7)
    I_b, I_w, sigma_t, rho_b, rho_w = _inputs(rng)
    alpha0, g0 = rng.uniform(-0.2, 1.2, len(I_b)), rng.uniform(-0.5, 1.5, len(I_b))
    sigma_I = rng.uniform(0.0, 0.01, (len(I_b), 3))
    grid = ForwardGrid.from_table(table)
    cell = grid.sigma_cell(sigma_t)
    compiled = NativeKernel().solve_alpha_g(grid, I_b, I_w, cell, rho_b, rho_w, alpha0, g0, iterations=3)
    compiled_std = NativeKernel().propagate(compiled[3], sigma_I)
    reference = NumpyKernel()
    expected = reference.solve_alpha_g(grid, I_b, I_w, cell, rho_b, rho_w, alpha0, g0, iterations=3)
    for got, want in zip(compiled, expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    expected_std = reference.propagate(expected[3], sigma_I)
    # the two evaluate J2⁻¹ Σ J2⁻ᵀ in a different order: where J2 is near-singular (stds ~1e5) its
    # condition number amplifies the rounding difference, hence 1e-5 rather than 1e-9
    for got, want in zip(compiled_std, expected_std, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-12)


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_the_stds_from_the_converging_step_are_those_at_the_solution():
    """fit() takes a converged bin's Jacobian from its last Newton evaluation, a step below κ of the
    noise std before the solution and in the same cell: its stds must be those evaluated at the
    solution itself, to a small fraction (measured: ≤ 0.4 % for α, ≤ 0.7 % for g here, ≤ 1.2 % on
    l0.8; a last step that crossed a cell boundary, where the map's derivatives jump, had moved an
    ill-conditioned bin's std by up to 50 %, hence the same-cell rule)."""
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    # without its in-scattering table: that correction moves σt after the Jacobian (first order: the
    # σt row stays right for the measured I_c, not for the unscattered one the reference below uses)
    amap.__dict__["inscatter"] = None
    rng = np.random.default_rng(5)
    n = 2000
    alpha, g = rng.uniform(0.3, 0.99, n), rng.uniform(0.0, 0.85, n)
    sigma_t = np.exp(rng.uniform(np.log(0.2), np.log(10), n))
    grid = load_artifacts(amap).grid
    I_b, I_w, I_c = grid.intensities(alpha, sigma_t, g, 0.02, 0.9)
    r = trimeter.fit(amap, I_b, I_w, I_c, 0.02, 0.9)
    ok = r.flags == 0
    assert ok.mean() > 0.8
    J = grid.jacobian(r.alpha[ok], r.sigma_t[ok], r.g[ok], 0.02, 0.9)
    noise = lambda x: 0.005 * x + 2e-4  # noqa: E731  (fit()'s default noise model)
    model = grid.model_variance(r.alpha[ok], grid.sigma_cell(r.sigma_t[ok]), r.g[ok])  # the map's own error
    sigma_I = np.column_stack([np.sqrt(noise(I_b[ok]) ** 2 + model[0]), np.sqrt(noise(I_w[ok]) ** 2 + model[1]),
                               noise(I_c[ok])])
    std_a, std_s, std_g = NativeKernel().propagate(J, sigma_I)
    np.testing.assert_allclose(r.alpha_std[ok], std_a, rtol=0.02)
    np.testing.assert_allclose(r.sigma_t_std[ok], std_s, rtol=1e-9)
    np.testing.assert_allclose(r.g_std[ok], std_g, rtol=0.02)


def _fit_inputs(rng, n=4000):
    """Measurements over the whole input space: inside the gamut, at and past every validity edge."""
    I_b = rng.uniform(0.0, 0.6, n)
    I_w = I_b + rng.uniform(0.0, 0.9, n)
    I_c = np.exp(rng.uniform(np.log(1e-6), np.log(0.95), n))
    rho_b = rng.uniform(0.0, 0.1, n)
    rho_w = rng.uniform(0.8, 1.0, n)
    edges = {"I_b": [np.nan, np.inf, -0.5, 1.5, 0.4, 0.0, 1e-310, 0.2, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1, 0.1, -5e-4],
             "I_w": [0.5, 0.5, 0.5, 0.5, 0.3, 0.0, 1e-300, -np.inf, 0.5, 0.5, 0.5, 0.6, 0.6, 0.6, 1.0005, 0.3],
             "I_c": [0.1, 0.1, 0.1, 0.1, 0.1, 0.0, 1.0, 0.1, np.nan, 1e-9, 0.99, 1.0005, -0.01, 1.01, 0.3, -5e-4],
             "rho_b": [0.02] * 8 + [0.02, 0.5, -0.1, 0.02, 0.02, 0.02, 0.02, 0.02],
             "rho_w": [0.9] * 8 + [0.9, 0.4, 0.9, 1.2, 0.9, 0.9, 0.9, 0.9]}
    k = len(edges["I_b"])
    for name, values in edges.items():
        locals()[name][:k] = values
    return I_b, I_w, I_c, rho_b, rho_w


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("method, polish, polish_tol", [("lut", 0, 0.0), ("lut", 8, 1e-6), ("lut", 3, 0.0),
                                                         ("mlp", 8, 1e-6)])
def test_the_whole_fit_in_c_matches_the_numpy_reference_bin_for_bin(monkeypatch, method, polish, polish_tol):
    """tm_fit (flags, σt from I_c, guess, adaptive polish, stds, blanking) against api's numpy path."""
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    assert amap.inscatter is not None  # so the in-scattering correction is compared too
    args = _fit_inputs(np.random.default_rng(polish))
    kw = dict(method=method, polish=polish, polish_tol=polish_tol)
    compiled = trimeter.fit(amap, *args[:3], rho_b=args[3], rho_w=args[4], kernel=NativeKernel(), **kw)
    reference = trimeter.fit(amap, *args[:3], rho_b=args[3], rho_w=args[4], kernel=NumpyKernel(), **kw)
    np.testing.assert_array_equal(compiled.flags, reference.flags)
    for name in FitResultColumns:
        # The stds come from the polish's last evaluation, a small step before the solution, so they
        # keep a trace of the path there. On the worst-conditioned bins (I_c under the floor: thick,
        # α and g barely determined) C's and numpy's rounding, ~1e-16 apart, grows to ~1e-10 in
        # (α, g) along the path, and to ~1e-7 in those stds (measured: 8 of 4000 bins, mlp).
        rtol = 1e-6 if name.endswith("_std") else 1e-8
        np.testing.assert_allclose(getattr(compiled, name), getattr(reference, name), rtol=rtol, atol=1e-11,
                                   err_msg=name)
    # the edges took every validity branch, and most bins are clean fits
    from trimeter.inversion.flags import FitFlag

    seen = np.bitwise_or.reduce(compiled.flags)
    # (the band flags belong to the band-aware fit and to multichannel sensors, not to a per-wavelength fit)
    for flag in FitFlag:
        if flag not in (FitFlag.NONE, FitFlag.THICKNESS_DISAGREE, FitFlag.BAND_UNRESOLVED, FitFlag.PER_CHANNEL_BANDS):
            assert seen & flag, flag.name


FitResultColumns = ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "sigma_t_beer")


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("method, own_stds", [("lut", False), ("mlp", False), ("lut", True)])
def test_four_bins_per_step_give_bit_for_bit_the_scalar_result(method, own_stds):
    """The AVX2 steps (the polish, the finish's arithmetic, the σ check: four bins at once) against the
    scalar loops, over the whole input space with its edges: every column identical, not merely close.
    With the intensities' own stds (some below the noise model, some above, some NaN), the conditioning
    stds take their own propagation."""
    from trimeter.formats.appearance import AppearanceMap

    if not native.set_simd(True):
        pytest.skip("this CPU has no AVX2: only the scalar loop runs")
    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.8.tmap")
    rng = np.random.default_rng(11)
    args = _fit_inputs(rng, n=4001)  # not a multiple of 4: the scalar tail too
    stds = {}
    if own_stds:
        for name in ("I_b_std", "I_w_std", "I_c_std"):
            sd = rng.uniform(0.0, 0.02, len(args[0]))
            sd[rng.random(len(sd)) < 0.1] = np.nan  # the noise model's there
            stds[name] = sd
    try:
        results = {}
        for simd in (True, False):
            native.set_simd(simd)
            results[simd] = trimeter.fit(amap, *args[:3], rho_b=args[3], rho_w=args[4], method=method, **stds)
            inverter = load_artifacts(amap).inverter
            results[simd, "solve"] = NativeKernel().invert(inverter, args[0], args[1], np.exp(args[2] * 3), args[3],
                                                           args[4], iterations=8, step_tol=1e-6,
                                                           step_var=np.full(len(args[0]), 1e-9))
    finally:
        native.set_simd(True)
    columns = FitResultColumns + ("flags",) + (("conditioning_alpha_std", "conditioning_g_std") if own_stds else ())
    for name in columns:
        np.testing.assert_array_equal(getattr(results[True], name), getattr(results[False], name), err_msg=name)
    for a, b in zip(results[True, "solve"], results[False, "solve"], strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_the_adaptive_polish_stops_converged_bins_early_with_the_same_result():
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    rng = np.random.default_rng(3)
    alpha, g = rng.uniform(0.3, 0.99, 2000), rng.uniform(0.0, 0.85, 2000)
    sigma_t = np.exp(rng.uniform(np.log(0.1), np.log(20), 2000))
    inverter = load_artifacts(amap).inverter
    solver = native.NativeSolver(inverter.grid, *inverter.inverse_cells)
    I_b, I_w, I_c = inverter.grid.intensities(alpha, sigma_t, g, 0.02, 0.9)  # I_c with in-scattered light
    rho_b, rho_w = np.full(2000, 0.02), np.full(2000, 0.9)
    fixed = NativeKernel().invert(inverter, I_b, I_w, sigma_t, rho_b, rho_w, iterations=12, step_tol=0.0)
    adaptive = NativeKernel().invert(inverter, I_b, I_w, sigma_t, rho_b, rho_w, iterations=12, step_tol=1e-6)
    np.testing.assert_allclose(adaptive[0], fixed[0], atol=1e-5)  # a step ≤ 1e-6 leaves at most a few of it
    np.testing.assert_allclose(adaptive[1], fixed[1], atol=1e-5)
    from trimeter.inversion.api import native_options

    options = native_options(amap, inverter.grid, polish=12, polish_tol=1e-6, noise_rel=0.005, noise_abs=2e-4,
                             ic_floor=1e-4, alpha_min_g=0.02)
    out = solver.fit(I_b, I_w, I_c, rho_b, rho_w, **options)
    # fit() also stops a bin once its step is below POLISH_TOL_STD (3e-3) of its noise std, or has
    # shrunk 4× with the next one extrapolated below that (newton.step_is_small): far fewer steps
    # than 12 per bin, and the result within a small fraction of that std of the fully converged one
    # (measured: ≤ 0.006 std at 2.6 steps per bin, 4.1 without the std rule; thick, underdetermined
    # bins converge slowly and differ most)
    assert 1.0 < out["steps"] / 2000 < 4.0
    assert np.all(np.abs(out["alpha"] - np.clip(fixed[0], 0, 1)) <= np.maximum(0.05 * out["alpha_std"], 1e-5))
    defined = np.isfinite(out["g"])
    assert np.all(np.abs(out["g"] - fixed[1])[defined] <= np.maximum(0.05 * out["g_std"], 1e-5)[defined])
    steps_without = solver.fit(I_b, I_w, I_c, rho_b, rho_w, **dict(options, step_tol_std=0.0))["steps"]
    assert out["steps"] < 0.85 * steps_without


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_the_mlp_features_from_c_match_the_numpy_preparation():
    """tm_fit_prepare's features (the network input from the sanitized I_b, I_w, ρ's and σt) against
    mlp.features of api._prepare, on inputs with every kind of bad value."""
    import trimeter.inversion.api as api
    from trimeter.inversion.mlp import features
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    args = _fit_inputs(np.random.default_rng(11))
    inverter = load_artifacts(amap).inverter
    grid = inverter.grid
    log_range = (float(np.log(amap.sigma_t[0])), float(np.log(amap.sigma_t[-1])))
    seen = []

    def guess(x):
        seen.append(x.copy())
        return np.column_stack([np.full(len(x), 0.5), np.full(len(x), 0.3)])

    options = api.native_options(amap, grid, polish=0, polish_tol=0.0, noise_rel=0.005, noise_abs=2e-4, ic_floor=1e-4,
                                 alpha_min_g=0.02)
    compiled = native.NativeSolver(grid, *inverter.inverse_cells).fit_guessed(*args, guess, log_range, **options)
    assert len(seen) == 1 and np.array_equal(seen[0], compiled["features"])
    compiled = compiled["features"]
    p = api._prepare(amap, grid, *args, 1e-4)
    want = features(p.ib, p.iw, p.sigma_t, p.rb, p.rw, log_range)
    assert compiled.dtype == np.float32 and compiled.shape == want.shape
    np.testing.assert_allclose(compiled, want, rtol=2e-7, atol=0)  # float32: one rounding step apart at most


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_a_guess_of_the_wrong_shape_is_refused():
    import trimeter.inversion.api as api
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    inverter = load_artifacts(amap).inverter
    args = _fit_inputs(np.random.default_rng(2))
    options = api.native_options(amap, inverter.grid, polish=2, polish_tol=1e-6, noise_rel=0.005, noise_abs=2e-4,
                                 ic_floor=1e-4, alpha_min_g=0.02)
    with pytest.raises(ValueError, match="guess must be"):
        native.NativeSolver(inverter.grid, *inverter.inverse_cells).fit_guessed(*args, lambda x: x[:, :1], (-3.0, 4.0),
                                                                                 **options)


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_a_guess_that_is_not_finite_falls_back_to_the_table():
    """A broken network (NaN or inf out) costs nothing but its guess: those bins start from the
    table's, so they come out exactly as the lut fit's; the other bins keep the network's guess."""
    import trimeter.inversion.api as api
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    inverter = load_artifacts(amap).inverter
    solver = native.NativeSolver(inverter.grid, *inverter.inverse_cells)
    args = _fit_inputs(np.random.default_rng(4))
    n = len(args[0])
    options = api.native_options(amap, inverter.grid, polish=8, polish_tol=1e-6, noise_rel=0.005, noise_abs=2e-4,
                                 ic_floor=1e-4, alpha_min_g=0.02)
    bad = np.arange(n) % 3 == 0

    def broken(x):
        y = np.column_stack([np.full(n, 0.7), np.full(n, 0.4)])
        y[bad, 0] = np.nan
        y[bad & (np.arange(n) % 2 == 0), 1] = np.inf
        return y

    guessed = solver.fit_guessed(*args, broken, (-3.0, 4.0), **options)
    lut = solver.fit(*args, **options)
    for name in ("alpha", "sigma_t", "g", "alpha_std", "g_std", "flags"):
        np.testing.assert_array_equal(guessed[name][bad], lut[name][bad], err_msg=name)
    assert np.all(np.isfinite(guessed["alpha"][~bad]) | (guessed["flags"][~bad] != 0))


@pytest.mark.parametrize("shape", [(5, 7, 3), (1,), (4, 24)])
def test_the_tables_handed_to_c_start_on_a_cache_line_and_hold_the_same_values(shape):
    """A forward cell's 24 coefficients are 3 cache lines: aligned, the 3 the kernel prefetches are all of it."""
    values = np.random.default_rng(1).standard_normal(shape)[..., ::-1]  # not contiguous either
    copy = native._cache_aligned(values)
    assert copy.ctypes.data % native.CACHE_LINE == 0 and copy.flags.c_contiguous
    assert copy.shape == values.shape and np.array_equal(copy, values)


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_a_bin_held_at_the_box_s_edge_ends_at_the_best_alpha_along_it_in_every_implementation():
    """newton.hold_at_edges: where g's step points out of the box at its edge, g is held and α takes a
    step of its own, so such a bin ends at the α that fits best along the edge (the unprojected 2×2
    step, clamped, only crawled there: up to half the residual left); numpy, C and C four bins wide
    agree on those bins as on the rest."""
    table = DeviceTable.load(TABLE)
    grid = ForwardGrid.from_table(table)
    rng = np.random.default_rng(5)
    n = 4000
    I_b = rng.uniform(0.0, 0.6, n)
    I_w = I_b + rng.uniform(0.0, 0.9, n)
    sigma_t = np.exp(rng.uniform(np.log(0.2), np.log(20.0), n))
    rho_b, rho_w = np.full(n, 0.02), np.full(n, 0.95)
    cell = grid.sigma_cell(sigma_t)
    start = (np.full(n, 0.7), np.full(n, 0.5))
    alpha, g, _, _ = expected = NumpyKernel().solve_alpha_g(grid, I_b, I_w, cell, rho_b, rho_w, *start,
                                                            iterations=12, step_tol=1e-12)
    (a_lo, a_hi), (g_lo, g_hi) = grid.alpha_range, grid.g_range
    edge = ((g == g_lo) | (g == g_hi)) & (alpha > a_lo + 0.02) & (alpha < a_hi - 0.02)
    assert edge.sum() > n // 10  # random intensities: many solutions lie past the map's g range

    def residual(a):
        return grid.residual_and_jacobian(I_b, I_w, cell, rho_b, rho_w, np.clip(a, a_lo, a_hi), g)[0][edge]

    at, best_neighbour = residual(alpha), np.minimum(residual(alpha + 1e-4), residual(alpha - 1e-4))
    assert np.all(best_neighbour >= at * (1 - 1e-3))
    try:
        for simd in (False, True):
            native.set_simd(simd)
            compiled = NativeKernel().solve_alpha_g(grid, I_b, I_w, cell, rho_b, rho_w, *start, iterations=12,
                                                    step_tol=1e-12)
            for got, want in zip(compiled, expected, strict=True):
                np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    finally:
        native.set_simd(True)


def _walk_steps(axis: np.ndarray, x: np.ndarray) -> np.ndarray:
    """How many cells the C side's walk takes from the cell index's start to x's cell (find_cell's)."""
    index, scale = native._cell_index(axis)
    t = (x - axis[0]) * scale
    bucket = np.where(t >= 1.0, np.minimum(np.where(np.isfinite(t), t, len(index) - 1), len(index) - 1), 0)
    start = index[bucket.astype(np.int64)].astype(np.int64)
    cell = np.clip(np.searchsorted(axis, x, side="right") - 1, 0, len(axis) - 2)
    return np.abs(cell - start)


@pytest.mark.parametrize("name", ["device-n1.5-l0.4", "ideal-n1.5-l0.5"])
def test_the_axes_cell_index_starts_each_search_a_step_or_two_from_the_cell(name):
    """native._cell_index: each bucket holds the cell of its start, so that the walk from it is short on
    the shipped maps' uneven α and g axes (refined near α = 1): at most two cells for any point."""
    grid = load_artifacts(MAPS_DIR / f"{name}.tmap").inverter.grid
    rng = np.random.default_rng(5)
    for axis in (np.asarray(grid.alpha, dtype=np.float64), np.asarray(grid.g, dtype=np.float64)):
        index, scale = native._cell_index(axis)
        assert index is not None and index.dtype == np.uint16 and len(index) <= native.CELL_INDEX_MAX
        starts = axis[0] + np.arange(len(index)) / scale
        assert np.all((axis[index] <= starts) | (index == 0)) and np.all(index <= len(axis) - 2)
        x = np.concatenate([rng.uniform(axis[0] - 0.1, axis[-1] + 0.1, 100_000), axis, np.nextafter(axis, -np.inf),
                            [-np.inf, np.inf]])
        assert _walk_steps(axis, x).max() <= 2
    assert native._cell_index(np.array([0.0, 1.0, 2.0])) == (None, 0.0)  # too short to be worth one


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("name", ["device-n1.5-l0.8", "ideal-n1.5-l0.5"])
def test_the_axes_cell_index_changes_no_result(name):
    """The α and g cells found through the axes' index (tm_forward_grid.alpha_index) against a binary
    search (no index): the whole fit, with its edges, bit for bit."""
    from trimeter.inversion.api import native_options

    artifacts = load_artifacts(MAPS_DIR / f"{name}.tmap")
    inverter = artifacts.inverter
    options = native_options(artifacts, inverter.grid, polish=8, polish_tol=1e-6, noise_rel=0.005, noise_abs=2e-4,
                             ic_floor=1e-4, alpha_min_g=0.02)
    indexed, searched = (native.NativeSolver(inverter.grid, *inverter.inverse_cells) for _ in range(2))
    assert indexed._grid.alpha_index and indexed._grid.g_index
    searched._grid.alpha_index = searched._grid.g_index = None
    args = _fit_inputs(np.random.default_rng(12), n=4001)
    results = [solver.fit(*args, **options) for solver in (indexed, searched)]
    for column in FitResultColumns + ("flags",):
        np.testing.assert_array_equal(results[0][column], results[1][column], err_msg=column)
    assert results[0]["steps"] == results[1]["steps"]
