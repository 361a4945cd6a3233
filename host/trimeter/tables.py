"""The one reader of trimeter's CSV tables: fit inputs (`trimeter fit --input`), fit outputs and the files of a
results directory (parameters, reflectances, raw spectra, calibration).

A table is one header line of column names, then rows of numbers separated by commas. Blank lines and
lines starting with `#` are skipped, a UTF-8 byte-order mark is ignored, empty cells and "nan" are
missing values (NaN). Only the columns asked for are parsed (a fit's output has a text column,
thickness_mm "0.4+0.8"); a cell that is not a number is an InputError naming its file line and column.
Files are opened only if they are regular files within a size limit (a FIFO or /dev/zero would block
or never end), and, where asked, not symbolic links.

`TableReader` reads in chunks of rows, so a caller can stream a table of any length in bounded memory;
`read_columns` reads it whole. Rows are parsed by numpy's C reader; a chunk it refuses (empty cells,
quoted or ragged rows) is parsed again cell by cell, which gives the same numbers (both round to the
nearest double) and the exact place of a bad cell.
"""

from __future__ import annotations

import csv
import math
import os
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO

import numpy as np

from trimeter.errors import InputError
from trimeter.validation import shown

MAX_RESULT_FILE_BYTES = 50_000_000   # any one file of a results directory, a parameters file to export
DEFAULT_CHUNK_ROWS = 65_536


def open_checked(path: str | Path, *, max_bytes: int, what: str = "", follow_symlinks: bool = True,
                 binary: bool = False) -> IO:
    """`path` opened for reading if it is a regular file of at most `max_bytes` (and, unless
    `follow_symlinks`, not a symbolic link); InputError naming it otherwise. `what` prefixes messages
    (e.g. "--input")."""
    path = Path(path)
    name = f"{what} {path}".strip()
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)  # opening a FIFO must not wait for a writer
    if not follow_symlinks:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    try:
        if not follow_symlinks and path.is_symlink():
            raise InputError(f"{name}: is a symbolic link; refusing to follow it")
        fd = os.open(path, flags)
    except OSError as exc:
        raise InputError(f"{name}: cannot read ({exc.strerror or exc})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputError(f"{name}: not a regular file (a directory, FIFO or device); refusing to read it")
        if info.st_size > max_bytes:
            raise InputError(f"{name}: {info.st_size} bytes, more than the {max_bytes} such a file may have")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb") if binary else os.fdopen(fd, "r", encoding="utf-8-sig", newline="")
    except BaseException:
        os.close(fd)
        raise


def read_text(path: str | Path, *, max_bytes: int = MAX_RESULT_FILE_BYTES, what: str = "",
              follow_symlinks: bool = True) -> str:
    """A whole text file through `open_checked`'s checks (UTF-8)."""
    with open_checked(path, max_bytes=max_bytes, what=what, follow_symlinks=follow_symlinks) as f:
        try:
            text: str = f.read(max_bytes + 1)
        except UnicodeDecodeError:
            raise InputError(f"{what} {path}: not a UTF-8 text file".strip()) from None
    if len(text.encode("utf-8")) > max_bytes:  # it grew since it was opened
        raise InputError(f"{what} {path}: more than the {max_bytes} bytes such a file may have".strip())
    return text


class TableReader:
    """A CSV table's header and its rows in chunks of at most `chunk_rows` (as float columns).

    `required` columns must be in the header; `optional` ones are read when there (None: every other
    column of the header). Use as a context manager, or call `close`.
    """

    def __init__(self, path: str | Path, *, required: Sequence[str] = (), optional: Sequence[str] | None = None,
                 max_bytes: int = MAX_RESULT_FILE_BYTES, what: str = "", follow_symlinks: bool = True,
                 chunk_rows: int = DEFAULT_CHUNK_ROWS) -> None:
        self.path = Path(path)
        self.name = f"{what} {self.path}".strip()
        self.chunk_rows = int(chunk_rows)
        self._file = open_checked(path, max_bytes=max_bytes, what=what, follow_symlinks=follow_symlinks)
        self.size_bytes = os.fstat(self._file.fileno()).st_size
        self.rows_read = 0
        self._line = 0
        try:
            header_line = self._next_content_line()
            self.header = [h.strip() for h in next(csv.reader([header_line or ""]), [])] if header_line else []
        except UnicodeDecodeError:
            self.close()
            raise InputError(f"{self.name}: not a UTF-8 text file") from None
        except csv.Error as exc:
            self.close()
            raise InputError(f"{self.name}: not a readable CSV ({exc})") from None
        duplicated = sorted({h for h in self.header if self.header.count(h) > 1})
        missing = [c for c in required if c not in self.header]
        if duplicated or missing:
            self.close()
            if duplicated:
                raise InputError(f"{self.name}: column(s) {', '.join(map(shown, duplicated))} appear more than once")
            raise InputError(f"{self.name}: missing column(s) {', '.join(missing)} (have: "
                             f"{', '.join(map(shown, self.header)) or 'none'})")
        wanted = list(required) + [c for c in (self.header if optional is None else optional)
                                   if c in self.header and c not in required]
        self.columns = [c for c in wanted if c]
        self._index = [self.header.index(c) for c in self.columns]

    def __enter__(self) -> TableReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    def _next_content_line(self) -> str | None:
        for line in self._file:
            self._line += 1
            if line.strip() and not line.lstrip().startswith("#"):
                return line
        return None

    def chunks(self) -> Iterator[dict[str, np.ndarray]]:
        """The rows in chunks: {column: float array}, each of at most chunk_rows rows (none when empty)."""
        while True:
            lines, numbers = [], []
            try:
                for line in self._file:
                    self._line += 1
                    if line.strip() and not line.lstrip().startswith("#"):
                        lines.append(line)
                        numbers.append(self._line)
                        if len(lines) == self.chunk_rows:
                            break
            except UnicodeDecodeError:
                raise InputError(f"{self.name}: not a UTF-8 text file") from None
            if not lines:
                return
            table = self._parse(lines, numbers)
            self.rows_read += len(lines)
            yield {c: table[:, i] for i, c in enumerate(self.columns)}

    def _parse(self, lines: list[str], numbers: list[int]) -> np.ndarray:
        if not self._index:
            return np.empty((len(lines), 0))
        try:
            table = np.loadtxt(lines, delimiter=",", usecols=self._index, ndmin=2, comments=None, dtype=float,
                               quotechar=None, encoding=None)
            if table.shape == (len(lines), len(self._index)):
                return table
        except ValueError:
            pass
        return self._parse_cells(lines, numbers)

    def _parse_cells(self, lines: list[str], numbers: list[int]) -> np.ndarray:
        """Cell by cell with the csv module: empty or absent cells are NaN; a bad cell is an InputError."""
        table = np.empty((len(lines), len(self._index)))
        try:
            rows = csv.reader(lines)
            for r, row in enumerate(rows):
                for j, (column, i) in enumerate(zip(self.columns, self._index, strict=True)):
                    cell = row[i].strip() if i < len(row) else ""
                    try:
                        table[r, j] = float(cell) if cell else math.nan
                    except ValueError:
                        raise InputError(f"{self.name}: line {numbers[r]}, column {column}: {shown(cell)} is not "
                                         f"a number") from None
        except csv.Error as exc:  # e.g. a field over the csv module's limit, a NUL byte
            raise InputError(f"{self.name}: not a readable CSV ({exc})") from None
        return table


def read_columns(path: str | Path, *, required: Sequence[str] = (), optional: Sequence[str] | None = None,
                 max_bytes: int = MAX_RESULT_FILE_BYTES, what: str = "", follow_symlinks: bool = True,
                 min_rows: int = 1) -> dict[str, np.ndarray]:
    """A whole CSV table as {column: float array} (TableReader's rules); InputError when it has fewer
    than `min_rows` data rows."""
    with TableReader(path, required=required, optional=optional, max_bytes=max_bytes, what=what,
                     follow_symlinks=follow_symlinks) as reader:
        parts = list(reader.chunks())
        columns, name, rows = reader.columns, reader.name, reader.rows_read
    if rows < min_rows:
        raise InputError(f"{name}: no data rows" if rows == 0 else f"{name}: {rows} data row(s), at least {min_rows} "
                                                                   f"expected")
    return {c: np.concatenate([p[c] for p in parts]) if parts else np.empty(0) for c in columns}

