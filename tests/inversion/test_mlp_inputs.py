"""The `mlp` method's network inputs (trimeter.inversion.mlp.network_inputs) and its model contract."""

from __future__ import annotations

import numpy as np
import pytest

import trimeter
from trimeter.errors import MapFileError
from trimeter.inversion.mlp import INPUTS, ScatterRange, features, network_inputs

from inversion_support import DATA


def _inputs(amap, alpha, sigma_t, g, rho_b, rho_w):
    grid = amap.between_nodes
    n = len(alpha)
    full = lambda v: np.full(n, v, dtype=float)  # noqa: E731
    I_b, I_w, _ = grid.intensities(alpha, sigma_t, g, full(rho_b), full(rho_w))
    x = features(I_b, I_w, sigma_t, full(rho_b), full(rho_w), (grid.log_sigma_t[0], grid.log_sigma_t[-1]))
    return network_inputs(x, ScatterRange(grid))


def test_the_inputs_place_each_intensity_between_the_maps_least_and_most_scattering_response(ideal_map):
    """At the map's α ends (g = 0) the inputs sit at the logit's clip on either side; between them they
    grow with α at every σt and background, and the background itself drops out of the α-ends."""
    a_lo, a_hi = ideal_map.between_nodes.alpha_range
    sigma_t = np.exp(np.linspace(np.log(ideal_map.sigma_t[0]), np.log(ideal_map.sigma_t[-1]), 9))
    for rho_b, rho_w in ((0.0, 0.9), (0.08, 0.97)):
        low = _inputs(ideal_map, np.full(9, a_lo), sigma_t, np.zeros(9), rho_b, rho_w)
        high = _inputs(ideal_map, np.full(9, a_hi), sigma_t, np.zeros(9), rho_b, rho_w)
        assert np.all(low[:, :2] < -9) and np.all(high[:, :2] > 9)  # logit(1e-4) ≈ −9.2
        alphas = np.linspace(0.1, 0.95, 6)
        for s in sigma_t[2:7]:
            x = _inputs(ideal_map, alphas, np.full(6, s), np.full(6, 0.3), rho_b, rho_w)
            assert np.all(np.diff(x[:, 0]) > 0), (s, x[:, 0])
        assert np.all(np.isfinite(low)) and low.dtype == np.float32 and low.shape == (9, len(INPUTS))


@pytest.mark.parametrize("refined", [False, True])
def test_the_ends_are_the_forward_models_own(ideal_map, refined):
    """ScatterRange's lookups equal grid.intensities at the map's α ends (g = 0) at any σt and ρ, on the
    map between its nodes and on the fit's grid (the table's, refined)."""
    from trimeter.inversion.artifacts import load_artifacts

    grid = load_artifacts(ideal_map).grid if refined else ideal_map.between_nodes
    rng = np.random.default_rng(7)
    n = 400
    sigma_t = np.exp(rng.uniform(grid.log_sigma_t[0] - 0.5, grid.log_sigma_t[-1] + 0.5, n))  # clamped past the ends
    rho = rng.uniform(0.0, 1.0, n)
    ends = ScatterRange(grid).ends(np.clip(np.log(sigma_t), grid.log_sigma_t[0], grid.log_sigma_t[-1]), rho)
    for got, alpha in zip(ends, grid.alpha_range, strict=True):
        want = grid.intensities(np.full(n, alpha), sigma_t, np.zeros(n), rho, rho)[0]
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)


def test_bad_features_give_finite_inputs(ideal_map):
    """NaN or out-of-range intensities (the fit computes unusable bins on stand-ins, but a guesser must
    never be handed NaN inputs by this step) and σt at the map's ends stay finite."""
    grid = ideal_map.between_nodes
    x = np.array([[np.nan, 0.5, 0.0, 0.02, 0.9], [2.0, -1.0, 10.0, 0.02, 0.9], [0.0, 0.0, -10.0, 0.0, 1.0]],
                 dtype=np.float32)
    assert np.all(np.isfinite(network_inputs(x, ScatterRange(grid))))


def test_a_model_made_for_the_raw_intensities_is_refused_by_name(ideal_map, tmp_path):
    """The earlier format (the network read √I_b, √I_w directly) would guess garbage from these inputs."""
    onnx = pytest.importorskip("onnx")
    model = onnx.load(DATA / "ideal-l0.5.onnx")
    for prop in model.metadata_props:
        if prop.key == "trimeter.format":
            prop.value = "1"
    old = tmp_path / "old.onnx"
    onnx.save(model, old)
    with pytest.raises(MapFileError, match="trimeter.format '1' is not supported"):
        trimeter.fit(ideal_map, [0.1], [0.5], [0.3], method="mlp", mlp_model=old)


def test_the_network_alone_guesses_within_its_polished_answers_reach(ideal_map, ideal_model):
    """polish=0 is the network's answer: close to the truth on well-conditioned materials (not the
    polished precision), and the default polish then lands on the lut's answer."""
    from inversion_support import forward, well_conditioned

    rng = np.random.default_rng(3)
    a, s, g = well_conditioned(ideal_map, 300, rng)
    I_b, I_w, I_c = forward(ideal_map, a, s, g, *ideal_map.reference_rhos)
    raw = trimeter.fit(ideal_map, I_b, I_w, I_c, method="mlp", mlp_model=ideal_model, polish=0)
    assert np.percentile(np.abs(raw.alpha - a), 95) < 0.05
    polished = trimeter.fit(ideal_map, I_b, I_w, I_c, method="mlp", mlp_model=ideal_model)
    lut = trimeter.fit(ideal_map, I_b, I_w, I_c, method="lut")
    assert np.percentile(np.abs(polished.alpha - lut.alpha), 95) < 1e-3
