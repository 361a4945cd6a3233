"""The app's middlewares: access (the token, same-origin for what changes things), every failure as the JSON
error envelope, and the browser-side protections on every response."""

from __future__ import annotations

import asyncio
import logging
from typing import Awaitable, Callable

from aiohttp import web

from trimeter.errors import TrimeterError
from trimeter.web import auth
from trimeter.web.handler_tools import MAX_BODY_BYTES, TOKEN, ApiError, error_response
from trimeter.web.history import IndexUnavailable
from trimeter.web.jobs import Busy, LinkDown

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

log = logging.getLogger("trimeter.web")

LINK_DOWN_RETRY_AFTER_S = 5         # work asked for while the device link is being tried again

# Sent with every response (page, static files, API, errors). The page loads only its own script and
# stylesheet, talks to its own API and websocket ('self' covers ws: on the same host and port) and is never
# framed; nothing inline, nothing from outside, no plugins.
CONTENT_SECURITY_POLICY = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; "
                           "connect-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
SECURITY_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",  # frame-ancestors' equivalent for browsers without CSP level 2
    "Referrer-Policy": "no-referrer",  # the page's first URL carries the access token
}



@web.middleware
async def errors_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Every failure of an API call as the JSON envelope; never a traceback on the wire."""
    try:
        return await handler(request)
    except ApiError as exc:
        return error_response(exc.status, exc.message, headers=exc.headers, close=exc.close, **exc.extra)
    except Busy as exc:
        return error_response(409, f"the instrument is busy: {exc}", job=exc.job.to_json())
    except LinkDown as exc:
        return error_response(503, str(exc), headers={"Retry-After": str(LINK_DOWN_RETRY_AFTER_S)})
    except IndexUnavailable as exc:
        return error_response(503, str(exc), headers={"Retry-After": str(IndexUnavailable.RETRY_AFTER_S)})
    except TrimeterError as exc:
        return error_response(400, str(exc))
    except web.HTTPException as exc:
        if exc.status < 400 or not request.path.startswith("/api"):
            raise
        message = {413: f"the request body is larger than {MAX_BODY_BYTES} bytes"}.get(exc.status, exc.reason)
        return error_response(exc.status, message)
    except asyncio.CancelledError:
        raise
    except Exception:
        log.exception("internal error answering %s %s", request.method, request.path)
        return error_response(500, "internal error (the serve log has the details)")


async def security_headers(request: web.Request, response: web.StreamResponse) -> None:
    """SECURITY_HEADERS on every response: as on_response_prepare it also reaches the responses raised as
    exceptions (the page's redirect, the router's 404/405), which no middleware gets back."""
    response.headers.update(SECURITY_HEADERS)


@web.middleware
async def auth_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    if not request.path.startswith("/api"):
        return await handler(request)
    if not auth.token_matches(request.app[TOKEN], auth.presented_token(request)):
        return error_response(401, "no or wrong token: open the link `trimeter serve --show-token` prints, or send "
                           "`Authorization: Bearer <token>`")
    guarded = request.method in auth.UNSAFE_METHODS or request.path == "/api/events"
    if guarded and (why := auth.cross_origin(request)):
        return error_response(403, f"refused: a request from another site's page ({why})")
    if request.content_length is not None and request.content_length > MAX_BODY_BYTES:
        return error_response(413, f"the request body is larger than {MAX_BODY_BYTES} bytes")
    return await handler(request)
