"""`trimeter bench bus`: bad options are one clear error; a small run prints and writes the figures."""

from __future__ import annotations

import json

import pytest

from trimeter.cli import main


@pytest.mark.parametrize("args,message", [(["--instruments", "1"], "--instruments must be within 2..32"),
                                          (["--rounds", "0"], "--rounds must be within 1..20")])
def test_bad_options_are_one_clear_error(args, message, capsys):
    assert main(["bench", "bus", *args]) == 2
    assert message in capsys.readouterr().err


def test_two_instruments_on_one_bus_against_their_own_ports(tmp_path, capsys):
    out = tmp_path / "bus.json"
    # the harness, not the figures: the twin at 200x (the bench's 50x only slows it)
    assert main(["bench", "bus", "--instruments", "2", "--rounds", "1", "--time-scale", "200", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "the bus's own cost (one bus / own ports)" in printed
    figures = json.loads(out.read_text())
    rows = figures["rows"]
    assert figures["instruments"] == 2 and rows["alone"]["cycle_s"] > 0
    for name in ("on one bus", "each on its own port"):
        assert rows[name]["cycle_s"] > 0 and rows[name]["slowest_s"] >= rows[name]["cycle_s"]
    assert rows["bus_cost"] == pytest.approx(rows["on one bus"]["cycle_s"] / rows["each on its own port"]["cycle_s"],
                                             abs=0.01)
    assert all(link["bus_wait_s"] > 0 and link["requests"] > 0 for link in figures["links"])
