"""Numerical stability: ≥ 1e6 random and edge inputs through every method (vectorised, a few big
batches), a Lipschitz check away from flagged bins, and noise propagation against the first-order
prediction from the map's Jacobian."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import trimeter

from inversion_support import forward, well_conditioned

EDGES = np.array([0.0, 1.0, 1e-300, 5e-324, 1e300, np.nan, np.inf, -np.inf, -0.5, -1e-12, 1 - 1e-16,
                  1 + 1e-12, 2.0, 0.5, 1e-7])
BATCH = 250_000
COUNTED = {}


def _inputs(rng, n, edge_fraction, n_rho_pairs=None):
    """Random intensities in and around [0, 1] (I_b > I_w in about half), with edge values mixed in."""
    cols = []
    for _ in range(3):
        x = rng.uniform(-0.05, 1.05, n)
        mask = rng.random(n) < edge_fraction
        x[mask] = rng.choice(EDGES, mask.sum())
        cols.append(x)
    if n_rho_pairs:  # the paper method triangulates per background pair: keep a few
        pairs = np.array([[0.02, 0.99], [0.05, 0.9], [np.nan, 0.9], [0.5, 0.4]])[:n_rho_pairs]
        pick = pairs[rng.integers(0, len(pairs), n)]
        rho_b, rho_w = pick[:, 0], pick[:, 1]
    else:
        rho_b, rho_w = rng.uniform(-0.01, 0.1, n), rng.uniform(0.8, 1.01, n)
        for rho in (rho_b, rho_w):
            mask = rng.random(n) < edge_fraction / 4
            rho[mask] = rng.choice(EDGES, mask.sum())
    return (*cols, rho_b, rho_w)


def _check(r, n):
    assert len(r) == n and r.flags.dtype.kind == "i" and np.all(r.flags >= 0)
    with np.errstate(invalid="ignore"):
        for name, lo, hi in (("alpha", 0, 1), ("sigma_t", 0, np.inf), ("g", -1, 1)):
            v = getattr(r, name)
            assert np.all(np.isnan(v) | ((v >= lo) & (v <= hi))), f"{name} out of bounds"
            assert np.all(np.isfinite(v) | (r.flags != 0)), f"{name}: NaN without a flag"
        for name in ("alpha_std", "sigma_t_std", "g_std"):
            v = getattr(r, name)
            assert np.all(np.isnan(v) | (v >= 0)), f"{name} negative"


@pytest.mark.parametrize("method, batches", [("lut", 4), ("mlp", 4), ("paper", 4)])
def test_a_million_random_and_edge_inputs(ideal_map, ideal_model, method, batches):
    kw = {"mlp_model": ideal_model} if method == "mlp" else {"samples": 0} if method == "paper" else {}
    seen = []

    @settings(max_examples=batches, deadline=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(seed=st.integers(0, 2**32 - 1), edge_fraction=st.sampled_from([0.0, 0.05, 0.3, 1.0]))
    def run(seed, edge_fraction):
        rng = np.random.default_rng(seed)
        args = _inputs(rng, BATCH, edge_fraction, n_rho_pairs=4 if method == "paper" else None)
        r = trimeter.fit(ideal_map, *args, method=method, **kw)
        _check(r, BATCH)
        seen.append(BATCH)

    run()
    COUNTED[method] = sum(seen)
    assert sum(seen) >= 1_000_000


def _perturbation_ratio(amap, method, kw, rng, n=2000, h=1e-6):
    a, s, g = well_conditioned(amap, n, rng)
    I = np.stack(forward(amap, a, s, g, 0.02, 0.99))
    r0 = trimeter.fit(amap, *I, method=method, **kw)
    d = rng.standard_normal(I.shape)
    d *= h / np.linalg.norm(d, axis=0)
    r1 = trimeter.fit(amap, *(I + d), method=method, **kw)
    clean = (r0.flags == 0) & (r1.flags == 0)
    dtheta = np.stack([r1.alpha - r0.alpha, r1.sigma_t - r0.sigma_t, r1.g - r0.g])
    from trimeter.inversion.artifacts import load_artifacts

    J = load_artifacts(amap).grid.jacobian(r0.alpha, r0.sigma_t, r0.g, np.full(n, 0.02), np.full(n, 0.99))
    inv_norm = np.linalg.norm(np.linalg.inv(J), ord=2, axis=(1, 2))
    ratio = np.linalg.norm(dtheta, axis=0) / h / inv_norm
    return ratio[clean], clean.mean()


@pytest.mark.parametrize("method, bound, clean_share", [("lut", 3.0, 0.9), ("mlp", 3.0, 0.9), ("paper", 5.0, 0.5)])
def test_lipschitz_away_from_flags(ideal_map, ideal_model, method, bound, clean_share):
    """|Δθ| / |ΔI| ≤ bound · ‖J⁻¹‖ per bin (the local inverse's own gain; the paper's piecewise-linear
    interpolant over a coarse triangulation gets a looser bound, and its residual flags more bins)."""
    kw = {"mlp_model": ideal_model} if method == "mlp" else {"samples": 0} if method == "paper" else {}
    ratio, clean = _perturbation_ratio(ideal_map, method, kw, np.random.default_rng(5),
                                       n=2000 if method != "paper" else 500)
    assert clean > clean_share
    assert np.all(ratio <= bound), f"max gain {ratio.max():.2f} × ‖J⁻¹‖"


@pytest.mark.parametrize("method", ["lut", "mlp"])
def test_noise_propagation_matches_first_order(ideal_map, ideal_model, method):
    """With 0.2 % noise the error's spread stays within 1.5× the first-order propagated std in the
    well-conditioned region (where the reported std is small enough for first order to apply)."""
    kw = {"mlp_model": ideal_model} if method == "mlp" else {}
    rng = np.random.default_rng(6)
    n, draws, level = 300, 60, 0.002
    a, s, g = well_conditioned(ideal_map, n, rng)
    I = np.stack(forward(ideal_map, a, s, g, 0.02, 0.99))
    clean = trimeter.fit(ideal_map, *I, method=method, noise_rel=level, noise_abs=0.0, **kw)
    noisy_I = np.repeat(I, draws, axis=1) * (1 + level * rng.standard_normal((3, n * draws)))
    r = trimeter.fit(ideal_map, *noisy_I, method=method, noise_rel=level, noise_abs=0.0, **kw)
    well = (clean.flags == 0) & (clean.alpha_std < 0.02) & (clean.g_std < 0.05) & (clean.sigma_t_std < 0.02 * s)
    assert well.mean() > 0.3
    for name, truth in (("alpha", a), ("sigma_t", s), ("g", g)):
        err = (getattr(r, name) - np.repeat(truth, draws)).reshape(n, draws)
        rms = np.sqrt(np.nanmean(err ** 2, axis=1))
        predicted = getattr(clean, f"{name}_std")
        ratio = (rms / predicted)[well]
        assert np.median(ratio) <= 1.5, f"{name}: median ratio {np.median(ratio):.2f}"
        assert np.percentile(ratio, 90) <= 1.5, f"{name}: 90th-percentile ratio {np.percentile(ratio, 90):.2f}"
