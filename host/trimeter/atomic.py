"""Files that are either the old version or the complete new one, never a truncated mix.

`atomic_output(path)` hands out a temporary file next to `path` (same file system, so the final
rename is atomic); on a clean exit it is flushed, fsynced and renamed over `path`, and the directory
is fsynced so the rename survives a power cut. On any error the temporary file is removed and the
previous `path`, if any, is untouched. `atomic_write(path, data)` is the one-shot form.

Errors come out as OutputError naming the path and the reason (full disk, read-only, no permission).
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, Iterator

from trimeter.errors import OutputError

TEMP_SUFFIX = ".tmp"


def _umask() -> int:
    """The process's umask. Read from /proc where there is one: setting it to learn it (the only portable
    way) briefly leaves 0 in force for every other thread's new files (the web server's, the instrument's)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    umask = os.umask(0o077)  # the restrictive value, should another thread create a file meanwhile
    os.umask(umask)
    return umask


def _mode_for(path: Path) -> int:
    """A replaced file keeps its permissions; a new one gets what open() would give it (not mkstemp's 0600)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_umask()


def fsync_directory(directory: str | os.PathLike) -> None:
    """Make a rename or a new entry in `directory` durable (a no-op where directories can't be fsynced)."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems refuse fsync on a directory; the rename itself is still atomic
    finally:
        os.close(fd)


def describe_os_error(exc: OSError) -> str:
    return exc.strerror or str(exc)


@contextmanager
def atomic_output(path: str | os.PathLike, *, make_parents: bool = True) -> Iterator[BinaryIO]:
    """Yield a binary file; when the block ends without an exception it replaces `path` atomically
    (through a symlink: the file it points to is replaced, the link stays)."""
    path = Path(path)
    if path.is_symlink():
        path = path.resolve()
    try:
        if make_parents:
            path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {describe_os_error(exc)}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), _mode_for(path))
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise OutputError(f"cannot write {path}: {describe_os_error(exc)}") from exc
        raise
    fsync_directory(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, make_parents: bool = True) -> Path:
    """Write `data` (str as UTF-8) to `path` atomically; return the path."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_output(path, make_parents=make_parents) as f:
        f.write(data)
    return Path(path)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True if `a` and `b` name one file (the same path, a symlink to it, or a hard link)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet): compare where they would be
        return Path(a).resolve() == Path(b).resolve()
