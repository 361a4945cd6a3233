"""Host settings through one schema (trimeter.sequences.settings.SCHEMA) whatever the source — the TOML
file, `config set --host`, `PUT /api/config` — and written by a TOML writer, so no value can make the file
unreadable."""

from __future__ import annotations

import tomllib
from dataclasses import fields

import pytest
from hypothesis import given, settings as hsettings, strategies as st

from trimeter.cli import main
from trimeter.errors import InputError
from trimeter.sequences.settings import SCHEMA, HostSettings, checked
from trimeter.toml_text import toml_table, toml_value


@pytest.fixture(autouse=True)
def dirs(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))


def test_the_schema_covers_every_setting_and_every_default_passes_it():
    assert set(SCHEMA) == {f.name for f in fields(HostSettings)}
    for key, value in HostSettings().as_dict().items():
        assert checked(key, value) == value


REFUSED = [("method", "evil"), ("address", -5), ("address", 0), ("address", 248), ("baudrate", 0),
           ("baudrate", 12345), ("white_reference_reflectance", -1), ("white_reference_reflectance", 5),
           ("attempts", 1e15), ("timeout_s", 1e308), ("frames", 1e9), ("frames", True), ("thickness_mm", True),
           ("local_echo", 2), ("second_map", "x\ny = 1"), ("map", "a\0b"), ("port", "x" * 5000),
           ("frames", 2.5), ("frames", "2.5"), ("frames", "1e3"), ("timeout_s", "nan"), ("timeout_s", float("inf")),
           ("address", 10**400), ("thickness_mm", 0), ("thickness_mm", 1000), ("second_thickness_mm", -0.1),
           ("map", 5), ("frames", "two"), ("frames", None), ("frames", [1]), ("frames", {"a": 1})]


@pytest.mark.parametrize("key,value", REFUSED, ids=[f"{k}={v!r}"[:40] for k, v in REFUSED])
def test_an_impossible_value_is_refused_by_name_and_changes_nothing(key, value):
    settings = HostSettings()
    with pytest.raises(InputError, match=key):
        settings.set(key, value, source="test")
    assert settings == HostSettings()


@pytest.mark.parametrize("key,value,expected", [("address", "247", 247), ("frames", "3", 3), ("frames", 3.0, 3),
                                                ("baudrate", "115200", 115200), ("timeout_s", "0.5", 0.5),
                                                ("white_reference_reflectance", 1, 1.0), ("method", "mlp", "mlp"),
                                                ("second_map", "ünïcode map", "ünïcode map")])
def test_good_values_are_converted(key, value, expected):
    assert checked(key, value) == expected


def test_update_applies_all_or_nothing():
    settings = HostSettings()
    with pytest.raises(InputError, match="address"):
        settings.update({"frames": 5, "address": 0})
    assert settings.frames == HostSettings().frames


def test_the_cli_refuses_a_value_that_would_break_the_file(capsys):
    assert main(["config", "set", "--host", "second_map", "a\nb"]) == 2
    assert "second_map" in capsys.readouterr().err
    assert main(["config", "set", "--host", "second_map", 'a "quoted" \\ map ü']) == 0
    assert main(["config", "set", "--host", "method", "evil"]) == 2
    assert main(["config", "set", "--host", "address", "-5"]) == 2
    assert HostSettings.load().second_map == 'a "quoted" \\ map ü'   # still a file every command reads


def test_a_hand_edited_file_is_checked_on_load():
    HostSettings.path().parent.mkdir(parents=True)
    HostSettings.path().write_text('method = "evil"\n')
    with pytest.raises(InputError, match="method"):
        HostSettings.load()
    HostSettings.path().write_text("frames = true\n")
    with pytest.raises(InputError, match="frames"):
        HostSettings.load()


@hsettings(max_examples=200, deadline=None)
@given(st.text(max_size=40))
def test_any_text_written_reads_back_as_itself(text):
    if any(0xD800 <= ord(c) <= 0xDFFF for c in text):
        with pytest.raises(InputError):
            toml_value(text)
        return
    assert tomllib.loads(toml_table({"key": text, "n": 5, "x": 1e300, "y": 2.0}, "a\ncomment")) == \
        {"key": text, "n": 5, "x": 1e300, "y": 2.0}


def test_the_writer_refuses_what_toml_cannot_hold():
    for bad in (float("nan"), float("inf"), None, [1], object()):
        with pytest.raises(InputError):
            toml_value(bad)
    with pytest.raises(InputError):
        toml_table({"a b": 1})
