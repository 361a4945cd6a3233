"""Hostile inputs to the CLI give one clear error line and exit 2 (a closed pipe: a quiet exit),
never a traceback: config backups (size, nesting, huge values), fit's CSV (duplicated columns, a
field over the csv module's limit) and the output streams (`| head -1`, `> /dev/full`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from trimeter.cli import main
from trimeter.device.backup import MAX_BACKUP_BYTES, MAX_NESTING, nesting_depth, parse_config
from trimeter.errors import InputError

IDEAL_MAP = Path(__file__).parents[1] / "inversion" / "data" / "ideal-l0.5.tmap"


def _error_line(capsys, argv) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: ") and err.count("\n") == 1 and "Traceback" not in err
    return err


# ------------------------------------------------------------------------------------ config import
@pytest.mark.parametrize("text, says", [
    ("[device]\nspeed_mm_s = " + "[" * 5000 + "]" * 5000 + "\n", f"nested deeper than {MAX_NESTING}"),
    ("[device]\nspeed_mm_s = \"" + "x" * 10_000_000 + "\"\n", "is not a number or a name"),
    ("[device]\n" + "y" * 5_000_000 + " = 1\n", "none of its items"),
    ("[device]\nspeed_mm_s = " + "9" * 5000 + "\n", "not a configuration backup"),
    ("[device]\nspeed_mm_s = 99999999999999999999\n", "is not a number or a name"),  # beyond 64 bits
    ("[device]\nspeed_mm_s = inf\n", "is not a number or a name"),
    ("[device]\nspeed_mm_s = nan\n", "is not a number or a name"),
    ("\0\xff", "not a configuration backup"),
], ids=["5000-deep array", "10 MB string", "5 MB name", "5000-digit integer", "over 64 bits", "inf", "nan",
        "binary"])
def test_hostile_backup_is_one_short_error(tmp_path, capsys, text, says):
    path = tmp_path / "backup.toml"
    path.write_text(text) if len(text) <= MAX_BACKUP_BYTES else path.write_text(text[:MAX_BACKUP_BYTES - 100] + "\n")
    if len(text) <= MAX_BACKUP_BYTES:
        with pytest.raises(InputError, match=says) as err:
            parse_config(text, "backup.toml")
        assert len(str(err.value)) < 400
    err = _error_line(capsys, ["config", "import", str(path), "--port", "/nonexistent"])
    assert len(err) < 400


def test_oversized_backup_is_refused_before_it_is_read(tmp_path, capsys):
    path = tmp_path / "backup.toml"
    with open(path, "wb") as f:
        f.truncate(1 << 30)
    err = _error_line(capsys, ["config", "import", str(path), "--port", "/nonexistent"])
    assert "larger than any configuration backup" in err


def test_nesting_depth_ignores_brackets_in_strings_and_comments():
    text = '[device]\na = [1, [2]]\nb = "[[[[\\"[["\n# [[[[[[[[[\nc = \'\'\'[[[\n[[\'\'\'\nd = {x = {y = 1}}\n'
    assert nesting_depth(text) == 2


# ------------------------------------------------------------------------------------- fit's CSV
def test_duplicated_csv_columns_are_an_error_naming_them(tmp_path, capsys):
    csv = tmp_path / "m.csv"
    csv.write_text("wavelength_nm,I_b,I_w,I_c,I_b\n500,0.1,0.5,0.3,0.2\n")
    err = _error_line(capsys, ["fit", "--map", str(IDEAL_MAP), "--input", str(csv)])
    assert "'I_b' appear more than once" in err


def test_csv_field_over_the_csv_limit_is_an_error(tmp_path, capsys):
    csv = tmp_path / "m.csv"
    csv.write_text('wavelength_nm,I_b,I_w,I_c\n500,"' + "1" * 200_000 + '",0.5,0.3\n')
    err = _error_line(capsys, ["fit", "--map", str(IDEAL_MAP), "--input", str(csv)])
    assert "not a readable CSV" in err and "field larger than field limit" in err


def test_huge_csv_cell_is_not_echoed(tmp_path, capsys):
    csv = tmp_path / "m.csv"
    csv.write_text("wavelength_nm,I_b,I_w,I_c\n500," + "x" * 100_000 + ",0.5,0.3\n")
    err = _error_line(capsys, ["fit", "--map", str(IDEAL_MAP), "--input", str(csv)])
    assert "column I_b" in err and len(err) < 300


# ----------------------------------------------------------------------------------------- streams
def _trimeter(*args, **kwargs):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2] / "host")}
    return subprocess.Popen([sys.executable, "-m", "trimeter", *args], stderr=subprocess.PIPE, env=env, **kwargs)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_full_disk_on_stdout_is_one_error_line():
    with open("/dev/full", "w") as full:
        proc = _trimeter("map", "info", str(IDEAL_MAP), "--json", stdout=full)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert err.decode().startswith("trimeter: error: ") and "No space left" in err.decode()
    assert b"Traceback" not in err and err.count(b"\n") == 1


def test_closed_pipe_exits_quietly():
    proc = _trimeter("map", "info", str(IDEAL_MAP), "--json", stdout=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before anything is written, as with `| head -0`
    err = proc.stderr.read()
    proc.wait(timeout=60)
    assert err == b"" and proc.returncode == 141
