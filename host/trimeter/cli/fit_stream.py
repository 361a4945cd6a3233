"""`trimeter fit`'s input and CSV output in chunks of rows: read, fitted and written a chunk at a time, so memory
stays bounded for any number of rows, and the output is the same, bit for bit, as one fit of every row
(each bin is fitted on its own, whatever its place in a batch; the paper method's samples are placed by
the bin's row in the whole input).

The output lists the rows in wavelength order. An input up to WHOLE_INPUT_BYTES is read whole and sorted
(its rows in any order), then fitted and written in chunks; a larger one is streamed and must come in
wavelength order already (`sort -t, -k1,1g` sorts one), checked as it is read. Two thicknesses are
paired row by row within each chunk as in one fit of all rows. Fits that need every row at once (JSON
output: written by column; the instrument's fit) read inputs up to WHOLE_FIT_BYTES whole. Inputs over
MAX_INPUT_BYTES, and anything but a regular file (a FIFO, /dev/zero), are refused before a row is read.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Protocol

import numpy as np

from trimeter.atomic import atomic_output
from trimeter.errors import InputError, OutputError
from trimeter.tables import TableReader

REQUIRED = ("wavelength_nm", "I_b", "I_w", "I_c")
OPTIONAL = ("rho_b", "rho_w", "thickness_mm", "I_b_std", "I_w_std", "I_c_std", "thickness_std_mm")
OUTPUT = ("wavelength_nm", "alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "flags", "sigma_t_beer",
          "thickness_mm")
MAX_INPUT_BYTES = 16_000_000_000    # ~2e8 rows: beyond, split the input
WHOLE_INPUT_BYTES = 32_000_000      # read whole (any row order) up to this; stream (in wavelength order) above
WHOLE_FIT_BYTES = 200_000_000       # the fits that need every row at once (two thicknesses, JSON, on the device)
CHUNK_ROWS = 1 << 16

Chunk = dict[str, np.ndarray]


def reader(path: Path, chunk_rows: int | None = None) -> TableReader:
    """The fit input's table (REQUIRED and OPTIONAL columns), its file checked and size-limited."""
    return TableReader(path, required=REQUIRED, optional=OPTIONAL, max_bytes=MAX_INPUT_BYTES, what="--input",
                       chunk_rows=CHUNK_ROWS if chunk_rows is None else chunk_rows)


def _check_wavelengths(chunk: Chunk, path: Path) -> None:
    if not np.all(np.isfinite(chunk["wavelength_nm"])):
        raise InputError(f"--input {path}: column wavelength_nm has an empty or non-finite value")


def read_whole(path: Path, max_bytes: int | None = None) -> Chunk:
    """Every row of the input as columns (for the fits that need them all at once: JSON output, the
    instrument's fit); an input over `max_bytes` is refused with what to do instead."""
    max_bytes = WHOLE_FIT_BYTES if max_bytes is None else max_bytes
    with reader(path) as table:
        size = table.size_bytes
        if size > max_bytes:
            raise InputError(f"--input {path}: {size} bytes; this fit (--json or --on-device) reads its input "
                             f"whole, up to {max_bytes} bytes: fit with CSV output, which streams inputs of any "
                             f"size")
        parts = list(table.chunks())
        columns = table.columns
    if not parts:
        raise InputError(f"--input {path}: no data rows")
    data = {c: np.concatenate([p[c] for p in parts]) for c in columns}
    _check_wavelengths(data, path)
    return data


def sorted_chunks(path: Path, chunk_rows: int | None = None, whole_bytes: int | None = None) -> Iterator[Chunk]:
    """The input's rows in wavelength order (stable), `chunk_rows` at a time: read whole and sorted up to
    `whole_bytes` (default WHOLE_INPUT_BYTES), streamed above, where a row out of order is an InputError."""
    whole_bytes = WHOLE_INPUT_BYTES if whole_bytes is None else whole_bytes
    chunk_rows = CHUNK_ROWS if chunk_rows is None else chunk_rows
    with reader(path, chunk_rows) as table:
        if table.size_bytes <= whole_bytes:
            parts = list(table.chunks())
            if not parts:
                raise InputError(f"--input {path}: no data rows")
            data = {c: np.concatenate([p[c] for p in parts]) for c in table.columns}
            del parts
            _check_wavelengths(data, path)
            order = np.argsort(data["wavelength_nm"], kind="stable")
            for start in range(0, len(order), chunk_rows):
                rows = order[start:start + chunk_rows]
                yield {c: v[rows] for c, v in data.items()}
            return
        last, rows_read = -math.inf, 0
        for chunk in table.chunks():
            _check_wavelengths(chunk, path)
            wl = chunk["wavelength_nm"]
            if wl[0] < last or np.any(np.diff(wl) < 0):
                at = rows_read + (0 if wl[0] < last else int(np.argmax(np.diff(wl) < 0)) + 1)
                raise InputError(f"--input {path}: data row {at + 1} is out of wavelength order; an input over "
                                 f"{whole_bytes} bytes is streamed and must be sorted by wavelength (e.g. "
                                 f"`sort -t, -k1,1g`, header kept first)")
            last = float(wl[-1])
            rows_read += len(wl)
            yield chunk
        if rows_read == 0:
            raise InputError(f"--input {path}: no data rows")


class FlagTally:
    """The distinct flag words of a streamed fit and how many bins carry each (for its advice)."""

    def __init__(self) -> None:
        self.counts: dict[int, int] = {}

    def add(self, flags: np.ndarray) -> None:
        words, counts = np.unique(np.asarray(flags, np.int64), return_counts=True)
        for word, count in zip(words.tolist(), counts.tolist(), strict=True):
            self.counts[word] = self.counts.get(word, 0) + count

    def advice(self, thicknesses: int = 1) -> list[str]:
        from trimeter.inversion.flags import advice

        return advice(list(self.counts), thicknesses, counts=list(self.counts.values()))


def csv_rows(columns: Chunk, used: str) -> str:
    """The output's rows for a chunk of fitted columns (OUTPUT order; flags as integers, the rest `%.9g`)."""
    cells = [[str(v) for v in np.asarray(columns[k], np.int64).tolist()] if k == "flags"
             else [f"{v:.9g}" for v in np.asarray(columns[k], float).tolist()] for k in OUTPUT[:-1]]
    return "".join(",".join(row) + f",{used}\n" for row in zip(*cells, strict=True))


class ByteSink(Protocol):
    def write(self, data: bytes, /) -> int: ...


@contextmanager
def output(path: Path | None) -> Iterator[ByteSink]:
    """Where the CSV goes: stdout, or `path` replaced atomically when every row is written (an error part
    way leaves the old file, or none)."""
    if path is None:
        sys.stdout.flush()  # anything printed before goes first
        yield sys.stdout.buffer if hasattr(sys.stdout, "buffer") else _TextSink(sys.stdout)
        sys.stdout.flush()
        return
    try:
        with atomic_output(path) as f:
            yield f
    except OutputError as exc:
        raise OutputError(f"-o: {exc}") from None


class _TextSink:
    """A text stream (pytest's captured stdout) taking the bytes a binary one would."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream

    def write(self, data: bytes) -> int:
        return self.stream.write(data.decode("utf-8"))


def fit_csv(path: Path, out: Path | None, fit_chunk: Callable[[Chunk], Chunk], used: str, *,
            chunk_rows: int | None = None, whole_bytes: int | None = None,
            regroup: Callable[[Iterator[Chunk]], Iterator[Chunk]] | None = None) -> FlagTally:
    """Fit the input `path` chunk by chunk with `fit_chunk` (input columns → OUTPUT columns but the last) and
    write the CSV to `out` (None: stdout); returns the flags' tally. `regroup` re-cuts the sorted chunks
    (e.g. so that each holds whole pairs of thicknesses)."""
    tally = FlagTally()
    chunks = sorted_chunks(path, chunk_rows, whole_bytes)
    if regroup is not None:
        chunks = regroup(chunks)
    first = next(chunks)  # the input's errors found up to here come before any output
    with output(out) as f:
        f.write((",".join(OUTPUT) + "\n").encode())
        for chunk in _chain(first, chunks):
            columns = fit_chunk(chunk)
            tally.add(columns["flags"])
            f.write(csv_rows(columns, used).encode())
    return tally


def _chain(first: Chunk, rest: Iterator[Chunk]) -> Iterator[Chunk]:
    yield first
    yield from rest
