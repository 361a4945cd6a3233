"""The compiled kernel (trimeter.inversion.native, invert.c) against the numpy kernel it mirrors:
same initial guess, Newton polish, residual, Jacobian and propagated uncertainty, to rounding, on
random and edge inputs. `make test` builds the library first, so here it must be available."""

import os

import numpy as np
import pytest

from trimeter.inversion import native
from trimeter.inversion.kernel import ForwardGrid
from trimeter.inversion.lut import TableInverter
from trimeter.inversion.table import MapTable
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
    return I_b, I_w, sigma_t, rho_b, rho_w


@pytest.mark.skipif(not native.available(), reason=native.status())
@pytest.mark.parametrize("polish", [0, 1, 4])
def test_table_inversion_matches_the_numpy_kernel(monkeypatch, polish):
    table = MapTable.load(TABLE)
    args = _inputs(np.random.default_rng(polish))
    compiled = TableInverter(table).invert(*args, polish_iterations=polish)
    monkeypatch.setattr(native, "_LIB", None)
    reference = TableInverter(table)
    assert reference._native is None
    expected = reference.invert(*args, polish_iterations=polish)
    for got, want, name in zip(compiled, expected, ("alpha", "g", "residual", "J")):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12, err_msg=name)
    assert np.all(np.isfinite(compiled[0])) and np.all(np.isfinite(compiled[1]))


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_polish_from_a_given_guess_and_the_propagated_uncertainty_match(monkeypatch):
    table = MapTable.load(TABLE)
    rng = np.random.default_rng(7)
    I_b, I_w, sigma_t, rho_b, rho_w = _inputs(rng)
    alpha0, g0 = rng.uniform(-0.2, 1.2, len(I_b)), rng.uniform(-0.5, 1.5, len(I_b))
    sigma_I = rng.uniform(0.0, 0.01, (len(I_b), 3))
    grid = ForwardGrid.from_table(table)
    cell = grid.sigma_cell(sigma_t)
    compiled = grid.solve_alpha_g(I_b, I_w, cell, rho_b, rho_w, alpha0, g0, iterations=3)
    compiled_std = grid.propagate(compiled[3], sigma_I)
    monkeypatch.setattr(native, "_LIB", None)
    reference = ForwardGrid.from_table(table)
    assert reference.native_solver is None
    expected = reference.solve_alpha_g(I_b, I_w, cell, rho_b, rho_w, alpha0, g0, iterations=3)
    for got, want in zip(compiled, expected):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    expected_std = reference.propagate(expected[3], sigma_I)
    for got, want in zip(compiled_std, expected_std):
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-12)


def test_a_missing_or_disabled_library_falls_back_with_a_reason(monkeypatch):
    monkeypatch.setenv("TRIMETER_NATIVE", "0")
    lib, reason = native._load()
    assert lib is None and "TRIMETER_NATIVE=0" in reason
    monkeypatch.delenv("TRIMETER_NATIVE")
    monkeypatch.setattr(native, "LIBRARY", native.LIBRARY.with_name("no-such-library.so"))
    lib, reason = native._load()
    assert lib is None and "make native" in reason
