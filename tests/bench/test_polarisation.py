"""`trimeter bench polarisation`: the clear slab's closed forms, Mitsuba's polarised variant through the project's
scenes and film-free render path against the unpolarised one, and the bench at a small size."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trimeter.bench.polarisation import (SLAB_N, SLAB_RHO, SLAB_THICKNESS_MM, clear_slab_over, slab_diffuse_from,
                                         slab_diffuse_reflectance)
from trimeter.cli import main


@pytest.fixture(scope="module")
def variants():
    pytest.importorskip("mitsuba")
    from trimeter.bench.polarisation import variants
    from trimeter.forward.mitsuba_env import MitsubaUnavailable

    try:
        return variants()
    except MitsubaUnavailable as exc:
        pytest.skip(str(exc))


def test_the_slabs_diffuse_reflectance_per_treatment_of_fresnel():
    """Unpolarised: the slab's R(μ) from the tracer's own (averaged) Fresnel, integrated independently; per
    polarisation it is lower (the mean of 2r/(1 + r) over r_s, r_p is below its value at their mean)."""
    from scipy.integrate import quad

    from trimeter.model.fresnel import NUMPY, fresnel

    unpolarised, polarised = slab_diffuse_reflectance(1.5)
    r = lambda mu: float(fresnel(NUMPY, mu, 1.5)[0])  # noqa: E731
    assert unpolarised == pytest.approx(quad(lambda mu: 2 * mu * 2 * r(mu) / (1 + r(mu)), 0, 1)[0], rel=1e-6)
    assert unpolarised == pytest.approx(0.1554, abs=5e-5) and polarised == pytest.approx(0.1491, abs=5e-5)
    assert slab_diffuse_reflectance(1.0) == pytest.approx((0.0, 0.0), abs=1e-12)  # no interface, no reflection
    for R_d in (0.0, 0.1491, 0.1554, 0.4):
        assert slab_diffuse_from(clear_slab_over(0.5, 1.5, R_d), 0.5, 1.5) == pytest.approx(R_d, abs=1e-12)
    assert clear_slab_over(1.0, 1.5, 0.3) == pytest.approx(1.0)  # lossless over a perfect white: all light back


@pytest.mark.slow
def test_a_clear_slab_seen_along_its_normal_is_the_same_polarised(variants):
    """Over black, a clear slab sends the detector only light reflected at normal incidence, where s and p
    reflect alike: the polarised variant must give the unpolarised intensity (same seeds, same paths)."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    unpolarised, polarised = variants
    out = {}
    try:
        for v in variants:
            mitsuba(v)
            out[v] = render_diffuse_batches("ideal", 0.0, 1e-4, 0.0, 1.5, 0.5, 0.0, spp=4096, seed=3)
    finally:
        mitsuba(unpolarised)
    assert out[unpolarised].mean() == pytest.approx(0.08, abs=0.005)  # two faces' Fresnel reflections, ~4 % each
    np.testing.assert_allclose(out[polarised], out[unpolarised], rtol=1e-5)


@pytest.mark.slow  # a few seconds: the fast check that polarisation is tracked
def test_a_clear_slab_over_grey_gives_back_both_diffuse_reflectances(variants):
    """Over a grey background the slab's diffuse reflectance R_d (oblique Fresnel) enters, and the rendered I gives
    it back: tracked per polarisation R_d is lower, so the polarised render comes out brighter. Each variant's
    R_d within 4σ of its closed form; their shared-seed difference within 4σ of the closed forms' and beyond
    10σ from none, so the project's scene and render path in the polarised variant do track polarisation."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    expected = slab_diffuse_reflectance(SLAB_N)
    R_d = {}
    try:
        for v in variants:
            mitsuba(v)
            I = render_diffuse_batches("ideal", 0.0, 1e-4, 0.0, SLAB_N, SLAB_THICKNESS_MM, SLAB_RHO, spp=1 << 20,
                                       seed=5)
            R_d[v] = slab_diffuse_from(I, SLAB_RHO, SLAB_N)
    finally:
        mitsuba(variants[0])
    k = np.sqrt(len(R_d[variants[0]]))
    for v, want in zip(variants, expected, strict=True):
        assert abs(R_d[v].mean() - want) < 4 * R_d[v].std(ddof=1) / k, (v, R_d[v].mean(), want)
    delta = R_d[variants[1]] - R_d[variants[0]]
    se = delta.std(ddof=1) / k
    assert abs(delta.mean() - (expected[1] - expected[0])) < 4 * se, (delta.mean(), expected)
    assert delta.mean() < -10 * se  # the shift is seen, not noise


@pytest.mark.slow
def test_bench_polarisation_prints_its_table_and_writes_its_figures(variants, tmp_path, capsys):
    out = tmp_path / "pol.json"
    assert main(["bench", "polarisation", "--geometry", "ideal", "--materials", "2", "--spp", "2048",
                 "--slab-spp", "65536", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"volpath {variants[0]} (u) against {variants[1]} with hg" in printed
    assert "clear slab check" in printed and "closed form 0.1554" in printed and "closed form 0.1491" in printed
    assert "fitted with ideal-n1.5-l0.5" in printed and "moved beyond the map's error" in printed
    report = json.loads(out.read_text())
    assert report["slab"]["unpolarised"]["closed_form"] == pytest.approx(0.1554, abs=5e-5)
    (geo,) = report["geometries"]
    assert [(r["material"], r["background"]) for r in geo["rows"]] == [
        ("clear", "black"), ("clear", "white"), ("grey", "black"), ("grey", "white")]
    for r in geo["rows"]:  # shared seeds: the difference is far less noisy than either render
        for suffix, key in (("", "polarised"), ("_depolarising", "depolarising")):
            assert r[f"delta{suffix}"] == pytest.approx(r[f"I_{key}"] - r["I_unpolarised"], abs=1e-12)
            assert 0 < r[f"stderr_delta{suffix}"] < min(r[f"stderr_{key}"], r["stderr_unpolarised"])
            assert r[f"z{suffix}"] == pytest.approx(r[f"delta{suffix}"] / r[f"stderr_delta{suffix}"])
    for f in geo["fits"]:
        assert 0 < f["I_c"] < 1
        for p in ("alpha", "sigma_t", "g"):
            c = f[p]
            assert c["shift"] == pytest.approx(c["polarised"] - c["unpolarised"]) and c["sigma_map"] >= 0
            assert c["shift_depolarising"] == pytest.approx(c["depolarising"] - c["unpolarised"])


def test_bench_polarisation_refuses_bad_sizes(capsys):
    assert main(["bench", "polarisation", "--materials", "0"]) == 2
    assert "--materials" in capsys.readouterr().err
    assert main(["bench", "polarisation", "--spp", "3"]) == 2
    assert "--spp" in capsys.readouterr().err
    assert main(["bench", "polarisation", "--slab-spp", "3"]) == 2
    assert "--slab-spp" in capsys.readouterr().err


def test_maps_readme_quotes_the_committed_run():
    """maps/README.md's polarisation figures are maps/polarisation.json's (the run its command wrote)."""
    from trimeter.paths import REPO_ROOT

    run = json.loads((REPO_ROOT / "maps" / "polarisation.json").read_text())
    readme = " ".join((REPO_ROOT / "maps" / "README.md").read_text().split())
    assert f"--spp {run['spp']} --out maps/polarisation.json" in readme
    slab = run["slab"]
    for key in ("unpolarised", "polarised"):
        assert f"{slab[key]['R_d']:.4f} ± {slab[key]['stderr']:.4f}" in readme
    for geo in run["geometries"]:
        for f in geo["fits"]:
            for p, name in (("alpha", "α"), ("g", "g")):
                c = f[p]
                if c["beyond_map_error"]:  # every shift beyond the map's error is quoted, with its σ_map
                    quoted = f"{name} {c['shift']:+.4f}".replace("-", "−")
                    assert quoted in readme and f"{c['sigma_map']:.4f}" in readme, (geo["geometry"], f["material"], p)
