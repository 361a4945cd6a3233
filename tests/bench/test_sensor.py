"""`trimeter bench sensor`: one run prints every build's accuracy and writes it as JSON; the band-aware
AS7341 fit beats the per-channel one on the inks, the spectrometers beat both."""

from __future__ import annotations

import json

from trimeter.cli import main


def test_bench_sensor_reports_every_build(tmp_path, capsys):
    assert main(["bench", "sensor", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    doc = json.loads((tmp_path / "sensor.json").read_text())
    rows = {(r["build"], r["materials"]): r for r in doc["builds"]}
    builds = {b for b, _ in rows}
    assert builds == {"ideal spectrometer", "seabreeze (slit)", "c12880ma", "AS7341 per-channel",
                      "AS7341 per-channel at centroids", "AS7341 band-aware"}
    assert all(b in printed for b in builds)
    band, per_channel = rows["AS7341 band-aware", "inks"], rows["AS7341 per-channel", "inks"]
    ideal = rows["ideal spectrometer", "inks"]
    for key in ("alpha_p95", "sigma_t_rel_p95"):
        assert ideal[key] < band[key] < per_channel[key]
    assert band["alpha_p95"] < 0.01 and band["sigma_t_rel_p95"] < 0.02 and band["g_p95"] < 0.03
    assert band["flagged"] * 8 <= band["values"]
    # the micro-spectrometer: its 12 nm blur costs accuracy against a fine spectrometer, far less than bands
    chip = rows["c12880ma", "all"]
    ideal_all, per_channel_all = rows["ideal spectrometer", "all"], rows["AS7341 per-channel", "all"]
    assert ideal_all["alpha_p95"] < chip["alpha_p95"] < per_channel_all["alpha_p95"]
    assert chip["alpha_p95"] < 0.01 and chip["sigma_t_rel_p95"] < 0.01 and chip["flagged"] == 0
    assert {r["basis smoothness"] for r in doc["bases"]} >= {"cubic 0.03", "linear 0.03"}


def test_bench_sensor_bad_options(capsys):
    assert main(["bench", "sensor", "--thickness", "0.5"]) == 2
    assert "--thickness" in capsys.readouterr().err
