"""The instrument's own device table: read from its active map slot and kept in a cache on this computer, one
file per table named by its SHA-256 (the table itself is trimeter.formats.device_table's byte format)."""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import stat
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

try:
    import fcntl
except ImportError:  # not on Windows: one reader at a time is then not enforced
    fcntl = None  # type: ignore[assignment]

from trimeter.atomic import atomic_write
from trimeter.errors import MapFileError, OutputError
from trimeter.formats.device_table import HEADER_SIZE, MAX_BYTES, SUFFIX, DeviceTable, read_header
from trimeter.registers import MapSlot

if TYPE_CHECKING:
    from trimeter.device.client import Device

SHA256_HEX = re.compile(r"[0-9a-f]{64}")  # a table's name in the cache
PARTIAL_SUFFIX = ".partial"  # the start of a table whose read the link cut short


def cache_dir() -> Path:
    """Where tables read from instruments are kept, one file per table named by its SHA-256
    (TRIMETER_CACHE_DIR overrides the user cache directory)."""
    import platformdirs

    return Path(os.environ.get("TRIMETER_CACHE_DIR") or platformdirs.user_cache_dir("trimeter")) / "device-tables"


def cached_tables(directory: Path | None = None) -> list[dict[str, Any]]:
    """What the cache of instruments' tables holds (default: cache_dir()), one entry per file by name: its
    SHA-256 as named (not recomputed) and read_header's fields, or for a file that is no readable table a
    `note` saying why (instrument_table checks an entry in full, and deletes a damaged one, when it uses it)."""
    directory = cache_dir() if directory is None else Path(directory)
    entries: list[dict[str, Any]] = []
    for path in sorted(directory.glob("*" + SUFFIX)):
        entry: dict[str, Any] = {"file": path.name, "sha256": path.stem}
        try:
            if not SHA256_HEX.fullmatch(path.stem):
                raise MapFileError(f"{path}: not named by a SHA-256, so not a cache entry")
            entry.update(read_header(path))
        except MapFileError as exc:
            entry["note"] = f"skipped: {exc}"
        entries.append(entry)
    return entries


def _cached(directory: Path, length: int, head: bytes, tail_at: int, tail: bytes) -> DeviceTable | None:
    """The cached table with this length, header and trailing CRC-32, checked against its SHA-256 name;
    a damaged entry is deleted (the caller then reads the slot again)."""
    if not directory.is_dir():
        return None
    for path in directory.glob("*" + SUFFIX):
        try:
            if path.stat().st_size != length:
                continue
            data = path.read_bytes()
        except OSError:
            continue
        if data[:len(head)] != head or data[tail_at:] != tail:
            continue
        try:
            if hashlib.sha256(data).hexdigest() != path.stem:
                raise MapFileError(f"{path}: its SHA-256 is not its name")
            table = DeviceTable.from_bytes(data, source=str(path))
        except MapFileError:
            path.unlink(missing_ok=True)
            continue
        return table
    return None


def instrument_table(device: Device, cache: Path | None = None) -> tuple[DeviceTable, str, bool]:
    """The table in the device's active map slot, (table, slot name, read from the cache). The slot's
    header and trailing CRC-32 (a few hundred bytes) find it in the cache; otherwise the whole slot is
    read, checked and cached (atomically, by its SHA-256). `device`: a trimeter.device.Device.

    MapFileError when the device has no active table or its slot holds no usable one (corrupt, or a
    retired format)."""
    directory = cache_dir() if cache is None else Path(cache)
    status = device.map_status()
    active = MapSlot(status["map_active_slot"])
    if active == MapSlot.NONE:
        # not a link fault: the service must report it, not reconnect over it
        raise MapFileError("the device has no active map table: flash one (`trimeter map flash maps/<map>.tlut "
                           "--port PORT`) or name a map to fit with (--map)")
    length = int(status[f"map_slot_{active.name.lower()}_length"])
    if not HEADER_SIZE + 4 <= length <= MAX_BYTES:
        raise MapFileError(f"the device's slot {active.name} holds {length} bytes, not a map table: flash one "
                           f"(`trimeter map flash maps/<map>.tlut --port PORT`) or pass --map")
    head = device.read_map(active, HEADER_SIZE)
    tail_at = (length - 4) & ~1  # the device reads whole 16-bit words
    tail = device.read_map(active, length - tail_at, offset=tail_at)
    table = _cached(directory, length, head, tail_at, tail)
    if table is not None:
        return table, active.name, True
    # named by what identifies the table before it is whole: its length, header and trailing CRC-32
    partial = directory / f"{length}-{hashlib.sha256(head).hexdigest()[:16]}-{tail.hex()}{PARTIAL_SUFFIX}"
    data, resumable = _read_slot(device, active, length, partial)
    try:
        table = DeviceTable.from_bytes(data, source=f"the device's slot {active.name}")
    except MapFileError as exc:
        raise MapFileError(f"{exc}; flash a current table (`trimeter map flash maps/<map>.tlut --port PORT`) or "
                           f"pass --map") from None
    finally:
        if resumable:  # whole now, or not worth resuming: the next read starts afresh
            partial.unlink(missing_ok=True)
    with contextlib.suppress(OutputError):  # an unwritable cache costs the next run a read, nothing else
        atomic_write(directory / f"{table.sha256}{SUFFIX}", data)
    return table, active.name, False


def _read_slot(device: Device, slot: MapSlot, length: int, partial: Path) -> tuple[bytes, bool]:
    """The slot's `length` bytes, going on from what an earlier read of the same table left in `partial` when
    the link cut it short; and whether this read kept its bytes there (the caller then removes the file). The
    bytes are kept as they arrive, so a read that fails (its time budget spent on a noisy line) is resumed by
    the next try, the service's or the next press's, instead of starting over: on a line too noisy to carry a
    whole table in one budget, the table still arrives. The whole table's CRC-32 is checked afterwards
    (DeviceTable.from_bytes), whatever tries it took. One reader at a time keeps bytes in `partial` (a lock on
    it): another process reading the same table meanwhile (a second instrument with the same map) reads its
    own from the start without keeping them."""
    sink = _resume_file(partial)
    data = bytearray()
    try:
        if sink is not None:
            data += sink.read(length)
            del data[len(data) & ~1:]  # whole 16-bit records only
            sink.seek(len(data))
            sink.truncate()
            sink.flush()

        def keep(chunk: bytes) -> None:
            with contextlib.suppress(OSError):
                if sink is not None:
                    sink.write(chunk)
                    sink.flush()

        if len(data) < length:
            data += device.read_map(slot, length - len(data), offset=len(data), on_data=keep)
    finally:
        if sink is not None:
            sink.close()  # and with it the lock
    return bytes(data[:length]), sink is not None


def _resume_file(partial: Path) -> IO[bytes] | None:
    """`partial` opened to read and write, locked for this reader alone; None where it cannot be (an unwritable
    cache, not a regular file, or another reader holds it): the read then goes on without keeping its bytes."""
    try:
        partial.parent.mkdir(parents=True, exist_ok=True)
        # not through a link, and a FIFO put there fails at once instead of waiting for a writer
        fd = os.open(partial, os.O_RDWR | os.O_CREAT | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0), 0o644)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(f"{partial} is not a regular file")
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # BlockingIOError (an OSError) while another holds it
        return os.fdopen(fd, "r+b")
    except OSError:
        os.close(fd)
        return None
