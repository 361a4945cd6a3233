"""What every route of the API shares: the app's keys, ApiError (an answer in the JSON error envelope), reading a
request's JSON body and query, and running file-system or instrument work off the event loop."""

from __future__ import annotations

import asyncio
import json
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Callable, TypeVar

from aiohttp import web
from aiohttp.web_protocol import RequestPayloadError

from trimeter.paths import real_subdirectory
from trimeter.web.history import History, is_measurement_id
from trimeter.web.jobs import Job, Jobs

if TYPE_CHECKING:
    from trimeter.sequences.service import Service

T = TypeVar("T")

MAX_BODY_BYTES = 64 * 1024          # every request body is a small JSON object
MAX_JSON_DEPTH = 16                 # the deepest body the API takes is two levels
BODY_TIMEOUT_S = 10.0               # a body that small arrives at once; a client holding one back is dropped
DEVICE_CALL_TIMEOUT_S = 15.0

JOBS = web.AppKey("jobs", Jobs)
HISTORY = web.AppKey("history", History)
TOKEN = web.AppKey("token", str)
STATE = web.AppKey("state", dict)


class ApiError(Exception):
    """An answer of `status` with `message`; `headers` sent with it; `close`: the connection is closed after
    it (its request body was not or could not be read to its end)."""

    def __init__(self, status: int, message: str, *, headers: dict[str, str] | None = None, close: bool = False,
                 **extra: object) -> None:
        super().__init__(message)
        self.status, self.message, self.extra = status, message, extra
        self.headers, self.close = headers or {}, close


def error_response(status: int, message: str, *, headers: dict[str, str] | None = None, close: bool = False,
                   **extra: object) -> web.Response:
    response = web.json_response({"error": {"status": status, "message": message, **extra}}, status=status,
                                 headers=headers)
    if close:
        response.force_close()
    return response


async def json_body(request: web.Request, allowed: tuple[str, ...]) -> dict:
    """The request's JSON object (empty body: {}); unknown keys are refused, not ignored."""
    try:
        raw = await asyncio.wait_for(request.read(), BODY_TIMEOUT_S)
    except RequestPayloadError as exc:  # e.g. a Content-Encoding it is not in
        raise ApiError(400, f"the body cannot be read ({' '.join(str(exc).split())})", close=True) from None
    except asyncio.TimeoutError:
        raise ApiError(408, f"the body did not arrive within {BODY_TIMEOUT_S:g} s", close=True) from None
    if not raw.strip():
        return {}
    if request.content_type not in ("application/json", "application/octet-stream", ""):
        raise ApiError(415, f"the body must be JSON (Content-Type application/json), not {request.content_type}")
    if json_depth(raw) > MAX_JSON_DEPTH:  # before parsing: a deep one would exhaust the parser's recursion
        raise ApiError(400, f"the body is nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        body = json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise ApiError(400, f"the body is not valid JSON ({str(exc)[:200]})") from None
    if not isinstance(body, dict):
        raise ApiError(400, f"the body must be a JSON object, not {type(body).__name__}")
    if unknown := [k for k in body if k not in allowed]:
        raise ApiError(400, f"unknown field(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(allowed)}")
    return body


def json_depth(raw: bytes) -> int:
    """The deepest nesting of arrays and objects in JSON text, without parsing it (strings skipped)."""
    depth = deepest = 0
    for token in _JSON_NESTING.finditer(raw):
        char = token.group()
        if char in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
        elif char in (b"]", b"}"):
            depth -= 1
    return deepest


_JSON_NESTING = re.compile(rb'"(?:[^"\\]|\\.)*"|[\[\]{}]')


def number(body: dict, key: str, *, default: float | None = None, minimum: float = 0.0, maximum: float = math.inf,
           allow_zero: bool = False) -> float | None:
    value = body.get(key, default)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ApiError(400, f"{key}: {value!r} is not a number")
    if not (minimum < value <= maximum or allow_zero and value == 0):
        raise ApiError(400, f"{key}: {value!r} must be within ({minimum:g}, {maximum:g}]")
    return float(value)


def query_int(request: web.Request, key: str, default: int) -> int:
    text = request.query.get(key)
    if text is None:
        return default
    try:
        return int(text)
    except ValueError:
        raise ApiError(400, f"{key}: {text!r} is not an integer") from None


async def blocking(request: web.Request, fn: Callable[..., T], *args: object) -> T:
    """Run file-system / SQLite / CPU work off the event loop (one thread: one SQLite connection)."""
    return await asyncio.get_running_loop().run_in_executor(request.app[STATE]["executor"], fn, *args)


async def device_call(request: web.Request, fn: Callable[[Service], T]) -> T:
    if stopped := request.app[JOBS].stopped:  # nothing would ever run the call: say why now, not after a timeout
        raise ApiError(503, f"the instrument loop has stopped: {stopped}")
    future = request.app[JOBS].call(fn)
    try:
        return await asyncio.wait_for(asyncio.wrap_future(future), DEVICE_CALL_TIMEOUT_S)
    except asyncio.TimeoutError:
        future.cancel()
        raise ApiError(503, f"the instrument did not answer within {DEVICE_CALL_TIMEOUT_S:g} s "
                            "(not connected?)") from None


def measurement_dir(request: web.Request) -> Path:
    measurement_id = request.match_info["id"]
    history = request.app[HISTORY]
    if not is_measurement_id(measurement_id):
        raise ApiError(400, f"{measurement_id!r} is not a measurement id (a results directory's name)")
    path = real_subdirectory(history.root, measurement_id)
    if path is None:  # missing, or not a real directory of the results root (a link is never followed)
        raise ApiError(404, f"no measurement {measurement_id!r}")
    return path


def accepted(job: Job) -> web.Response:
    return web.json_response({"job": job.to_json()}, status=202, headers={"Location": f"/api/jobs/{job.id}"})
