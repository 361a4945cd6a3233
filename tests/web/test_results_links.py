"""The web API serves only what is really in the results root: a results directory or a file replaced by a
symbolic link (to /etc, say) or a FIFO is not found, never followed, read or waited on; the history never
indexes a linked directory; the token file is never reached through a link."""

from __future__ import annotations

import io
import json
import os
import stat
import zipfile

import pytest

from conftest import idle_web
from trimeter.cli import main
from trimeter.errors import InputError
from trimeter.web.auth import load_or_create_token, token_path

LINKED = "20261206T020005Z-x5"
REAL = "20261206T020006Z-real"


def _record(directory, label: str) -> None:
    directory.mkdir(parents=True)
    (directory / "measurement.json").write_text(json.dumps({"label": label, "thicknesses_mm": [0.4], "maps": []}))
    (directory / "parameters.json").write_text(json.dumps({"combined": {"flags": [0, 0]}}))


@pytest.fixture(scope="module")
def web(tmp_path_factory):
    root = tmp_path_factory.mktemp("links")
    secret = root / "outside"
    _record(secret, "outside")
    (secret / "shadow").write_text("root:secret\n")
    results = root / "results"
    _record(results / REAL, "real")
    (results / LINKED).symlink_to(secret, target_is_directory=True)
    (results / REAL / "shadow").symlink_to(secret / "shadow")
    os.mkfifo(results / REAL / "raw_black.csv")
    with idle_web(root) as instrument:
        yield instrument


@pytest.mark.parametrize("path", [f"/api/measurements/{LINKED}", f"/api/measurements/{LINKED}/files/shadow",
                                  f"/api/measurements/{LINKED}/files/measurement.json",
                                  f"/api/measurements/{LINKED}/zip", f"/api/measurements/{REAL}/files/shadow",
                                  f"/api/measurements/{REAL}/files/raw_black.csv"])
def test_a_linked_directory_or_file_and_a_fifo_are_not_found(web, path):
    answer = web.call("GET", path, timeout=10)
    assert answer.status == 404, answer.body
    assert b"root:secret" not in answer.body


def test_the_real_record_is_served_without_its_link_or_fifo(web):
    details = web.call("GET", f"/api/measurements/{REAL}").json
    assert details["files"] == ["measurement.json", "parameters.json"]
    archive = zipfile.ZipFile(io.BytesIO(web.call("GET", f"/api/measurements/{REAL}/zip", timeout=10).body))
    assert sorted(archive.namelist()) == [f"{REAL}/measurement.json", f"{REAL}/parameters.json"]
    assert json.loads(web.call("GET", f"/api/measurements/{REAL}/files/measurement.json").body)["label"] == "real"


def test_the_history_does_not_index_a_linked_directory(web):
    ids = [row["id"] for row in web.call("GET", "/api/measurements").json["measurements"]]
    assert ids == [REAL]


@pytest.fixture
def dirs(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    return tmp_path


def test_a_link_in_place_of_the_token_file_is_refused_and_its_target_untouched(dirs, capsys):
    victim = dirs / "victim"
    victim.write_text("not yours\n")
    victim.chmod(0o644)
    token_path().parent.mkdir(parents=True)
    token_path().symlink_to(victim)
    with pytest.raises(InputError, match="symbolic link"):
        load_or_create_token()
    assert stat.S_IMODE(victim.stat().st_mode) == 0o644 and victim.read_text() == "not yours\n"
    assert main(["serve", "--show-token"]) == 2 and "symbolic link" in capsys.readouterr().err
    token_path().unlink()
    token_path().symlink_to(dirs / "dangling")  # a dangling link is not created through either
    with pytest.raises(InputError):
        load_or_create_token()
    assert not (dirs / "dangling").exists()


def test_a_fifo_in_place_of_the_token_file_is_refused_at_once(dirs):
    token_path().parent.mkdir(parents=True)
    os.mkfifo(token_path())
    with pytest.raises(InputError, match="not a regular file"):
        load_or_create_token()
