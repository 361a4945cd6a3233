"""`trimeter bench polarisation` at a small size: Mitsuba's polarised variant through the project's scenes
and film-free render path, against the unpolarised one (slow: two variants JIT their kernels)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trimeter.cli import main

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def variants():
    pytest.importorskip("mitsuba")
    from trimeter.bench.polarisation import variants
    from trimeter.forward.mitsuba_env import MitsubaUnavailable

    try:
        return variants()
    except MitsubaUnavailable as exc:
        pytest.skip(str(exc))


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


def _clear_slab_over(rho: float, n: float) -> tuple[float, float]:
    """(unpolarised, polarised) closed forms of a clear, lossless slab's reflectance factor along its normal
    over a Lambertian ρ under uniform light: I = R₀ + T₀·(1 − R_d)·ρ / (1 − R_d·ρ), with R₀ = 2r/(1 + r) the
    slab's normal reflectance and R_d its diffuse one, ∫ R_slab(μ) 2μ dμ — from the averaged Fresnel
    (unpolarised) or per polarisation, then averaged (polarised)."""
    from scipy.integrate import quad

    def fresnel(mu):
        mu_t = np.sqrt(1.0 - (1.0 - mu * mu) / (n * n))
        return ((mu - n * mu_t) / (mu + n * mu_t)) ** 2, ((n * mu - mu_t) / (n * mu + mu_t)) ** 2

    def slab(r):
        return 2.0 * r / (1.0 + r)  # both faces, all internal reflections, no loss

    unpolarised = quad(lambda mu: 2 * mu * slab(sum(fresnel(mu)) / 2), 0, 1)[0]
    polarised = quad(lambda mu: 2 * mu * sum(slab(r) for r in fresnel(mu)) / 2, 0, 1)[0]
    r0 = slab(((n - 1) / (n + 1)) ** 2)
    return tuple(r0 + (1 - r0) * (1 - rd) * rho / (1 - rd * rho) for rd in (unpolarised, polarised))


def test_a_clear_slab_over_white_matches_the_closed_form_in_both_variants(variants):
    """Over a white background the slab's diffuse reflectance (oblique Fresnel) enters: tracked per polarisation
    it is lower (0.149 against 0.155 at n = 1.5), so the polarised render must come out higher by the closed
    form's difference: the project's scene and render path in the polarised variant track it."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    expected = _clear_slab_over(0.9, 1.5)
    batches = {}
    try:
        for v in variants:
            mitsuba(v)
            batches[v] = render_diffuse_batches("ideal", 0.0, 1e-4, 0.0, 1.5, 0.5, 0.9, spp=1 << 21, seed=5)
    finally:
        mitsuba(variants[0])
    k = np.sqrt(len(batches[variants[0]]))
    for v, want in zip(variants, expected, strict=True):
        got = batches[v]
        assert abs(got.mean() - want) < 4 * got.std(ddof=1) / k, (v, got.mean(), want)
    delta = batches[variants[1]] - batches[variants[0]]
    se = delta.std(ddof=1) / k
    assert abs(delta.mean() - (expected[1] - expected[0])) < 4 * se, (delta.mean(), expected)
    assert delta.mean() > 5 * se  # the shift is seen, not noise


def test_bench_polarisation_prints_its_table_and_writes_its_figures(variants, tmp_path, capsys):
    out = tmp_path / "pol.json"
    assert main(["bench", "polarisation", "--geometry", "ideal", "--materials", "2", "--spp", "2048",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"volpath {variants[0]} (u) against {variants[1]} (p)" in printed
    assert "fitted with ideal-n1.5-l0.5" in printed and "moved beyond the map's error" in printed
    report = json.loads(out.read_text())
    (geo,) = report["geometries"]
    assert [(r["material"], r["background"]) for r in geo["rows"]] == [
        ("clear", "black"), ("clear", "white"), ("grey", "black"), ("grey", "white")]
    for r in geo["rows"]:  # shared seeds: the difference is far less noisy than either render
        assert r["delta"] == pytest.approx(r["I_polarised"] - r["I_unpolarised"], abs=1e-12)
        assert 0 < r["stderr_delta"] < min(r["stderr_polarised"], r["stderr_unpolarised"])
    for f in geo["fits"]:
        for p in ("alpha", "sigma_t", "g"):
            c = f[p]
            assert c["shift"] == pytest.approx(c["polarised"] - c["unpolarised"]) and c["sigma_map"] >= 0


def test_bench_polarisation_refuses_bad_sizes(capsys):
    assert main(["bench", "polarisation", "--materials", "0"]) == 2
    assert "--materials" in capsys.readouterr().err
    assert main(["bench", "polarisation", "--spp", "3"]) == 2
    assert "--spp" in capsys.readouterr().err
