"""Access to the web API: one token, made at first start and kept 0600 in the host config directory.

The page takes it once (`/?token=…`, answered with an HttpOnly cookie and a redirect that drops it
from the address bar); every API call needs that cookie or `Authorization: Bearer <token>`. A
missing or wrong token is 401. Requests that change state (and the event websocket, which a foreign
page could otherwise open with the cookie) are refused with 403 when the browser says they come
from another origin.
"""

from __future__ import annotations

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
    A token file others can read is made private again: the token is as good as a password."""
    path = path or token_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        pass
    else:
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
            f.flush()
            os.fsync(f.fileno())
    try:
        if stat.S_IMODE(path.stat().st_mode) & 0o077:
            path.chmod(0o600)
        token = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: the web token cannot be read ({exc}); delete the file to make a new one") from None
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
