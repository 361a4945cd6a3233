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
        if field.name == "per_thickness" or isinstance(x, (str, int)):
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
