"""`trimeter bench http`: a short run against a real `serve --http` on the twin answers every request;
bad bounds are refused before anything starts."""

from __future__ import annotations

import json

from trimeter.cli import main


def test_a_short_load_is_answered_and_reported(tmp_path, capsys):
    out = tmp_path / "http.json"
    assert main(["bench", "http", "--clients", "4", "--seconds", "1", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["requests"] > 20 and report["errors"] == 0
    assert report["server_state"] != "connecting"   # measured against a connected instrument loop
    assert 0 < report["p50_ms"] <= report["p95_ms"] <= report["p99_ms"] <= report["max_ms"]
    assert "requests/s" in capsys.readouterr().out


def test_bounds_are_refused(capsys):
    assert main(["bench", "http", "--clients", "0"]) == 2
    assert main(["bench", "http", "--seconds", "-1"]) == 2
    assert "trimeter: error: --seconds" in capsys.readouterr().err
