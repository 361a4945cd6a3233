"""`trimeter bench fit`'s error budget on synthetic held-out sets whose answers are known:
- intensities that ARE the forward model lut/mlp polish on (the table's, refined in σt) → map error
  floor 0, map-exact rows = rendered rows;
- the map's forward model + a known offset → the map error floor is the first-order error an exact
  inversion makes (checked against a Newton solve of the offset intensities);
- MC std-errors → the reference noise floor is the std of Newton solves of noisy draws."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from trimeter.bench.fit_scoring import error_budget
from trimeter.bench.heldout import heldout_intensities
from trimeter.cli import main
from trimeter.inversion.kernel import default_kernel
from trimeter.formats.appearance import AppearanceMap
from trimeter.formats.container import write_container
from trimeter.model.grid import ForwardGrid

from inversion_support import DATA

RHO_B, RHO_W = 0.02, 0.99  # the ideal test map's reference backgrounds


@pytest.fixture(scope="module")
def amap():
    return AppearanceMap.load(DATA / "ideal-l0.5.tmap")


def model(amap) -> ForwardGrid:
    from trimeter.inversion.artifacts import load_artifacts

    return load_artifacts(amap).grid


def synthetic_heldout(amap, n=200, seed=7, offset_A=0.0, std=1e-3):
    """Off-grid interior materials whose A, B, C are those of the forward model the budget uses."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.2, 0.97, n)
    s = np.exp(rng.uniform(np.log(0.3), np.log(6.0), n))
    g = rng.uniform(0.05, 0.8, n)
    grid = model(amap)
    coef = grid.coefficients(a, grid.sigma_cell(s), g)[0]
    return {"alpha": a, "sigma_t": s, "g": g, "A": coef[0] + offset_A, "B": coef[1], "C": coef[2],
            "std_b": np.full(n, std), "std_w": np.full(n, std)}


def test_heldout_equal_to_the_map_has_no_map_error(amap):
    b = error_budget(amap, synthetic_heldout(amap), RHO_B, RHO_W)
    assert b["measurable"].sum() > 150
    assert np.max(np.abs(b["alpha_map_err"])) < 1e-9 and np.max(np.abs(b["g_map_err"])) < 1e-9


def test_map_error_floor_is_the_exact_inversions_first_order_error(amap):
    h = synthetic_heldout(amap, offset_A=2e-4)
    b = error_budget(amap, h, RHO_B, RHO_W)
    grid = model(amap)
    I_b, I_w = heldout_intensities(h, RHO_B, RHO_W)
    n = len(I_b)
    alpha, g, _, _ = default_kernel().solve_alpha_g(grid, I_b, I_w, grid.sigma_cell(h["sigma_t"]), np.full(n, RHO_B),
                                                    np.full(n, RHO_W), h["alpha"], h["g"], iterations=8)
    da, dg = alpha - h["alpha"], g - h["g"]
    ok = b["g_scored"] & (np.abs(dg) > 1e-5)  # skip nodes/kinks where the trilinear slope jumps
    assert ok.sum() > 50
    # first order: the same signed error, up to the trilinear map's curvature
    assert np.median(np.abs(b["alpha_map_err"][ok] / da[ok] - 1)) < 0.05
    assert np.median(np.abs(b["g_map_err"][ok] / dg[ok] - 1)) < 0.05


def test_reference_noise_floor_is_the_std_of_noisy_solves(amap):
    std = 2e-4
    h = synthetic_heldout(amap, n=60, std=std)
    b = error_budget(amap, h, RHO_B, RHO_W)
    grid = model(amap)
    draws = 400
    rng = np.random.default_rng(1)
    I_b, I_w = (np.repeat(x, draws) + std * rng.standard_normal(len(x) * draws)
                for x in heldout_intensities(h, RHO_B, RHO_W))
    rep = lambda x: np.repeat(x, draws)  # noqa: E731
    m = len(I_b)
    alpha, g, _, _ = default_kernel().solve_alpha_g(grid, I_b, I_w, grid.sigma_cell(rep(h["sigma_t"])),
                                                    np.full(m, RHO_B), np.full(m, RHO_W), rep(h["alpha"]),
                                                    rep(h["g"]), iterations=8)
    std_a, std_g = alpha.reshape(-1, draws).std(axis=1), g.reshape(-1, draws).std(axis=1)
    sel = b["g_scored"]
    assert sel.sum() > 20
    # 400 draws: the sample std is within ~±7 % (2σ); the median ratio much tighter
    assert 0.9 < np.median(std_a[sel] / b["alpha_floor_std"][sel]) < 1.1
    assert 0.9 < np.median(std_g[sel] / b["g_floor_std"][sel]) < 1.1
    # and it scales with the held-out std-error (no constant hiding in it)
    b2 = error_budget(amap, {**h, "std_b": 2 * h["std_b"], "std_w": 2 * h["std_w"]}, RHO_B, RHO_W)
    np.testing.assert_allclose(b2["alpha_floor_std"], 2 * b["alpha_floor_std"], rtol=1e-9)


def test_bench_map_exact_rows_equal_rendered_rows_when_the_references_are_the_map(amap, tmp_path):
    for suffix in (".tmap", ".tlut"):  # no .onnx next to it: no mlp rows
        shutil.copy(DATA / f"ideal-l0.5{suffix}", tmp_path / f"ideal-l0.5{suffix}")
    h = synthetic_heldout(amap, n=60)  # few: the paper ε-median (250 interpolations each) dominates the cost
    write_container(tmp_path / "ideal-l0.5.held", "heldout-set",
                    {"source": "synthetic: the map's forward model", "recipe": amap.recipe}, h)
    out = tmp_path / "bench"
    rc = main(["bench", "fit", "--map", str(tmp_path / "ideal-l0.5.tmap"), "--noise", "0", "--repeats", "1",
               "--median-bins", "4", "--out", str(out)])
    assert rc == 0
    result = json.loads((out / "results.json").read_text())["maps"][0]
    rendered = {r["variant"]: r for r in result["rows"]}
    exact = {r["variant"]: r for r in result["map_exact_rows"]}
    assert set(rendered) == set(exact) and {"paper", "lut p≤8"} <= set(rendered)
    for name, r in rendered.items():
        for key in ("alpha_p50", "alpha_p95", "sigma_rel_p95", "g_p95", "alpha_p95_well", "nan_rate", "flag_rate"):
            assert exact[name][key] == pytest.approx(r[key], rel=1e-6, abs=1e-9), (name, key)
    budget = result["budget"]
    assert budget["map_error_floor"]["alpha_p95"] < 1e-9 and budget["map_error_floor"]["g_p95"] < 1e-9
    assert budget["reference_noise_floor"]["alpha_p95"] > 0
    wc = budget["well_conditioned"]
    assert 0 < wc["alpha_count"] <= wc["alpha_of"] and 0 <= wc["g_count"] <= wc["g_of"]
