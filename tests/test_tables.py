"""trimeter.tables, the one reader of CSV tables: numpy's fast path and the cell-by-cell path give the same
doubles (Python's float()), missing cells are NaN, bad cells name their file line and column, and files
that are not regular, too large or (where asked) symbolic links are refused."""

from __future__ import annotations

import os

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.tables import TableReader, read_columns, read_text


def _write(tmp_path, text, name="t.csv"):
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def test_the_fast_and_the_cell_path_read_the_same_doubles(tmp_path):
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(size=300) * 10.0 ** rng.integers(-300, 300, 300), [0.0, -0.0, 1e-320]])
    texts = [f"{v:.17g}" if i % 3 == 0 else f"{v:.6e}" if i % 3 == 1 else repr(float(v)) for i, v in
             enumerate(values)]
    clean = _write(tmp_path, "x,y\n" + "".join(f"{t},{t}\n" for t in texts), "clean.csv")
    # a quoted cell sends the chunk down the cell-by-cell path
    quoted = _write(tmp_path, "x,y\n" + "".join(f"{t},{t}\n" for t in texts) + '"1",2\n', "quoted.csv")
    fast, slow = read_columns(clean), read_columns(quoted)
    expected = np.array([float(t) for t in texts])
    np.testing.assert_array_equal(fast["x"], expected)
    np.testing.assert_array_equal(slow["x"][:-1], expected)
    assert slow["x"][-1] == 1.0


def test_missing_cells_comments_bom_and_only_the_asked_columns(tmp_path):
    path = _write(tmp_path, "\ufeff# a comment\n a , b ,label\n\n1,,0.4+0.8\n# another\n2, nan ,x\n3\n")
    got = read_columns(path, required=("a",), optional=("b", "absent"))
    assert list(got) == ["a", "b"]          # the text column is never parsed
    np.testing.assert_array_equal(got["a"], [1, 2, 3])
    assert np.isnan(got["b"]).all()


@pytest.mark.parametrize("text, message", [
    ("a,b\n1,2\n# c\n\n3,x\n", "line 5, column b: 'x' is not a number"),
    ("a,a\n1,2\n", "column(s) 'a' appear more than once"),
    ("a\n1\n", "missing column(s) b (have: 'a')"),
    ("", "missing column(s) a, b (have: none)"),
    ("a,b\n", "no data rows"),
    ("a,b\n1,\x002\n", "line 2, column b: '\\x002' is not a number"),
    (b"a,b\n1,\xff\n", "not a UTF-8 text file"),
])
def test_bad_tables_are_one_clear_error(tmp_path, text, message):
    with pytest.raises(InputError) as caught:
        read_columns(_write(tmp_path, text), required=("a", "b"))
    assert message in str(caught.value) and str(tmp_path) in str(caught.value)


def test_chunks_cover_every_row_once(tmp_path):
    path = _write(tmp_path, "a\n" + "".join(f"{i}\n" for i in range(1000)) + "x\n")
    with TableReader(path, required=("a",), chunk_rows=64) as table:
        chunks = table.chunks()
        sizes = [len(next(chunks)["a"]) for _ in range(15)]
        with pytest.raises(InputError, match="line 1002, column a"):
            next(chunks)  # the bad row is in the last chunk: reported there, with its line
    assert sizes == [64] * 15


def test_unsafe_files_are_refused(tmp_path):
    path = _write(tmp_path, "a\n1\n")
    link = tmp_path / "link.csv"
    link.symlink_to(path)
    assert read_columns(link)["a"][0] == 1.0
    with pytest.raises(InputError, match="symbolic link"):
        read_columns(link, follow_symlinks=False)
    with pytest.raises(InputError, match="more than the 3 such a file may have"):
        read_columns(path, max_bytes=3)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        read_text(fifo)   # without waiting for a writer
    with pytest.raises(InputError, match="not a regular file"):
        read_text("/dev/zero")
    with pytest.raises(InputError, match="not a regular file"):
        read_text(tmp_path)
    with pytest.raises(InputError, match="cannot read"):
        read_text(tmp_path / "absent")


def test_the_calibration_reads_through_it(tmp_path):
    from trimeter.domain import Calibration

    with pytest.raises(InputError, match="no calibration in"):
        Calibration.load(tmp_path)
    wl = np.linspace(400, 700, 5)
    cal = Calibration(wl, np.full(5, 1e6), np.full(5, 2e6), np.full(5, 0.03), 0.99, np.zeros(5, np.int32))
    cal.save(tmp_path)
    back = Calibration.load(tmp_path)
    np.testing.assert_array_equal(back.wavelengths_nm, wl)
    assert back.flags.dtype == np.int32 and back.rho_white == 0.99
    text = (tmp_path / "calibration.csv").read_text().splitlines()
    (tmp_path / "calibration.csv").write_text("\n".join(text[:3] + ["401,x"] + text[4:]) + "\n")
    with pytest.raises(InputError, match="is corrupt .*line 4, column diffuse_counts_per_s"):
        Calibration.load(tmp_path)
    (tmp_path / "calibration.csv").write_text("\n".join(text[:-1]) + "\n")
    with pytest.raises(InputError, match="unknown format or is truncated"):
        Calibration.load(tmp_path)


def test_rows_are_counted_without_columns_asked(tmp_path):
    path = _write(tmp_path, "a,b\n1,2\n3,4\n")
    assert read_columns(path, optional=("c",), min_rows=2) == {}
    with pytest.raises(InputError, match="2 data row.s., at least 3 expected"):
        read_columns(path, optional=("c",), min_rows=3)
