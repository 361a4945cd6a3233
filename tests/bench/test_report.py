"""`trimeter bench report` on a tiny size into a temporary directory: the page and its figures are written
from the benches' own figures, so the machinery that makes docs/validation.md cannot rot."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from trimeter.bench import report
from trimeter.cli import main

MAP = "device-n1.5-l0.4"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    docs, work = tmp / "docs", tmp / "work"
    rc = main(["bench", "report", "--map", MAP, "--noise", "0,0.01", "--repeats", "1", "--median-bins", "8",
               "--draws", "1", "--sensor-noise", "0,0.01", "--sensor-draws", "1", "--tracer-materials", "0",
               "--polarisation-spp", "0",
               "--docs", str(docs), "--work", str(work)])
    assert rc == 0
    page = docs / report.PAGE
    return page, page.read_text(), json.loads((work / "report.json").read_text())


def test_the_page_is_stamped_and_says_what_the_figures_are(made):
    _, text, results = made
    stamp = results["stamp"]
    assert stamp["commit"][:12] in text and stamp["date_utc"] in text and stamp["cpu"] in text
    assert "Nothing on this page has touched real hardware" in text
    assert "Monte Carlo" in text and "adding-doubling" in text


def test_every_figure_the_page_links_exists_and_is_a_png(made):
    page, text, _ = made
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert f"img/validation/time-vs-error-{MAP}.png" in links and "img/validation/coverage.png" in links
    for link in links:
        assert (page.parent / link).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", link


def _row(text: str, method: str) -> list[str]:
    line = next(line for line in text.splitlines() if line.startswith(f"| {method} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_the_headline_rows_are_the_benches_figures(made):
    _, text, results = made
    fit_rows = {r["variant"]: r for r in results["fit"]["maps"][0]["rows"] if r["noise"] == 0}
    for variant, method in (("paper", "paper"), ("lut p≤8", "lut"), ("mlp p≤8", "mlp")):
        cells = _row(text, method)
        assert cells[2] == f"{fit_rows[variant]['alpha_p95']:.4f}" and cells[4] == f"{fit_rows[variant]['g_p95']:.4f}"
    table = {r["variant"]: r for r in results["tables"][MAP]["double"]["rows"]}
    cells = _row(text, "table alone (C, double)")
    assert cells[2] == f"{table['table alone, C, double']['alpha_p95']:.4f}"
    # the noisy level has its own table, and it differs from the noise-free figures
    noisy = {r["variant"]: r for r in results["fit"]["maps"][0]["rows"] if r["noise"] == 0.01}
    assert "at 1 % noise" in text and f"{noisy['lut p≤8']['alpha_p95']:.4f}" in text


def test_the_speed_section_is_bench_fit_s(made):
    _, text, results = made
    speed = results["fit"]["speed"]
    lookup = speed["ms_per_1024"]["bare lookup"]
    assert "### Speed with uncertainty" in text
    assert f"| lut | {speed['ms_per_1024']['lut']:.3g} | {speed['ms_per_1024']['lut'] / lookup:.3g} |" in text


def test_the_device_row_comes_from_the_single_precision_build_and_the_qemu_count(made):
    _, text, results = made
    tables = results["tables"][MAP]
    if not (shutil.which("arm-none-eabi-gcc") and shutil.which("qemu-system-arm") and shutil.which("cc")):
        assert "On the device: not measured (" in text
        return
    device = tables["device"]
    lo, hi = device["ms_per_1024"]
    assert 0 < lo < hi and hi == pytest.approx(1.5 * lo)
    per_bin = device["instructions_per_bin"]
    assert per_bin["calls"] >= 1 and per_bin["bins_per_call"] == 4  # as the device's fit loop calls the core
    assert f"On the device: {per_bin['mean']:,.0f} instructions per bin, fitted 4 per call" in text
    cells = _row(text, report.DEVICE_LABEL)
    assert cells[1] == f"{lo:.0f}–{hi:.0f} (est.)"
    single = next(r for r in tables["single"]["rows"] if r["variant"].startswith("table alone, C"))
    assert "single" in single["variant"] and cells[2] == f"{single['alpha_p95']:.4f}"


def test_the_coverage_table_is_the_uncertainty_bench_s(made):
    _, text, results = made
    r = results["uncertainty"]["rows"][0]
    cells = _row(text, r["case"])
    assert cells[2] == r["mode"] and cells[4].startswith(f"{100 * r['alpha']['within_1sigma']:.0f} %")


def test_without_the_tracer_check_the_page_says_so_and_gives_the_command(made):
    _, text, _ = made
    section = text.split("## The map tracer against Mitsuba 3", 1)[1]
    assert "Not run by this command" in section and "trimeter bench tracer-check" in section


def test_a_tracer_check_result_becomes_its_table_and_figure(tmp_path):
    """The tracer section from a check's rows (made up here: the check itself needs Mitsuba and minutes)."""
    from trimeter.bench.tracer_check import summarise

    rng = np.random.default_rng(1)
    rows = [{"geometry": geometry, "rho": rho, "z": float(z), "tracer": 0.5, "tracer_stderr": 0.001, "volpath": 0.5,
             "volpath_stderr": 0.002, **({"z_iad": float(z) / 2} if geometry == "ideal" else {})}
            for geometry in ("ideal", "device") for rho in (0.02, 0.9) for z in rng.standard_normal(6)]
    summary, ok = summarise(rows, ("ideal", "device"))
    tracer = {"settings": {"materials": 6, "paths": 4096, "spp": 1024}, "seconds": 1.0, "rows": rows,
              "summary": summary, "ok": ok, "mitsuba": "x"}
    png = report._plot_tracer(tracer, tmp_path)
    lines = report._tracer_section(tracer, png, tmp_path / report.PAGE)
    text = "\n".join(lines)
    assert png.read_bytes()[:4] == b"\x89PNG" and "](tracer-z.png)" in text
    device = summary["device"]
    assert f"| device | {device['count']} | {device['mean']:+.2f}" in text
    assert "ideal vs adding-doubling" in text


def test_without_the_polarisation_bench_the_page_says_so_and_gives_the_command(made):
    _, text, results = made
    section = text.split(f"## {report.POLARISATION_HEADING}", 1)[1].split("\n## ", 1)[0]
    assert results["polarisation"] is None
    assert "Not run by this command" in section and "trimeter bench polarisation" in section


@pytest.mark.slow
def test_a_polarisation_result_becomes_its_tables(tmp_path):
    """The section from the bench itself at a tiny size (it needs Mitsuba's polarised variant)."""
    import argparse

    pytest.importorskip("mitsuba")
    from trimeter.bench import polarisation
    from trimeter.forward.mitsuba_env import MitsubaUnavailable

    try:
        pol = polarisation.measure(argparse.Namespace(geometry="ideal", spp=256, slab_spp=4096, materials=2, seed=1))
    except MitsubaUnavailable as exc:
        pytest.skip(str(exc))
    text = "\n".join(report.polarisation_section(pol))
    assert "### ideal (fitted with ideal-n1.5-l0.5)" in text and "closed form 0.1554" in text
    clear = pol["geometries"][0]["fits"][0]
    assert "| clear (0.5, 0.2/mm, 0) | " in text and f"{clear['alpha']['shift']:+.4f}" in text
    assert text.count("| grey (0.6, 2/mm, 0.3) |") == 1 and "Beyond the map's error:" in text


@pytest.mark.parametrize("argv, message", [(["--noise", "0.01"], "including 0"), (["--noise", "a"], "not a comma"),
                                           (["--repeats", "0"], "at least 1"),
                                           (["--sensor-noise", "0.6"], "--sensor-noise"),
                                           (["--tracer-materials", "-1"], "≥ 0"),
                                           (["--polarisation-spp", "3"], "--polarisation-spp")])
def test_bad_settings_are_refused_before_anything_runs(tmp_path, capsys, argv, message):
    assert main(["bench", "report", "--docs", str(tmp_path / "d"), "--work", str(tmp_path / "w"), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "d").exists() and not (tmp_path / "w").exists()


def test_the_committed_page_was_made_by_this_command():
    page = Path(report.__file__).resolve().parents[3] / "docs" / report.PAGE
    if not page.is_file():
        pytest.skip("no docs/validation.md in this checkout")
    text = page.read_text()
    assert "Generated by `trimeter bench report`" in text
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        assert (page.parent / link).is_file(), link


def test_the_builds_table_is_the_sensor_bench_s_for_every_build_it_measured(made):
    page, text, results = made
    section = text.split("## Each build", 1)[1].split("\n## ", 1)[0]
    runs = results["builds"]["runs"]
    assert [r["noise"] for r in runs] == [0.0, 0.01] and "Noise-free:" in section and "With 1 % noise" in section
    for run in runs:
        assert {r["build"] for r in run["builds"]} >= {"ideal spectrometer", "AS7341 band-aware"}
        for r in run["builds"]:  # whatever builds the bench measures, each is a row of its noise level's table
            row = (f"| {r['build']} | {r['materials']} | {r['alpha_p95']:.4f} | {100 * r['sigma_t_rel_p95']:.2f} % | "
                   f"{r['g_p95']:.4f} | {r['flagged']} of {r['values']} (")
            assert row in section
    noisy = {r["id"]: r for r in runs[1]["builds"] if r["materials"] == "all"}
    clean = {r["id"]: r for r in runs[0]["builds"] if r["materials"] == "all"}
    assert noisy["as7341-band-aware"]["alpha_p95"] != clean["as7341-band-aware"]["alpha_p95"]


def test_the_figures_are_written_as_json_beside_the_page_with_its_stamp(made):
    page, text, results = made
    beside = json.loads((page.parent / report.FIGURES_JSON).read_text())
    assert beside == results and beside["stamp"]["commit"][:12] in text
    assert beside["settings"]["sensor_noise"] == "0,0.01"
