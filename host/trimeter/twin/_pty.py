"""Small pty helpers shared by the twin's servers (raw mode, non-blocking, bounded writes)."""

from __future__ import annotations

import errno
import os
import select
import time
import tty


def open_raw_pty() -> tuple[int, int, str]:
    """(master_fd, slave_fd, slave_path): raw (no echo, no line discipline), master non-blocking.

    The twin keeps the slave open itself, so a client closing and reopening the port never makes the
    master see EOF/EIO.
    """
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


def write_all(fd: int, data: bytes, timeout_s: float = 2.0) -> bool:
    """Write everything or give up after timeout_s (a client that stopped reading); True if all written."""
    deadline = time.monotonic() + timeout_s
    view = memoryview(data)
    while view:
        try:
            n = os.write(fd, view)
            view = view[n:]
        except BlockingIOError:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            select.select([], [fd], [], min(remaining, 0.05))
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.EBADF):
                return False
            raise
    return True


def read_some(fd: int, size: int = 65536) -> bytes | None:
    """Non-blocking read: bytes, b"" if nothing is there, None if the other side is gone (EIO)."""
    try:
        return os.read(fd, size) or None
    except BlockingIOError:
        return b""
    except OSError as exc:
        if exc.errno in (errno.EIO, errno.EBADF):
            return None
        raise
