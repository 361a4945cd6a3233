"""Access to the web API: one token, made at first start and kept 0600 in the host config directory.

The page takes it once (`/?token=…`, answered with an HttpOnly cookie and a redirect that drops it
from the address bar); every API call needs that cookie or `Authorization: Bearer <token>`. A
missing or wrong token is 401. Requests that change state (and the event websocket, which a foreign
page could otherwise open with the cookie) are refused with 403 when the browser says they come
from another origin.
"""

from __future__ import annotations

import errno
import hmac
import os
import secrets
import stat
from pathlib import Path

from aiohttp import web

from trimeter.errors import InputError
from trimeter.paths import config_dir

TOKEN_FILE_NAME = "web-token"
COOKIE = "trimeter_token"
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def token_path() -> Path:
    return config_dir() / TOKEN_FILE_NAME


def load_or_create_token(path: Path | None = None) -> str:
    """The token in `path` (default: the host config directory's), created there (0600) if missing.
    A token file others can read is made private again: the token is as good as a password. The file is
    never reached through a link (O_NOFOLLOW) and its mode is changed on the opened file (fchmod): a link
    put in its place is refused, not followed to chmod or read whatever it points at."""
    path = path or token_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    nofollow = os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    try:  # O_EXCL never follows a link either: a dangling one is EEXIST, then refused below
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | nofollow, 0o600)
    except FileExistsError:
        pass
    except OSError as exc:
        raise InputError(f"{path}: the web token cannot be created ({exc.strerror or exc})") from None
    else:
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
            f.flush()
            os.fsync(f.fileno())
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | nofollow)
    except OSError as exc:
        why = "it is a symbolic link" if exc.errno == errno.ELOOP else exc.strerror or str(exc)
        raise InputError(f"{path}: the web token cannot be read ({why}); delete the file to make a new one") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputError(f"{path}: the web token is not a regular file; delete it to make a new one")
        if stat.S_IMODE(info.st_mode) & 0o077:
            os.fchmod(fd, 0o600)
        with os.fdopen(os.dup(fd), "rb") as f:
            token = f.read(4096).decode().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: the web token cannot be read ({exc}); delete the file to make a new one") from None
    finally:
        os.close(fd)
    if len(token) < 16 or not token.isascii() or not token.isprintable() or " " in token:
        raise InputError(f"{path}: not a web token (too short or not printable); delete the file to make a new one")
    return token


def presented_token(request: web.Request) -> str | None:
    header = request.headers.get("Authorization", "")
    if header[:7].lower() == "bearer ":
        return header[7:].strip()
    return request.cookies.get(COOKIE)


def token_matches(token: str, presented: str | None) -> bool:
    return presented is not None and hmac.compare_digest(token.encode(), presented.encode("utf-8", "replace"))


def cross_origin(request: web.Request) -> str | None:
    """Why the browser's own headers say this request comes from another site's page (None: it does not)."""
    if request.headers.get("Sec-Fetch-Site", "same-origin") not in ("same-origin", "none"):
        return f"Sec-Fetch-Site is {request.headers['Sec-Fetch-Site']}"
    origin = request.headers.get("Origin")
    if origin is not None and origin != f"{request.scheme}://{request.host}":
        return f"Origin {origin} is not {request.scheme}://{request.host}"
    return None
