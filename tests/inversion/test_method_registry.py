"""Adding an inversion method is one module and one registration line: a throw-away method (the map
box's centre as every bin's guess, then the usual polish) registered here fits through the public
`trimeter.fit`, on both kernels, and shows up in the bench's variants and the CLI's --method."""

from __future__ import annotations

import numpy as np
import pytest

import trimeter
from trimeter.cli import main
from trimeter.inversion import native
from trimeter.inversion.kernel import NativeKernel, NumpyKernel
from trimeter.inversion.methods import METHODS, register, unregister
from trimeter.inversion.strategy import Method
from trimeter.inversion.artifacts import ArtifactCache, load_artifacts

from inversion_support import forward


# ---------------------------------------------------------------------- the whole new method's module
class CentreGuess:
    """Every bin starts at the centre of the map's (α, g) box."""

    def __init__(self, model):
        grid = model.grid
        self.centre = (sum(grid.alpha_range) / 2, sum(grid.g_range) / 2)
        self.log_sigma_range = (float(grid.log_sigma_t[0]), float(grid.log_sigma_t[-1]))

    def run(self, x: np.ndarray) -> np.ndarray:
        return np.tile(np.asarray(self.centre, dtype=np.float32), (len(x), 1))

    def predict(self, I_b, I_w, sigma_t, rho_b, rho_w):
        return np.full(len(I_b), self.centre[0]), np.full(len(I_b), self.centre[1])


CENTRE = Method("centre", "the map box's centre as the guess, then the Newton polish",
                guesser=lambda model, options: CentreGuess(model))
# ------------------------------------------------------------------------------------------------------


@pytest.fixture()
def centre_method():
    register(CENTRE)  # the one registration line
    yield CENTRE
    unregister(CENTRE.name)


def _materials(amap, n=200, seed=3):
    rng = np.random.default_rng(seed)
    alpha, g = rng.uniform(0.6, 0.95, n), rng.uniform(0.2, 0.7, n)
    sigma_t = np.exp(rng.uniform(np.log(1.0), np.log(4.0), n))
    return (alpha, sigma_t, g), forward(amap, alpha, sigma_t, g, *amap.reference_rhos)


@pytest.mark.parametrize("kernel", ["numpy", "native"])
def test_a_registered_method_fits_through_the_public_fit(ideal_map, centre_method, kernel):
    if kernel == "native" and not native.available():
        pytest.skip(native.status())
    chosen = NumpyKernel() if kernel == "numpy" else NativeKernel()
    (alpha, sigma_t, g), I = _materials(ideal_map)
    r = trimeter.fit(ideal_map, *I, method="centre", polish=30, kernel=chosen)
    assert r.method == "centre"
    ok = r.flags == 0
    assert ok.mean() > 0.8
    np.testing.assert_allclose(r.alpha[ok], alpha[ok], atol=2e-3)
    np.testing.assert_allclose(r.sigma_t[ok], sigma_t[ok], rtol=1e-3)
    np.testing.assert_allclose(r.g[ok], g[ok], atol=1e-2)
    # no polish: the guess itself comes back, so the fit did use the new method's guess
    raw = trimeter.fit(ideal_map, *I, method="centre", polish=0, kernel=chosen)
    centre = CentreGuess(load_artifacts(ideal_map)).centre
    np.testing.assert_allclose(raw.alpha[np.isfinite(raw.alpha)], centre[0], atol=1e-6)


def test_a_registered_method_is_in_the_bench_and_the_cli(ideal_map, centre_method, capsys):
    from trimeter.bench.fit_variants import fit_variant, variants_of

    cache = ArtifactCache()
    variants = {v[0]: v for v in variants_of(ideal_map, cache, cache)}
    assert "centre p≤8" in variants and variants["centre p≤8"][1] == "centre"
    (_, _, _), I = _materials(ideal_map, n=50)
    benched = fit_variant(variants["centre p≤8"], *I)
    direct = trimeter.fit(ideal_map, *I, method="centre")
    np.testing.assert_array_equal(benched.alpha, direct.alpha)
    assert "centre" in METHODS
    with pytest.raises(SystemExit) as exc:  # argparse's own usage error
        main(["fit", "--method", "nonesuch", "--map", str(ideal_map.path), "--input", "x.csv"])
    assert exc.value.code == 2
    assert "'centre'" in capsys.readouterr().err  # the CLI's choices are the table's


def test_an_unknown_or_duplicate_method_is_a_clear_error(ideal_map):
    from trimeter.errors import InputError

    with pytest.raises(InputError, match="method must be one of lut, mlp, paper"):
        trimeter.fit(ideal_map, [0.1], [0.5], [0.3], method="centre")
    with pytest.raises(ValueError, match="registered already"):
        register(Method("lut", "another lut"))
