"""`trimeter serve --show-token / --http / --webhook`: the token is made once, private, and printed
with the page's link; a bad bind address or webhook is a clear error before anything starts."""

from __future__ import annotations

import stat

import pytest

from trimeter.cli import main
from trimeter.web.server import parse_bind
from trimeter.web.auth import load_or_create_token, token_path


@pytest.fixture(autouse=True)
def dirs(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))


def test_show_token_makes_a_private_token_once_and_prints_the_link(capsys):
    assert main(["serve", "--show-token"]) == 0
    first = capsys.readouterr().out
    token = token_path().read_text().strip()
    assert stat.S_IMODE(token_path().stat().st_mode) == 0o600 and len(token) >= 40
    assert f"http://localhost:8080/?token={token}" in first
    assert main(["serve", "--show-token", "--http", "192.168.1.5:9000"]) == 0
    assert f"http://192.168.1.5:9000/?token={token}" in capsys.readouterr().out   # the same token


def test_a_token_file_others_can_read_is_made_private_and_a_broken_one_refused(capsys):
    token = load_or_create_token()
    token_path().chmod(0o644)
    assert load_or_create_token() == token and stat.S_IMODE(token_path().stat().st_mode) == 0o600
    token_path().write_text("short\n")
    assert main(["serve", "--show-token"]) == 2
    assert "not a web token" in capsys.readouterr().err


@pytest.mark.parametrize("text,expected", [("8080", ("127.0.0.1", 8080)), ("0.0.0.0:80", ("0.0.0.0", 80)),
                                           ("[::1]:8080", ("::1", 8080)), ("localhost:0", ("localhost", 0))])
def test_bind_addresses(text, expected):
    assert parse_bind(text) == expected


@pytest.mark.parametrize("args,message", [(["--http", "nonsense"], "--http"), (["--http", "1.2.3.4:99999"], "port"),
                                          (["--http", "127.0.0.1:0", "--webhook", "ftp://x/"], "--webhook")])
def test_bad_options_are_clear_errors(args, message, capsys):
    assert main(["serve", "--port", "/dev/null-none", "--spectrometer", "sim:/dev/null", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error:") and message in err and "Traceback" not in err
