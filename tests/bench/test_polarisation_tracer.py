"""`trimeter bench polarisation-tracer`: the tracer's polarisation option against the closed forms and the
committed polarised renders, and its cost, at a small size; bad options are refused."""

from __future__ import annotations

import json
import math

from trimeter.cli import main


def test_the_bench_at_a_small_size_writes_every_figure(tmp_path, capsys):
    out = tmp_path / "results.json"
    assert main(["bench", "polarisation-tracer", "--geometry", "ideal", "--paths", "16384", "--batches", "2",
                 "--cost-paths", "4096", "--cost-repeats", "1", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "clear lossless slab" in printed and "on/off" in printed
    report = json.loads(out.read_text())
    slab = report["slab"]
    assert {(t["factorised"], t["treatment"]) for t in slab["traced"]} == {
        (f, k) for f in (True, False) for k in ("unpolarised", "polarised")}
    for t in slab["traced"]:   # 65536 paths: R_d to ±0.002, the two closed forms 0.0064 apart
        assert abs(t["R_d"] - slab["closed_form"][t["treatment"]]) < 5 * t["stderr"] < 0.015
    (geo,) = report["geometries"]
    assert [(r["material"], r["background"]) for r in geo["rows"]] == [
        (m, b) for m in ("clear", "thin") for b in ("black", "white")]
    for r in geo["rows"]:
        assert r["stderr_shift"] > 0 and "render_d" in r and math.isfinite(r["z"])
    white = [r for r in geo["rows"] if r["background"] == "white"]
    # the ideal geometry's renders: I rises on white, by ~0.001 (this size: ±0.0003)
    assert all(r["shift"] > 0 and abs(r["z"]) < 5 for r in white), white
    assert [c["sigma_t"] for c in report["cost"]["columns"]] == [0.2, 20.0]
    assert all(c["median_ratio"] > 0 for c in report["cost"]["columns"])


def test_bad_options_are_refused(capsys, tmp_path):
    for args in (["--paths", "100"], ["--batches", "1"], ["--series-orders", "2"], ["--cost-paths", "10"],
                 ["--renders", str(tmp_path / "missing.json")]):
        assert main(["bench", "polarisation-tracer", *args]) == 2
        assert args[0] in capsys.readouterr().err


def test_maps_readme_quotes_the_committed_run():
    """maps/README.md's figures of the tracer's polarisation option are maps/polarisation-tracer.json's."""
    from trimeter.paths import REPO_ROOT

    run = json.loads((REPO_ROOT / "maps" / "polarisation-tracer.json").read_text())
    readme = " ".join((REPO_ROOT / "maps" / "README.md").read_text().split())
    assert "every figure in `maps/polarisation-tracer.json`" in readme
    for t in run["slab"]["traced"]:
        if t["factorised"]:
            assert f"{t['R_d']:.4f} ± {t['stderr']:.4f}" in readme, t
    for geo in run["geometries"]:
        for r in geo["rows"]:
            if r["background"] == "white":
                quoted = f"{r['shift']:+.5f} ± {r['stderr_shift']:.5f}".replace("-", "−")
                assert f"{r['material']} {quoted}" in readme, (geo["geometry"], r["material"])
    for c in run["cost"]["columns"]:
        assert f"{c['median_ratio']:.3f}" in readme and f"{c['fastest_ratio']:.3f}" in readme, c
