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
