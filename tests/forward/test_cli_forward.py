"""`trimeter forward` input checking (no rendering: every case fails before Mitsuba is touched)."""

import json

import pytest

from trimeter.cli import main

GOOD = ["forward", "--geometry", "ideal", "--alpha", "0.9", "--sigma-t", "2", "--g", "0.5", "--thickness", "0.5",
        "--n", "1.5", "--rho-b", "0.02", "--rho-w", "0.99"]


def _with(flag, value):
    args = list(GOOD)
    args[args.index(flag) + 1] = value
    return args


@pytest.mark.parametrize("flag,value,message", [
    ("--n", "0.9", "--n must be >= 1"),
    ("--thickness", "0", "--thickness must be > 0"),
    ("--thickness", "-1", "--thickness must be > 0"),
    ("--alpha", "1.01", "--alpha must be <= 1"),
    ("--alpha", "-0.1", "--alpha must be >= 0"),
    ("--g", "1", "--g must be < 1"),
    ("--g", "-1", "--g must be > -1"),
    ("--rho-b", "-0.01", "--rho-b must be >= 0"),
    ("--rho-w", "1.5", "--rho-w must be <= 1"),
    ("--sigma-t", "-2", "--sigma-t must be >= 0"),
    ("--sigma-t", "nan", "--sigma-t must be finite"),
    ("--alpha", "abc", "--alpha must be a number"),
])
def test_bad_value_is_one_line_naming_the_flag(flag, value, message, capsys):
    assert main(_with(flag, value)) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"trimeter: error: {message}, got {value}" or err.startswith(f"trimeter: error: {message}")
    assert "\n" not in err


def test_missing_flag_is_named(capsys):
    args = GOOD[: GOOD.index("--rho-w")]
    assert main(args) == 2
    assert capsys.readouterr().err.strip() == "trimeter: error: --rho-w is required"


def test_bad_spp_is_refused_before_rendering(capsys):
    assert main(GOOD + ["--spp", "3"]) == 2
    assert "--spp" in capsys.readouterr().err


@pytest.mark.slow
def test_json_output_has_the_documented_keys(capsys):
    assert main(GOOD + ["--spp", "4096", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"I_b", "I_w", "I_c", "stderr", "provenance"}
    assert set(out["stderr"]) == {"I_b", "I_w"}
    assert out["provenance"]["spp"] == 4096 and out["provenance"]["engine"] == "volpath"
    assert 0 < out["I_b"] < out["I_w"] < 1 and 0 < out["I_c"] < 1
