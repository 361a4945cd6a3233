"""The thicknesses' combination in C (tm_combine through NativeKernel.combine) against finish.combine, the
numpy reference it mirrors: the same columns and flags bit for bit, on random fits with NaN, ±inf and
zero values and stds, any flag bits, with and without conditioning stds, one to four thicknesses."""

import dataclasses
import os

import numpy as np
import pytest

from trimeter.domain.parameters import FitResult
from trimeter.inversion import api, finish, native
from trimeter.inversion.flags import FitFlag
from trimeter.inversion.kernel import NativeKernel, NumpyKernel

THRESHOLDS = dict(underdetermined_std=(finish.UNDERDETERMINED_ALPHA_STD, finish.UNDERDETERMINED_G_STD),
                  disagree_sigmas=finish.DISAGREE_SIGMAS)


def _random_fit(rng, n, bad=1.0):
    """bad: scales the share of NaN, ±inf and zero cells (1: a quarter of each column)."""
    columns = {name: rng.normal(size=n) * rng.choice([1e-3, 1.0], size=n)
               for name in ("alpha", "sigma_t", "g", "sigma_t_beer")}
    for name in ("alpha_std", "sigma_t_std", "g_std"):
        columns[name] = np.abs(rng.normal(size=n)) * rng.choice([1e-3, 0.05, 1.0, 1e200], size=n)
    for name, column in columns.items():
        u = rng.random(n)
        zero = 0.0 if name.endswith("_std") else -0.0  # a std is never -0 (a square root's)
        columns[name] = np.select([u < 0.1 * bad, u < 0.15 * bad, u < 0.2 * bad, u < 0.22 * bad, u < 0.25 * bad],
                                  [np.nan, np.inf, 0.0, -np.inf, zero], column)
    u = rng.random()
    conditioning = {} if u < 0.5 else {"conditioning_alpha_std": np.abs(rng.normal(size=n)) * 0.2,
                                       "conditioning_g_std": None if u < 0.75 else np.abs(rng.normal(size=n))}
    flags = rng.integers(0, 1 << 12, size=n).astype(np.int64)
    return FitResult(**columns, flags=flags, method="x", **conditioning)


def _assert_identical(a: FitResult, b: FitResult):
    for field in dataclasses.fields(FitResult):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if field.name == "per_thickness":
            assert len(x) == len(y)
            for one, other in zip(x, y, strict=True):
                _assert_identical(one, other)
        elif x is None or isinstance(x, (str, int)):
            assert x == y
        else:
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), field.name


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_c_combination_is_the_numpy_one_bit_for_bit():
    rng = np.random.default_rng(3)
    kernel = NativeKernel()
    seen = 0
    for _ in range(300):
        k, n = int(rng.integers(1, 5)), int(rng.integers(1, 50))
        fits = [_random_fit(rng, n) for _ in range(k)]
        with np.errstate(all="ignore"):
            expected = finish.combine(fits, "x")
            got = kernel.combine(fits, "x", **THRESHOLDS)
        _assert_identical(got, expected)
        seen |= np.bitwise_or.reduce(expected.flags)
    # the random cases reach every flag the combination sets or clears
    for flag in (FitFlag.THICKNESS_DISAGREE, FitFlag.UNDERDETERMINED, FitFlag.STD_APPROXIMATE):
        assert seen & int(flag)


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("simd", [True, False])
def test_two_mostly_clean_thicknesses_combine_bit_for_bit(simd):
    """Two thicknesses with few bad cells: most bins take the four-lane path (every weight sum positive), a
    few the scalar one, with and without AVX2; stds scaled so that the quarter-weight rule and the
    disagreement go both ways."""
    rng = np.random.default_rng(5)
    kernel = NativeKernel()
    try:
        native.set_simd(simd)
        for _ in range(40):
            n = int(rng.integers(1, 200))
            fits = [_random_fit(rng, n, bad=0.05) for _ in range(2)]
            fits[1].alpha_std[:] = fits[0].alpha_std * rng.uniform(0.3, 3.0, n)  # weights within ×10
            with np.errstate(all="ignore"):
                _assert_identical(kernel.combine(fits, "x", **THRESHOLDS), finish.combine(fits, "x"))
    finally:
        native.set_simd(True)


def test_the_numpy_kernel_leaves_the_combination_to_api():
    assert NumpyKernel().combine([], "x", **THRESHOLDS) is None


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("sd", [None, 2e-3])
def test_thicknesses_fitted_into_one_block_combine_as_gathered_ones(ideal_map, thick_map, sd):
    """fit() writes each thickness's fused fit into its place of one (k, rows, n) block and combines
    that block as it is: the same result, bit for bit, as each thickness fitted alone and combined
    from its columns (with and without the intensities' own stds, i.e. conditioning rows)."""
    from trimeter.inversion.artifacts import load_artifacts

    rng = np.random.default_rng(8)
    n = 301
    alpha, g = rng.uniform(0.3, 0.99, n), rng.uniform(0, 0.9, n)
    sigma_t = np.exp(rng.uniform(np.log(0.5), np.log(15.0), n))
    models = [load_artifacts(m) for m in (ideal_map, thick_map)]
    I = [np.stack(x) for x in zip(*(m.grid.intensities(alpha, sigma_t, g, *m.reference_rhos) for m in models),
                                 strict=True)]
    stds = {} if sd is None else dict(I_b_std=sd, I_w_std=sd, I_c_std=sd)
    kernel = NativeKernel()
    together = api.fit(models, *I, method="lut", kernel=kernel, **stds)
    assert together.per_thickness[0].alpha.base is together.per_thickness[1].alpha.base  # one block
    alone = [api.fit(m, *(x[i] for x in I), method="lut", kernel=kernel,
                     **{key: np.full(n, v) for key, v in stds.items()}) for i, m in enumerate(models)]
    gathered = kernel.combine(alone, "lut", **THRESHOLDS)
    gathered.guess_fallback_bins = 0
    _assert_identical(together, gathered)


class _PerThickness(NativeKernel):
    """The native kernel without its one-call path for several thicknesses: fit() then fits each
    thickness on its own (fused_fit into output_blocks) and combines them (combine), as it did before
    tm_fit_thicknesses."""

    def fit_thicknesses(self, *args, **kwargs):
        return None


def _device_pair_inputs(rng, n):
    """The shipped device maps at 0.4 and 0.8 mm (in-scattering and model-error tables both) and their
    intensities of random materials, with bad bins of every kind in some places and per-bin backgrounds."""
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.artifacts import load_artifacts
    from trimeter.paths import MAPS_DIR

    models = [load_artifacts(AppearanceMap.load(MAPS_DIR / f"device-n1.5-l{ell}.tmap")) for ell in ("0.4", "0.8")]
    alpha, g = rng.uniform(0.05, 0.999, n), rng.uniform(-0.2, 0.95, n)
    sigma_t = np.exp(rng.uniform(np.log(0.05), np.log(40.0), n))
    rho_b = rng.uniform(0.0, 0.1, n)
    rho_w = rng.uniform(0.6, 0.95, n)
    I = [np.stack(x) for x in zip(*(m.grid.intensities(alpha, sigma_t, g, rho_b, rho_w) for m in models), strict=True)]
    I = [x * (1 + 0.01 * rng.normal(size=x.shape)) for x in I]
    I[0][0, :7] = [np.nan, -0.5, 1.5, 0.9, np.inf, 0.0, 1e-6]  # unusable, black not below white, dark
    I[2][1, 7:10] = [0.0, 1e-7, np.nan]  # I_c under the floor, missing
    return models, I, np.stack([rho_b, rho_w])


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("options", [{}, dict(I_b_std=1e-3, I_w_std=np.linspace(5e-4, 3e-3, 999), I_c_std=np.nan),
                                     dict(thickness_std_mm=[0.01, 0.03], polish=3, polish_tol=0.0)])
def test_thicknesses_fitted_in_one_call_are_the_per_thickness_fits_combined(options):
    """tm_fit_thicknesses (every thickness's fit and their combination in one C call) against each
    thickness fitted on its own and combined after, the path it replaced (and the one a guesser's
    method still takes): every column of the combined result and of each thickness's, bit for bit."""
    models, I, rho = _device_pair_inputs(np.random.default_rng(21), n=999)
    kw = dict(rho_b=rho[0], rho_w=rho[1], method="lut", **options)
    together = api.fit(models, *I, kernel=NativeKernel(), **kw)
    apart = api.fit(models, *I, kernel=_PerThickness(), **kw)
    _assert_identical(together, apart)
    assert together.per_thickness[0].alpha.base is together.per_thickness[1].alpha.base  # one block
    assert np.isfinite(together.alpha).mean() > 0.9 and (together.flags != 0).any()  # a fit, and bad bins in it


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_three_thicknesses_in_one_call_are_the_per_thickness_fits_combined(ideal_map, thick_map):
    """k = 3 (tm_combine's general loop, not the one unrolled for two)."""
    from trimeter.inversion.artifacts import load_artifacts

    rng = np.random.default_rng(4)
    n = 203
    alpha, g = rng.uniform(0.3, 0.99, n), rng.uniform(0, 0.9, n)
    sigma_t = np.exp(rng.uniform(np.log(0.5), np.log(15.0), n))
    models = [load_artifacts(m) for m in (ideal_map, thick_map, ideal_map)]
    I = [np.stack(x) for x in zip(*(m.grid.intensities(alpha, sigma_t, g, *m.reference_rhos) for m in models),
                                 strict=True)]
    I[1][2] *= 1.5  # the third thickness disagrees with the others
    together = api.fit(models, *I, method="lut", kernel=NativeKernel())
    _assert_identical(together, api.fit(models, *I, method="lut", kernel=_PerThickness()))
    assert (together.flags & int(FitFlag.THICKNESS_DISAGREE)).any()


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("options", [{}, dict(I_b_std=2e-3, I_w_std=1e-3, I_c_std=np.nan, thickness_std_mm=0.02)])
def test_thicknesses_fitted_in_threads_are_those_fitted_one_after_the_other(options):
    """The thicknesses' bins in parts shared out between threads (three thicknesses of 777 bins: runs of parts
    that end inside a thickness with two threads, a thickness each with three, more threads than thicknesses
    with eight): every column bit for bit as in one thread."""
    models, I, rho = _device_pair_inputs(np.random.default_rng(5), n=777)
    models, I = [*models, models[0]], [np.concatenate([x, x[:1] * 1.01]) for x in I]
    kw = dict(rho_b=rho[0], rho_w=rho[1], method="lut", **options)
    alone = api.fit(models, *I, kernel=NativeKernel(threads=1), **kw)
    for threads in (2, 3, 8):
        _assert_identical(alone, api.fit(models, *I, kernel=NativeKernel(threads=threads), **kw))
    assert np.isfinite(alone.alpha).mean() > 0.9 and (alone.flags != 0).any()


_FORKED_CASE: dict = {}  # what a forked child fits: inherited with the parent's memory, nothing sent to it


def _fit_in_a_forked_child():
    """The threaded fit's columns, in a child forked after the parent's helper threads were started (they
    are not in the child: its fit must start its own, not wait for the parent's forever)."""
    models, I, kw = _FORKED_CASE["case"]
    together = api.fit(models, *I, kernel=NativeKernel(threads=2), **kw)
    return together.alpha.tobytes() + together.g_std.tobytes() + together.flags.tobytes()


@pytest.mark.skipif(not native.available() or not hasattr(os, "fork"), reason="needs the native kernel and fork()")
def test_threads_kept_between_fits_serve_concurrent_callers_and_a_forked_child():
    """The helper threads outlive a call: fits from several threads at once (some find every helper busy
    and fit alone) and from a child forked after the helpers started all give the one-thread columns."""
    import multiprocessing
    from concurrent.futures import ThreadPoolExecutor

    models, I, rho = _device_pair_inputs(np.random.default_rng(9), n=600)
    kw = dict(rho_b=rho[0], rho_w=rho[1], method="lut")
    alone = api.fit(models, *I, kernel=NativeKernel(threads=1), **kw)
    threaded = NativeKernel(threads=2)
    with ThreadPoolExecutor(max_workers=12) as pool:
        results = list(pool.map(lambda _: api.fit(models, *I, kernel=threaded, **kw), range(24)))
    for result in results:
        _assert_identical(alone, result)
    expected = alone.alpha.tobytes() + alone.g_std.tobytes() + alone.flags.tobytes()
    _FORKED_CASE["case"] = (models, I, kw)
    try:
        with multiprocessing.get_context("fork").Pool(1) as child:
            assert child.apply_async(_fit_in_a_forked_child).get(timeout=60) == expected
    finally:
        _FORKED_CASE.clear()


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_helpers_woken_ahead_of_a_fit_take_its_parts_and_otherwise_sleep_again():
    """expect_fit wakes the helpers a fit will hand parts to: the fits that follow give the one-thread columns;
    helpers woken for fits that never come (absurd ones too) wait awake a millisecond at most, then sleep, so
    the process takes next to no CPU while this thread sleeps."""
    import time

    models, I, rho = _device_pair_inputs(np.random.default_rng(21), n=600)
    kw = dict(rho_b=rho[0], rho_w=rho[1], method="lut")
    alone = api.fit(models, *I, kernel=NativeKernel(threads=1), **kw)
    threaded = NativeKernel(threads=4)
    for _ in range(5):
        native.expect_fit(2, 600, 4)
        _assert_identical(alone, api.fit(models, *I, kernel=threaded, **kw))
    for k, n, threads in ((2, 600, 4), (0, 0, 4), (1, 10, 1), (3, 10**9, 1 << 16)):
        native.expect_fit(k, n, threads)
    before = time.process_time()
    time.sleep(0.3)
    assert time.process_time() - before < 0.1


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("n", [1, 129, 1000])
def test_one_thickness_shared_out_between_threads_is_its_fit_in_one_call(n):
    """tm_fit_thicknesses with one thickness: its bins' parts (one part of a bin; two, the second of one bin;
    eight, the last short) in up to four threads, bit for bit tm_fit's whole fit of them."""
    models, I, rho = _device_pair_inputs(np.random.default_rng(13), n=max(n, 10))
    solver = NativeKernel()._table_solver(models[0].inverter)
    options = api.native_options(models[0], models[0].inverter.grid, polish=8, polish_tol=1e-6, noise_rel=0.005,
                                 noise_abs=2e-4, ic_floor=1e-4, alpha_min_g=0.02)
    rows = [x[:1, :n] for x in I] + [r[None, :n] for r in rho]
    whole = solver.fit(*(x[0] for x in rows), **options)
    for threads in (1, 2, 4):
        fits, combined, steps = native.fit_thicknesses([solver], *rows, sd=None, options=[options],
                                                       underdetermined_std=THRESHOLDS["underdetermined_std"],
                                                       disagree_sigmas=THRESHOLDS["disagree_sigmas"], threads=threads)
        assert steps == whole["steps"]
        for row, name in zip(fits[0], native._OUTPUT_ROWS, strict=True):
            want = whole[name].view(np.float64) if name == "flags" else whole[name]
            assert row.tobytes() == want.tobytes(), (threads, name)


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_the_thread_count_comes_from_the_environment_where_set_and_given_wins(monkeypatch):
    monkeypatch.setenv("TRIMETER_FIT_THREADS", " 3 ")
    assert NativeKernel().fit_threads() == 3
    assert NativeKernel(threads=1).fit_threads() == 1
    monkeypatch.setenv("TRIMETER_FIT_THREADS", "")
    assert NativeKernel().fit_threads() == native.usable_cpus()
    for bad in ("0", "-1", "two", "1.5"):
        monkeypatch.setenv("TRIMETER_FIT_THREADS", bad)
        with pytest.raises(native.NativeKernelError, match="TRIMETER_FIT_THREADS must be a whole number"):
            NativeKernel()
        assert NativeKernel(threads=2).fit_threads() == 2


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("threads", [0, -1, 1.5, True, "2"])
def test_a_thread_count_that_is_not_a_whole_number_of_at_least_one_is_refused(threads):
    with pytest.raises(ValueError, match="threads must be"):
        NativeKernel(threads=threads)


def test_the_numpy_kernel_has_no_one_call_path_for_several_thicknesses():
    assert NumpyKernel().fit_thicknesses([], (), sd=None, options=[], method="lut", **THRESHOLDS) is None


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_thicknesses_of_the_wrong_shape_are_refused(ideal_map):
    from trimeter.inversion.artifacts import load_artifacts

    solver = NativeKernel()._table_solver(load_artifacts(ideal_map).inverter)
    x = np.full((2, 5), 0.5)
    args = dict(sd=None, options=[{}, {}], underdetermined_std=(0.1, 0.2), disagree_sigmas=3.0)
    with pytest.raises(ValueError, match="one solver and one set of options"):
        native.fit_thicknesses([solver], x, x, x, x, x, **args)
    with pytest.raises(ValueError, match=r"must be \(2, n\)"):
        native.fit_thicknesses([solver, solver], x, x, x[:, :4], x, x, **args)


def test_an_output_block_of_the_wrong_shape_is_refused():
    from trimeter.inversion.native import _fit_outputs

    with pytest.raises(ValueError, match="output block"):
        _fit_outputs(4, np.empty((3, 4)))
    with pytest.raises(ValueError, match="output block"):
        _fit_outputs(4, np.empty((len(native.invert_h.OUTPUT_ROWS), 8))[:, ::2])
