"""Outputs are replaced whole or not at all: a full disk at any stage leaves the previous file as it was
and no temporary file behind; `fit -o` never writes over one of its own inputs."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

import trimeter.atomic as atomic
from trimeter.atomic import atomic_output, atomic_write, same_file
from trimeter.cli import main
from trimeter.errors import OutputError

IDEAL_MAP = Path(__file__).resolve().parents[1] / "inversion" / "data" / "ideal-l0.5.tmap"
MEASUREMENT = "wavelength_nm,I_b,I_w,I_c\n450,0.05,0.4,0.1\n550,0.06,0.45,0.12\n"


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_atomic_write_replaces_the_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "out.csv"
    atomic_write(target, "old\n")
    atomic_write(target, b"new\n")
    assert target.read_text() == "new\n"
    assert [p.name for p in target.parent.iterdir()] == ["out.csv"]
    assert target.stat().st_mode & 0o777 == 0o666 & ~_umask()  # what open() would have given, not mkstemp's 0600
    target.chmod(0o640)
    atomic_write(target, "newer\n")
    assert target.stat().st_mode & 0o777 == 0o640               # a replaced file keeps its permissions


def test_atomic_write_through_a_symlink_replaces_its_target(tmp_path):
    target, link = tmp_path / "real.csv", tmp_path / "link.csv"
    target.write_text("old")
    link.symlink_to(target)
    atomic_write(link, "new")
    assert link.is_symlink() and target.read_text() == "new"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads the umask from /proc")
def test_a_new_file_follows_the_umask_without_changing_it_meanwhile(tmp_path, monkeypatch):
    previous = os.umask(0o027)
    try:
        # setting the umask to learn it would leave another thread's new files unprotected for a moment
        monkeypatch.setattr(atomic.os, "umask", lambda mask: pytest.fail("os.umask called"))
        atomic_write(tmp_path / "new.csv", "x")
    finally:
        monkeypatch.undo()
        os.umask(previous)
    assert (tmp_path / "new.csv").stat().st_mode & 0o777 == 0o640


@pytest.mark.parametrize("stage", ["write", "fsync", "replace"])
def test_full_disk_leaves_the_previous_output_and_no_temporary(tmp_path, monkeypatch, stage):
    target = tmp_path / "params.csv"
    target.write_text("previous\n")
    if stage == "fsync":
        monkeypatch.setattr(atomic.os, "fsync", _enospc)
    elif stage == "replace":
        monkeypatch.setattr(atomic.os, "replace", _enospc)
    with pytest.raises(OutputError, match=r"cannot write .*params\.csv: No space left on device"):
        with atomic_output(target) as f:
            f.write(b"half of the new")
            if stage == "write":
                _enospc()
    assert target.read_text() == "previous\n"
    assert [p.name for p in tmp_path.iterdir()] == ["params.csv"]


def test_an_exception_in_the_writer_is_not_swallowed_and_cleans_up(tmp_path):
    with pytest.raises(ZeroDivisionError):
        with atomic_output(tmp_path / "x.bin") as f:
            f.write(b"abc")
            1 / 0
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_place_is_an_output_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError, match="cannot write"):
        atomic_write(blocker / "out.csv", "x")     # a parent that is a file: fails even as root
    (tmp_path / "adir").mkdir()
    with pytest.raises(OutputError, match="cannot write"):
        atomic_write(tmp_path / "adir", "x")       # a directory in the way
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "file"]


def test_same_file_sees_symlinks_and_hard_links(tmp_path):
    a = tmp_path / "a.csv"
    a.write_text("x")
    os.link(a, tmp_path / "hard.csv")
    (tmp_path / "soft.csv").symlink_to(a)
    assert same_file(a, tmp_path / "hard.csv") and same_file(a, tmp_path / "soft.csv")
    assert same_file(a, tmp_path / "." / "a.csv")
    assert not same_file(a, tmp_path / "b.csv")


# ------------------------------------------------------------------------------------------- fit -o
@pytest.fixture
def measurement_csv(tmp_path):
    path = tmp_path / "meas.csv"
    path.write_text(MEASUREMENT)
    return path


@pytest.mark.parametrize("alias", ["same", "hard", "soft", "dotted"])
def test_fit_refuses_to_write_over_its_input(measurement_csv, capsys, alias):
    out = {"same": measurement_csv, "hard": measurement_csv.with_name("hard.csv"),
           "soft": measurement_csv.with_name("soft.csv"),
           "dotted": measurement_csv.parent / "." / measurement_csv.name}[alias]
    if alias == "hard":
        os.link(measurement_csv, out)
    elif alias == "soft":
        out.symlink_to(measurement_csv)
    assert main(["fit", "--map", str(IDEAL_MAP), "--input", str(measurement_csv), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: -o ") and "is the input" in err and "Traceback" not in err
    assert measurement_csv.read_text() == MEASUREMENT


def test_fit_refuses_to_write_over_its_map(measurement_csv, tmp_path, capsys):
    amap = tmp_path / "copy.tmap"
    amap.write_bytes(IDEAL_MAP.read_bytes())
    assert main(["fit", "--map", str(amap), "--input", str(measurement_csv), "-o", str(amap)]) == 2
    assert "is the input" in capsys.readouterr().err
    assert amap.read_bytes() == IDEAL_MAP.read_bytes()


def test_fit_output_on_a_full_disk_keeps_the_previous_output(measurement_csv, tmp_path, monkeypatch, capsys):
    out = tmp_path / "params.csv"
    assert main(["fit", "--map", str(IDEAL_MAP), "--input", str(measurement_csv), "-o", str(out)]) == 0
    previous = out.read_text()
    assert previous.startswith("wavelength_nm,alpha,")
    monkeypatch.setattr(atomic.os, "fsync", _enospc)
    assert main(["fit", "--map", str(IDEAL_MAP), "--input", str(measurement_csv), "-o", str(out), "--json"]) == 2
    err = capsys.readouterr().err
    assert "trimeter: error: -o: cannot write" in err and "No space left on device" in err
    assert out.read_text() == previous
    assert sorted(p.name for p in tmp_path.iterdir()) == ["meas.csv", "params.csv"]
