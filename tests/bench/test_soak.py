"""`trimeter bench soak` at a few cycles: the operator drives serve on the twin through a calibration and
measurements, every written result is checked against the twin's truth, and the check itself rejects a
result compared with the wrong material (so a garbage count of 0 means something)."""

import json
from pathlib import Path

import numpy as np

from trimeter.bench.soak import is_garbage, print_report, result_errors, run_soak
from trimeter.bench.link import parse_levels
from trimeter.cli import main
from trimeter.twin.optics import material_spectra


def test_a_short_soak_calibrates_measures_and_checks_every_result(tmp_path, capsys):
    # A clean link: this checks the harness (operator, checks, report), which a faulty link's outcome on a
    # loaded machine must not decide; the link's faults have their own tests and `bench link`.
    clean = ((1.0, dict(corrupt=0.0, drop=0.0, late=0.0)),)
    report = run_soak(4, seed=2, time_scale=100.0, root=tmp_path, progress=lambda line: None, link_levels=clean)
    assert report.cycles == 4 and report.calibrations >= 1 and report.results >= 1
    assert report.garbage == [] and len(report.checked) == report.results
    assert report.rss_mb and all(mb > 0 for _, _, mb in report.rss_mb)
    print_report(report)
    out = capsys.readouterr().out
    assert f"cycles 4   results {report.results}" in out and "garbage results: 0" in out

    # the same written result against another material's truth is garbage
    cycle, sample, path, errors = report.checked[0]
    assert not is_garbage(errors)
    wl = np.linspace(400, 750, 200)
    other = "milk" if sample != "milk" else "cyan-ink"
    truth = {"wavelengths_nm": wl, **{k: np.asarray(v, float) for k, v in material_spectra(other, wl).items()
                                       if k in ("alpha", "sigma_t", "g")}}
    assert is_garbage(result_errors(path, truth))
    assert Path(path).parent == tmp_path / "results" and (Path(path) / "parameters.json").is_file()


def test_bench_commands_refuse_bad_arguments(capsys):
    assert main(["bench", "soak", "--cycles", "0"]) == 2
    assert "--cycles must be ≥ 1" in capsys.readouterr().err
    assert main(["bench", "link", "--levels", "0.02+x"]) == 2
    assert "is not CORRUPT[+DROP]" in capsys.readouterr().err
    assert main(["bench", "link", "--levels", "2"]) == 2
    assert "probability" in capsys.readouterr().err
    assert parse_levels("0, 0.01,0.02+0.05") == [(0.0, 0.0), (0.01, 0.0), (0.02, 0.05)]


def test_bench_link_times_a_cold_read_of_the_instruments_table(tmp_path, capsys):
    out = tmp_path / "link.json"
    assert main(["bench", "link", "--levels", "0", "--table", "--time-scale", "200", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert row["table_s"] > 0 and row["table_resumes"] == 0 and "table_error" not in row
    assert "cold table read" in capsys.readouterr().out
