"""The thicknesses' combination in C (tm_combine through NativeKernel.combine) against api.combine, the
numpy reference it mirrors: the same columns and flags bit for bit, on random fits with NaN, ±inf and
zero values and stds, any flag bits, with and without conditioning stds, one to four thicknesses."""

import dataclasses

import numpy as np
import pytest

from trimeter.domain.parameters import FitResult
from trimeter.inversion import api, native
from trimeter.inversion.flags import FitFlag
from trimeter.inversion.kernel import NativeKernel, NumpyKernel

THRESHOLDS = dict(underdetermined_std=(api.UNDERDETERMINED_ALPHA_STD, api.UNDERDETERMINED_G_STD),
                  disagree_sigmas=api._DISAGREE_SIGMAS)


def _random_fit(rng, n):
    columns = {name: rng.normal(size=n) * rng.choice([1e-3, 1.0], size=n)
               for name in ("alpha", "sigma_t", "g", "sigma_t_beer")}
    for name in ("alpha_std", "sigma_t_std", "g_std"):
        columns[name] = np.abs(rng.normal(size=n)) * rng.choice([1e-3, 0.05, 1.0, 1e200], size=n)
    for name, column in columns.items():
        u = rng.random(n)
        zero = 0.0 if name.endswith("_std") else -0.0  # a std is never -0 (a square root's)
        columns[name] = np.select([u < 0.1, u < 0.15, u < 0.2, u < 0.22, u < 0.25],
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
            expected = api.combine(fits, "x")
            got = kernel.combine(fits, "x", **THRESHOLDS)
        _assert_identical(got, expected)
        seen |= np.bitwise_or.reduce(expected.flags)
    # the random cases reach every flag the combination sets or clears
    for flag in (FitFlag.THICKNESS_DISAGREE, FitFlag.UNDERDETERMINED, FitFlag.STD_APPROXIMATE):
        assert seen & int(flag)


def test_the_numpy_kernel_leaves_the_combination_to_api():
    assert NumpyKernel().combine([], "x", **THRESHOLDS) is None


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("sd", [None, 2e-3])
def test_thicknesses_fitted_into_one_block_combine_as_gathered_ones(ideal_map, thick_map, sd):
    """fit() writes each thickness's fused fit into its place of one (k, rows, n) block and combines
    that block as it is: the same result, bit for bit, as each thickness fitted alone and combined
    from its columns (with and without the intensities' own stds, i.e. conditioning rows)."""
    from trimeter.maps.artifacts import load_artifacts

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


def test_an_output_block_of_the_wrong_shape_is_refused():
    from trimeter.inversion.native import _fit_outputs

    with pytest.raises(ValueError, match="output block"):
        _fit_outputs(4, np.empty((3, 4)))
    with pytest.raises(ValueError, match="output block"):
        _fit_outputs(4, np.empty((len(native.invert_h.OUTPUT_ROWS), 8))[:, ::2])
