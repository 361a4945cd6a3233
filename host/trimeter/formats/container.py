"""The self-describing, versioned, checksummed binary container used by every trimeter data file
(appearance maps; the map table has its own fixed C-readable layout).

Layout (all little-endian):

    offset 0   8 bytes   magic  b"\\x89TRMAP\\r\\n"  (PNG-style: catches text-mode and truncation mangling)
    offset 8   u32       container format version (FORMAT_VERSION)
    offset 12  u32       header length H in bytes
    offset 16  H bytes   JSON header, UTF-8: {"kind", "meta", "arrays": {name: {dtype, shape, offset, nbytes}}}
    ...        payload   raw arrays, each 8-byte aligned, offsets relative to the payload start
    end - 32   32 bytes  SHA-256 of every byte before it

A reader checks the file's size (os.fstat, before reading: at most MAX_CONTAINER_BYTES), magic,
version, checksum, the header's structure (trimeter.formats.schema: every array descriptor's dtype from
ALLOWED_DTYPES, shape, offset and length inside the payload) and, given the file kind's schema, its
metadata, array names, shapes and values, so a truncated, tampered or crafted file is refused whole
with a MapFileError naming the field, never half-loaded. No pickle: dtypes are plain numeric numpy dtypes.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import stat
import struct
import tempfile
from pathlib import Path
from typing import NoReturn

import numpy as np

from trimeter.errors import MapFileError
from trimeter.formats.schema import ALLOWED_DTYPES, ContainerSchema, Items, Json, Number, SchemaError, Table, Text
from trimeter.validation import shown

MAGIC = b"\x89TRMAP\r\n"
FORMAT_VERSION = 1
# The largest shipped file is ~0.2 MB and a map 100× finer in every axis would be ~100 MB: 512 MiB is
# generous for any real file and still refuses a hostile one before it is read into memory.
MAX_CONTAINER_BYTES = 512 * 2**20
MAX_HEADER_BYTES = 4 * 2**20
_PREFIX = struct.Struct("<8sII")
_DIGEST = 32
_DESCRIPTOR = Table({"dtype": Text(max_len=8, choices=ALLOWED_DTYPES),
                     "shape": Items(Number(lo=0, hi=2**31, integer=True), max_len=8),
                     "offset": Number(lo=0, integer=True), "nbytes": Number(lo=0, integer=True)},
                    required=("dtype", "shape", "offset", "nbytes"), extra=None)
_HEADER = Table({"kind": Text(max_len=64), "meta": Json(max_depth=16, max_items=100_000),
                 "arrays": Table(extra=_DESCRIPTOR, max_keys=64)},
                required=("kind", "meta", "arrays"), extra=None)


def write_container(path: str | os.PathLike, kind: str, meta: dict, arrays: dict[str, np.ndarray]) -> str:
    """Write atomically (temp file + rename). Returns the hex SHA-256 (the file's identity)."""
    descriptors, chunks, offset = {}, [], 0
    for name, arr in arrays.items():
        arr = np.ascontiguousarray(arr)
        arr = arr.astype(arr.dtype.newbyteorder("<"), copy=False)
        if arr.dtype.str not in ALLOWED_DTYPES:
            raise TypeError(f"array {name!r}: dtype {arr.dtype} is not one of {', '.join(ALLOWED_DTYPES)}")
        pad = (-offset) % 8
        chunks.append(b"\0" * pad)
        offset += pad
        descriptors[name] = {"dtype": arr.dtype.str, "shape": list(arr.shape), "offset": offset,
                             "nbytes": arr.nbytes}
        chunks.append(arr.tobytes())
        offset += arr.nbytes
    header = json.dumps({"kind": kind, "meta": meta, "arrays": descriptors},
                        sort_keys=True, allow_nan=False).encode()
    body = _PREFIX.pack(MAGIC, FORMAT_VERSION, len(header)) + header + b"".join(chunks)
    digest = hashlib.sha256(body).digest()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)      # mkstemp's 0600 would make shipped maps unreadable to others
        with os.fdopen(fd, "wb") as f:
            f.write(body + digest)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return digest.hex()


def read_container(path: str | os.PathLike, kind: str,
                   schema: ContainerSchema | None = None) -> tuple[dict, dict[str, np.ndarray], str]:
    """Return (meta, arrays, sha256 hex). Raises MapFileError with a clear reason on any defect;
    with a `schema`, also on metadata or arrays that break it (checked before the arrays are made)."""
    path = Path(path)
    data = read_bounded(path, MAX_CONTAINER_BYTES, "trimeter data file")
    if len(data) < _PREFIX.size + _DIGEST:
        raise MapFileError(f"{path}: truncated ({len(data)} bytes) — not a complete trimeter file")
    magic, version, header_len = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        raise MapFileError(f"{path}: not a trimeter data file (bad magic)")
    if version != FORMAT_VERSION:
        raise MapFileError(f"{path}: container version {version} is not supported (this trimeter reads "
                           f"{FORMAT_VERSION})")
    body, digest = data[:-_DIGEST], data[-_DIGEST:]
    if hashlib.sha256(body).digest() != digest:
        raise MapFileError(f"{path}: checksum mismatch — the file is truncated or was modified")
    if header_len > min(MAX_HEADER_BYTES, len(body) - _PREFIX.size):
        raise MapFileError(f"{path}: header length {header_len} does not fit the file (or exceeds "
                           f"{MAX_HEADER_BYTES} bytes)")
    try:
        header = json.loads(body[_PREFIX.size:_PREFIX.size + header_len], parse_constant=_refuse_constant)
        _HEADER.check(header, "header")
        if header["kind"] != kind:
            raise MapFileError(f"{path}: holds a {header['kind']!r}, expected a {kind!r}")
        if schema is not None:
            schema.check_header(header["meta"], header["arrays"])
    except (UnicodeDecodeError, ValueError) as exc:  # incl. json.JSONDecodeError, SchemaError
        raise MapFileError(f"{path}: {'unreadable header: ' if not isinstance(exc, SchemaError) else ''}"
                           f"{exc}") from None
    except RecursionError:
        raise MapFileError(f"{path}: unreadable header: nested too deeply") from None
    payload = memoryview(body)[_PREFIX.size + header_len:]
    arrays = {}
    for name, d in header["arrays"].items():
        dtype, shape, start, nbytes = np.dtype(d["dtype"]), tuple(d["shape"]), d["offset"], d["nbytes"]
        if start + nbytes > len(payload) or nbytes != dtype.itemsize * math.prod(shape):
            raise MapFileError(f"{path}: array {shown(name, 40)} is inconsistent with the file (shape {list(shape)}, "
                               f"{nbytes} bytes at {start}, payload {len(payload)} bytes)")
        arrays[name] = np.frombuffer(payload[start:start + nbytes], dtype=dtype).reshape(shape)
    if schema is not None:
        try:
            schema.check_arrays(arrays)
        except SchemaError as exc:
            raise MapFileError(f"{path}: {exc}") from None
    return header["meta"], arrays, digest.hex()


def read_bounded(path: Path, limit: int, what: str) -> bytes:
    """A regular file's bytes, refused before reading when it is larger than `limit` (or not a file:
    a device such as /dev/zero never ends)."""
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (regular files ignore the flag)
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as f:
            info = os.fstat(f.fileno())
            if not stat.S_ISREG(info.st_mode):
                raise MapFileError(f"{path}: not a regular file")
            if info.st_size > limit:
                raise MapFileError(f"{path}: {info.st_size} bytes is larger than any {what} "
                                   f"(at most {limit} bytes)")
            data = f.read(limit + 1)
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) > limit:
        raise MapFileError(f"{path}: larger than any {what} (at most {limit} bytes)")
    return data


def _refuse_constant(name: str) -> NoReturn:
    raise ValueError(f"{name} is not a number a trimeter file may hold")
