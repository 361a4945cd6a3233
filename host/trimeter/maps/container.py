"""The self-describing, versioned, checksummed binary container used by every trimeter data file
(appearance maps; the map table has its own fixed C-readable layout).

Layout (all little-endian):

    offset 0   8 bytes   magic  b"\\x89TRMAP\\r\\n"  (PNG-style: catches text-mode and truncation mangling)
    offset 8   u32       container format version (FORMAT_VERSION)
    offset 12  u32       header length H in bytes
    offset 16  H bytes   JSON header, UTF-8: {"kind", "meta", "arrays": {name: {dtype, shape, offset, nbytes}}}
    ...        payload   raw arrays, each 8-byte aligned, offsets relative to the payload start
    end - 32   32 bytes  SHA-256 of every byte before it

A reader verifies size, magic, version, checksum and every array's bounds before returning anything,
so a truncated or tampered file is refused whole, never half-loaded. No pickle: dtypes are plain
numeric numpy dtypes.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import tempfile
from pathlib import Path

import numpy as np

from trimeter.errors import MapFileError

MAGIC = b"\x89TRMAP\r\n"
FORMAT_VERSION = 1
_PREFIX = struct.Struct("<8sII")
_DIGEST = 32
_ALLOWED_KINDS = "biufc"  # bool, int, uint, float, complex: never object


def write_container(path: str | os.PathLike, kind: str, meta: dict, arrays: dict[str, np.ndarray]) -> str:
    """Write atomically (temp file + rename). Returns the hex SHA-256 (the file's identity)."""
    descriptors, chunks, offset = {}, [], 0
    for name, arr in arrays.items():
        arr = np.ascontiguousarray(arr)
        if arr.dtype.kind not in _ALLOWED_KINDS:
            raise TypeError(f"array {name!r}: dtype {arr.dtype} is not a plain numeric type")
        arr = arr.astype(arr.dtype.newbyteorder("<"), copy=False)
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


def read_container(path: str | os.PathLike, kind: str) -> tuple[dict, dict[str, np.ndarray], str]:
    """Return (meta, arrays, sha256 hex). Raises MapFileError with a clear reason on any defect."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
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
    try:
        header = json.loads(body[_PREFIX.size:_PREFIX.size + header_len])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapFileError(f"{path}: unreadable header ({exc})") from None
    if header.get("kind") != kind:
        raise MapFileError(f"{path}: holds a {header.get('kind')!r}, expected a {kind!r}")
    payload = memoryview(body)[_PREFIX.size + header_len:]
    arrays = {}
    for name, d in header.get("arrays", {}).items():
        try:
            dtype = np.dtype(d["dtype"])
            shape = tuple(int(s) for s in d["shape"])
            start, nbytes = int(d["offset"]), int(d["nbytes"])
        except (KeyError, TypeError, ValueError) as exc:
            raise MapFileError(f"{path}: array {name!r} has a malformed descriptor ({exc})") from None
        if (dtype.kind not in _ALLOWED_KINDS or start < 0 or start + nbytes > len(payload)
                or nbytes != dtype.itemsize * int(np.prod(shape, dtype=np.int64))):
            raise MapFileError(f"{path}: array {name!r} is inconsistent with the file")
        arrays[name] = np.frombuffer(payload[start:start + nbytes], dtype=dtype).reshape(shape)
    return header.get("meta", {}), arrays, digest.hex()
