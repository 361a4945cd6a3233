"""`trimeter bench fit` runs end to end on the ideal test map and reports every figure it promises."""

from __future__ import annotations

import json

import pytest

from trimeter.cli import main

from inversion_support import DATA


def test_bench_fit_reports_figures_and_plot(tmp_path, capsys):
    out = tmp_path / "bench"
    rc = main(["bench", "fit", "--map", str(DATA / "ideal-l0.5.tmap"), "--noise", "0,0.01", "--repeats", "1",
               "--median-bins", "4", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "ratio to paper" in text and "Pareto plot" in text
    report = json.loads((out / "results.json").read_text())["maps"][0]
    rows = report["rows"]
    hull = report["paper_hull_split"]  # the paper's time inside its hull alone, next to the whole set
    assert 0 <= hull["outside_hull"] < hull["of"] and hull["lut_ms"] > 0 and hull["paper_core_ms"] > 0
    variants = {r["variant"] for r in rows}
    assert {"paper", "paper-median", "lut p0", "lut p≤8", "lut-small p≤8", "mlp p0", "mlp p≤8"} <= variants
    for r in rows:
        assert r["ms_per_1024"] > 0 and 0 <= r["nan_rate"] <= 1
        assert 0 <= r["alpha_misses_flagged"] <= r["alpha_misses"] <= r["measurable"]
    noisy = {r["variant"]: r for r in rows if r["noise"] == 0.01}
    assert noisy["lut p0"]["alpha_misses"] > 0  # 1 % noise puts some bins over 0.01: the count is live
    assert "flags UNDERDETERMINED" in text
    # every target judged from this run's figures: speed-ups at least, the rest at most their limit
    assert set(report["targets"]) == {"lut p≤8", "mlp p≤8"} and "inversion targets" in text
    lut = report["targets"]["lut p≤8"]
    clean_lut = next(r for r in rows if r["noise"] == 0 and r["variant"] == "lut p≤8")
    assert len(lut) == 7 and lut["α p95"]["value"] == clean_lut["alpha_p95"]
    for checks in report["targets"].values():
        for name, c in checks.items():
            assert c["met"] == (c["value"] >= c["limit"] if name.startswith("×") else c["value"] <= c["limit"])
            assert c["issue_target"] == (name != "× paper cold")
    clean = {r["variant"]: r for r in rows if r["noise"] == 0}
    assert clean["lut p≤8"]["nan_rate"] == 0 and clean["lut p≤8"]["alpha_p95"] < 0.05
    assert (out / "pareto-ideal-l0.5.png").stat().st_size > 10_000
    speed = json.loads((out / "results.json").read_text())["speed"]  # one map: no two-thickness figure
    assert set(speed["targets"]) == {"lut_over_lookup"} and "speed with uncertainty" in text
    ms = speed["ms_per_1024"]
    assert speed["targets"]["lut_over_lookup"]["value"] == ms["lut"] / ms["bare lookup"]
    assert ms["paper ε-median"] > ms["lut"] > 0


@pytest.mark.parametrize("cpus", [1, 2])
def test_speed_times_two_thicknesses_where_two_maps_differ_only_in_thickness(capsys, monkeypatch, cpus):
    """Where the process may use two CPUs (and the kernel is the C one) the lut fits are timed in two threads
    and in one, both two-thickness figures judged; on one CPU in one thread only."""
    from trimeter.bench.fit_speed import SPEED_TWO_MS_MAX, speed
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion import native

    monkeypatch.setattr(native, "usable_cpus", lambda: cpus)
    maps = [AppearanceMap.load(DATA / name) for name in ("ideal-l0.5.tmap", "ideal-l1.0.tmap")]
    report = speed(maps, 4, 1)
    ms, threads = report["ms_per_1024"], report["fit_threads"]
    assert threads == (cpus if native.available() else 1)
    two = report["targets"]["two_thicknesses_ms"]
    assert two["value"] == ms["lut, two thicknesses"] > 0
    assert two["met"] == (two["value"] <= SPEED_TWO_MS_MAX)
    one = report["targets"].get("two_thicknesses_one_thread_ms")
    assert (one is not None) == (threads > 1)
    if one is not None:
        assert one["value"] == ms["lut, two thicknesses, one thread"] > 0 and one["met"] == (one["value"] <= 0.8)
    text = capsys.readouterr().out
    rows = [line for line in text.splitlines() if line.startswith("   ") and "×" not in line and "targets" not in line]
    # the paper's ε-median, the lookup, lut, lut on the first map alone, both maps; lut and both maps in one
    # thread as well
    assert len(rows) == 5 + 2 * (threads > 1), text
    assert ("lut, one thread" in ms) == (threads > 1)
    order = report["round"]  # the one-thickness fits each right after a lookup, in threads and in one alike
    assert [order[order.index(name) - 1] for name in ("lut", "lut, one thread") if name in ms] == \
        ["bare lookup"] * (1 + (threads > 1))
    assert set(order) == set(ms) - {"paper ε-median"}
    assert f"two thicknesses (ideal-l0.5 + ideal-l1.0, {threads} thread" in text


def test_per_wavelength_backgrounds_case_scores_the_fit_at_the_bins_own_backgrounds():
    """The opt-in ρ(λ) case (its paper row takes minutes, so only lut runs here): intensities at the
    bins' own backgrounds, fitted with them, score like the reference-background case."""
    import numpy as np

    from trimeter.bench.fit import _bench_backgrounds
    from trimeter.bench.fit_scoring import error_budget
    from trimeter.bench.fit_variants import DEFAULT_POLISH
    from trimeter.bench.heldout import heldout_for
    from trimeter.inversion.artifacts import load_artifacts
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(DATA / "ideal-l0.5.tmap")
    _, _, h = heldout_for(amap)
    h = {k: v[:40] for k, v in h.items()}
    rb, rw = float(amap.recipe["reference_rho_b"]), float(amap.recipe["reference_rho_w"])
    budget = error_budget(amap, h, rb, rw)
    budget["rho"] = (rb, rw)
    rows = _bench_backgrounds(amap, h, budget, [("lut p≤8", "lut", DEFAULT_POLISH, load_artifacts(amap))])
    assert [r["variant"] for r in rows] == ["lut p≤8"]
    row = rows[0]
    assert row["background_pairs"] > 20 and row["ms_per_1024"] > 0
    assert row["nan_rate_measurable"] == 0 and row["alpha_p95"] < 0.05 and np.isfinite(row["g_p95"])


def test_two_thicknesses_case_fits_the_shipped_pair_together(capsys, monkeypatch):
    """The paper's procedure on the device pair (whose held-out sets hold the same materials): the
    joint fit resolves what l0.8 alone cannot (its optically thick samples), and sets of different
    materials are refused rather than scored together."""
    from trimeter.bench import fit as bench
    from trimeter.formats.appearance import AppearanceMap, find_map

    pair = [AppearanceMap.load(find_map(n)) for n in ("device-n1.5-l0.4", "device-n1.5-l0.8")]
    report = bench.two_thicknesses(pair, repeats=1)
    rows = {r["variant"]: r for r in report["rows"]}
    assert set(rows) == {"paper", "lut p≤8", "mlp p≤8"}
    lut = rows["lut p≤8"]
    assert lut["ms_per_1024"] > 0
    assert lut["alpha_p95"] < 0.01 and lut["g_p95"] < 0.015
    assert lut["alpha_p95"] < lut["alone"]["device-n1.5-l0.8"]["alpha_p95"] / 2
    real = bench.heldout_for

    def shuffled(amap):
        path, meta, h = real(amap)
        return path, meta, ({**h, "g": h["g"][::-1].copy()} if amap.name.endswith("l0.8") else h)

    monkeypatch.setattr(bench, "heldout_for", shuffled)
    assert bench.two_thicknesses(pair, repeats=1) == {}
    assert "different materials" in capsys.readouterr().out


def test_a_held_out_set_of_another_model_is_refused(tmp_path):
    """A set next to the map wins over the shipped one, so a set rendered for another model (here: the faces'
    polarisation) must not silently score the map."""
    import shutil

    import pytest

    from trimeter.bench.heldout import heldout_for
    from trimeter.errors import MapFileError
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.formats.container import read_container, write_container

    shutil.copy(DATA / "ideal-l0.5.tmap", tmp_path / "ideal-l0.5.tmap")
    meta, arrays, _ = read_container(DATA / "ideal-l0.5.held", "heldout-set")
    write_container(tmp_path / "ideal-l0.5.held", "heldout-set", meta, arrays)
    amap = AppearanceMap.load(tmp_path / "ideal-l0.5.tmap")
    assert heldout_for(amap)[0] == tmp_path / "ideal-l0.5.held"
    polarised = {**meta, "recipe": {**meta["recipe"], "polarisation": True}}
    write_container(tmp_path / "ideal-l0.5.held", "heldout-set", polarised, arrays)
    with pytest.raises(MapFileError, match="Fresnel per polarisation, the map ideal-l0.5 is .*Fresnel unpolarised"):
        heldout_for(amap)
    write_container(tmp_path / "ideal-l0.5.held", "heldout-set", {"source": "no recipe"}, arrays)
    with pytest.raises(MapFileError, match="does not say what it was rendered for"):
        heldout_for(amap)
