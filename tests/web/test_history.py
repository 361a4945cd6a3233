"""The history index: built from the results directories, searched, rebuilt when missing or damaged,
and whole after a writer is killed with SIGKILL mid-insert."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from trimeter.errors import InputError, OutputError
from trimeter.inversion.flags import FitFlag
from trimeter.web.history import History, parse_day_or_time, summarize


def fake_result(root: Path, name: str, *, label=None, flags=(0, 0, 0), written="2026-03-04T05:06:07+00:00") -> Path:
    path = root / name
    path.mkdir(parents=True)
    (path / "measurement.json").write_text(json.dumps({"label": label, "method": "lut", "maps": ["m"],
                                                       "thicknesses_mm": [0.4], "written_utc": written,
                                                       "advice": []}))
    n = len(flags)
    combined = {"wavelength_nm": [400.0 + i for i in range(n)], "alpha": [0.5] * n, "sigma_t": [1.0] * n,
                "g": [0.0] * n, "flags": list(flags)}
    (path / "parameters.json").write_text(json.dumps({"combined": combined, "per_thickness": []}))
    return path


@pytest.fixture
def results(tmp_path):
    root = tmp_path / "results"
    fake_result(root, "20260301T000000Z-red", label="red", written="2026-03-01T00:00:00+00:00")
    fake_result(root, "20260302T000000Z-blue", label="blue", flags=(0, int(FitFlag.UNDERDETERMINED), 0),
                written="2026-03-02T12:00:00+00:00")
    fake_result(root, "20260303T000000Z", written="2026-03-03T00:00:00+00:00")
    (root / ".partial-1-20260304T000000Z").mkdir()      # an interrupted write: not a measurement
    (root / "20260305T000000Z-broken").mkdir()           # no measurement.json: not one either
    return root


def test_the_index_is_built_from_the_directories_and_searched(results, tmp_path):
    history = History(results, tmp_path / "h.sqlite")
    assert "no index yet" in history.open()[0]
    rows, total = history.search()
    assert total == 3 and [r["id"] for r in rows] == ["20260303T000000Z", "20260302T000000Z-blue",
                                                      "20260301T000000Z-red"]
    assert history.search(label="lu")[1] == 1
    assert history.search(label="%")[1] == 0        # LIKE wildcards are text
    assert [r["id"] for r in history.search(flagged=True)[0]] == ["20260302T000000Z-blue"]
    assert history.search(flag="underdetermined")[0][0]["flag_names"] == ["UNDERDETERMINED"]
    assert history.search(since=parse_day_or_time("2026-03-02", "since"),
                          until=parse_day_or_time("2026-03-02", "until", end=True))[1] == 1
    page, total = history.search(limit=2, offset=2)
    assert total == 3 and len(page) == 1
    with pytest.raises(InputError):
        history.search(flag="NO_SUCH")
    for offset in (-1, 10**20):  # beyond SQLite's 64-bit integers: an input error, not an OverflowError
        with pytest.raises(InputError, match="offset"):
            history.search(offset=offset)
    with pytest.raises(InputError):
        parse_day_or_time("tomorrow", "until")


def test_runs_made_meanwhile_are_added_and_removed_ones_dropped(results, tmp_path):
    History(results, tmp_path / "h.sqlite").open()
    fake_result(results, "20260306T000000Z-new", label="new")
    shutil.rmtree(results / "20260301T000000Z-red")
    history = History(results, tmp_path / "h.sqlite")
    assert history.open() == ["history index: 1 measurement(s) added, 1 gone"]
    assert {r["id"] for r in history.search()[0]} == {"20260306T000000Z-new", "20260302T000000Z-blue",
                                                       "20260303T000000Z"}


@pytest.mark.parametrize("damage", ["garbage", "truncated", "other root"])
def test_a_damaged_or_foreign_index_is_rebuilt_from_the_directories(results, tmp_path, damage):
    db = tmp_path / "h.sqlite"
    history = History(results, db)
    history.open()
    history.close()
    if damage == "garbage":
        db.write_bytes(b"this is not a database" * 100)
    elif damage == "truncated":
        data = db.read_bytes()
        db.write_bytes(data[:100] + b"\0" * (len(data) - 100))
    else:
        History(tmp_path / "elsewhere", db).open()
    history = History(results, db)
    notes = history.open()
    assert "built from the results directories" in notes[0]
    assert history.search()[1] == 3


WRITER = """
import sys, time
from pathlib import Path
sys.path.insert(0, {tests!r})
from test_history import fake_result
from trimeter.web.history import History
root, db = Path(sys.argv[1]), Path(sys.argv[2])
history = History(root, db)
history.open()
print("ready", flush=True)
i = 0
while True:  # index directories as fast as possible until killed
    i += 1
    history.add(fake_result(root, f"20270101T{{i // 3600 % 24:02d}}{{i // 60 % 60:02d}}{{i % 60:02d}}Z-n{{i}}"))
"""


def test_the_index_survives_its_writer_killed_mid_insert(results, tmp_path):
    db = tmp_path / "h.sqlite"
    script = tmp_path / "writer.py"
    script.write_text(WRITER.format(tests=str(Path(__file__).parent)))
    writer = subprocess.Popen([sys.executable, str(script), str(results), str(db)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert writer.stdout.readline().strip() == "ready"
        time.sleep(1.0)   # hundreds of inserts under way
        os.kill(writer.pid, signal.SIGKILL)
    finally:
        writer.wait(10)
    con = sqlite3.connect(db)
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    indexed = con.execute("SELECT COUNT(*) FROM measurements").fetchone()[0]
    con.close()
    # the index's own definition of a measurement (a readable measurement.json): the kill can land between or
    # inside fake_result's two plain writes, leaving a directory without one, or one whose parameters.json is
    # short (indexed with no bins)
    on_disk = sum(1 for p in results.iterdir() if summarize(p) is not None)
    assert indexed > 3 and on_disk - indexed <= 1   # at most the directory being indexed when it died
    history = History(results, db)
    assert "built" not in " ".join(history.open())   # reopened, not rebuilt
    assert history.search()[1] == on_disk


def test_an_index_that_cannot_be_written_is_a_clear_error(results, tmp_path, monkeypatch):
    def refuse(self):  # what sqlite says for a read-only data directory (root writes anywhere, so faked)
        raise sqlite3.OperationalError("unable to open database file")

    monkeypatch.setattr(History, "_connect", refuse)
    with pytest.raises(OutputError, match="history index .* cannot be opened"):
        History(results, tmp_path / "h.sqlite").open()
