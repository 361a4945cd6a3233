"""tools/gen_docs.py: the reference pages cover every command, endpoint, flag and file kind, and
--check fails on a stale page without writing."""

from __future__ import annotations

import argparse
import os
import re

import pytest

from tools import gen_docs
from trimeter.cli import build_parser
from trimeter.inversion.flags import FitFlag
from trimeter.web.openapi import openapi


def _commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("trimeter",)):
    for name, child in gen_docs._subparsers(parser).items():
        yield (*path, name)
        yield from _commands(child, (*path, name))


def test_every_command_and_option_is_in_the_cli_page():
    page = gen_docs.cli_page()
    parser = build_parser()
    commands = list(_commands(parser))
    assert len(commands) > 20
    for command in commands:
        assert f"`{' '.join(command)}`" in page, command
    fit = gen_docs._subparsers(parser)["fit"]
    for action in fit._actions:
        for option in action.option_strings:
            if option not in ("-h", "--help"):
                assert f"`{option}" in page, option


def test_help_text_is_prose_and_its_indented_usage_is_code():
    text = """`trimeter x`: does things [--flag].

      trimeter x A [--notes TEXT]    # an example
      trimeter x B

    More prose, `[kept]` in code."""
    md = gen_docs._prose(text)
    assert "does things \\[--flag\\]." in md                 # not a Markdown link
    assert "```text\ntrimeter x A [--notes TEXT]    # an example\ntrimeter x B\n```" in md
    assert "`[kept]`" in md


def test_every_endpoint_is_in_the_http_page():
    page = gen_docs.http_page()
    for path, operations in openapi()["paths"].items():
        for method in operations:
            assert f"## `{method.upper()} {path}`" in page


def test_every_flag_has_its_meaning_and_advice():
    page = gen_docs.flags_page()
    for flag in FitFlag:
        if flag.value:
            rows = [line for line in page.splitlines() if f"`{flag.name}`" in line]
            assert len(rows) == 2, flag.name          # the meaning table and the advice table
            assert not rows[0].rstrip().endswith("|  |"), f"{flag.name} has no meaning"
    assert "second thickness" in page                 # UNDERDETERMINED's advice, from flags.advice


def test_host_settings_page_lists_every_setting_and_environment_variable():
    import dataclasses

    from trimeter.sequences.settings import HostSettings

    page = gen_docs.settings_page()
    for f in dataclasses.fields(HostSettings):
        assert f"| `{f.name}` |" in page, f.name
    assert "| `TRIMETER_DATA_DIR` |" in page and "| `TRIMETER_KERNEL` |" in page
    assert "&lt;data dir&gt;" in page          # `<data dir>` in a comment is shown, not taken for HTML


def test_file_formats_page_states_the_schemas():
    from trimeter.formats.appearance import MAP_SCHEMA
    from trimeter.formats.inscatter_file import INSCATTER_SCHEMA

    page = gen_docs.formats_page()
    for schema in (MAP_SCHEMA, INSCATTER_SCHEMA):
        for name in schema.arrays:
            assert re.search(rf"^\| `{name}` \|", page, re.M), name
    assert "b\"\\\\x89TRLUT" in page or "TRLUT" in page     # the device table's layout
    assert "`I_b_std`" in page and "`sigma_t_beer`" in page


def test_no_machine_specific_text(monkeypatch):
    monkeypatch.setenv("HOME", "/nonexistent-home")
    for make in gen_docs.PAGES.values():
        text = make()
        assert "/nonexistent-home" not in text
        assert str(gen_docs.ROOT) not in text
        assert f"{os.cpu_count()} cores" not in text     # `map build --workers` states the machine's cores


def test_check_names_a_stale_page_and_writes_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(gen_docs, "OUT_DIR", tmp_path)
    assert gen_docs.main([]) == 0
    assert gen_docs.main(["--check"]) == 0
    stale = tmp_path / "flags.md"
    stale.write_text(stale.read_text(encoding="utf-8") + "edited by hand\n", encoding="utf-8")
    assert gen_docs.main(["--check"]) == 1
    assert "flags.md" in capsys.readouterr().err
    assert stale.read_text(encoding="utf-8").endswith("edited by hand\n")


@pytest.mark.parametrize("name", sorted(gen_docs.PAGES))
def test_committed_pages_are_current(name):
    assert (gen_docs.OUT_DIR / name).read_text(encoding="utf-8") == gen_docs.PAGES[name](), \
        f"docs/reference/{name} is stale: run `python -m tools.gen_docs`"
