"""`trimeter serve --http`: the instrument on the LAN — a JSON API, a live event websocket and a page.

aiohttp: one dependency that is both the server (HTTP/1.1, websockets, file responses) and the client
(webhooks, `trimeter bench http`), running on plain asyncio in the serve process next to the
instrument's worker thread; no ASGI server or framework layer to configure. The API is the product
and the page (static/) one client of it; every answer is JSON, errors as {"error": {"status",
"message"}}. See `openapi()` for the endpoints, trimeter.web.auth for access, trimeter.web.jobs for
how the button and the page share the instrument.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import copy
import csv
import functools
import io
import json
import logging
import math
import mimetypes
import re
import threading
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from collections.abc import Sequence
from typing import TYPE_CHECKING, Awaitable, Callable, TypeVar

from aiohttp import ClientSession, ClientTimeout, WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web_protocol import RequestPayloadError

from trimeter import registers as regs
from trimeter.device.client import CONFIG_NAMES, encode
from trimeter.errors import DeviceError, InputError, TrimeterError
from trimeter.inversion.methods import METHODS
from trimeter.inversion.flags import advice, describe
from trimeter.formats.appearance import AppearanceMap, find_map, shipped_maps
from trimeter.device.table_cache import cached_tables
from trimeter.formats.device_table import DeviceTable
from trimeter.paths import NAME_MAX, real_subdirectory, regular_files
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.instruments import Instrument
from trimeter.sequences.service import EMPTY_HOLDER, NEXT_SAMPLE
from trimeter.sequences.settings import HostSettings
from trimeter.tables import MAX_RESULT_FILE_BYTES, open_checked
from trimeter.web import auth
from trimeter.web import instruments_routes, library_routes
from trimeter.web.isolated import run_with_time_limit
from trimeter.web.history import History, IndexUnavailable, is_measurement_id, parse_day_or_time
from trimeter.web.jobs import Busy, Job, Jobs, LinkDown

if TYPE_CHECKING:
    from trimeter.domain.measurement import MapRef
    from trimeter.sequences.service import Service

T = TypeVar("T")
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

log = logging.getLogger("trimeter.web")

STATIC = Path(__file__).resolve().parent / "static"   # package data (pyproject)
MAX_BODY_BYTES = 64 * 1024          # every request body is a small JSON object
MAX_JSON_DEPTH = 16                 # the deepest body the API takes is two levels
BODY_TIMEOUT_S = 10.0               # a body that small arrives at once; a client holding one back is dropped
# A connection must complete its request's headers within this of opening or of its previous answer (aiohttp's
# keep-alive timer, which also runs until the first request): a client sending them slowly is dropped.
HEADER_TIMEOUT_S = 15.0
EVENT_QUEUE = 256                   # events buffered per websocket client; a client that falls further behind is closed
DEVICE_CALL_TIMEOUT_S = 15.0
LINK_DOWN_RETRY_AFTER_S = 5         # work asked for while the device link is being tried again
REFIT_TIME_LIMIT_S = 300.0          # a re-fit runs in a child process, stopped at this
WEBHOOK_TIMEOUT_S = 5.0
LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
MAX_THICKNESS_MM = 100.0
CSV_COLUMNS = ("id", "written_utc", "label", "thicknesses_mm", "maps", "method", "bins", "flagged_bins",
               "flag_names", "incomplete", "refit_of")

JOBS = web.AppKey("jobs", Jobs)
HISTORY = web.AppKey("history", History)
TOKEN = web.AppKey("token", str)
STATE = web.AppKey("state", dict)

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


class ApiError(Exception):
    """An answer of `status` with `message`; `headers` sent with it; `close`: the connection is closed after
    it (its request body was not or could not be read to its end)."""

    def __init__(self, status: int, message: str, *, headers: dict[str, str] | None = None, close: bool = False,
                 **extra: object) -> None:
        super().__init__(message)
        self.status, self.message, self.extra = status, message, extra
        self.headers, self.close = headers or {}, close


def _error(status: int, message: str, *, headers: dict[str, str] | None = None, close: bool = False,
           **extra: object) -> web.Response:
    response = web.json_response({"error": {"status": status, "message": message, **extra}}, status=status,
                                 headers=headers)
    if close:
        response.force_close()
    return response


# ------------------------------------------------------------------------------------ middleware
@web.middleware
async def errors_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Every failure of an API call as the JSON envelope; never a traceback on the wire."""
    try:
        return await handler(request)
    except ApiError as exc:
        return _error(exc.status, exc.message, headers=exc.headers, close=exc.close, **exc.extra)
    except Busy as exc:
        return _error(409, f"the instrument is busy: {exc}", job=exc.job.to_json())
    except LinkDown as exc:
        return _error(503, str(exc), headers={"Retry-After": str(LINK_DOWN_RETRY_AFTER_S)})
    except IndexUnavailable as exc:
        return _error(503, str(exc), headers={"Retry-After": str(IndexUnavailable.RETRY_AFTER_S)})
    except TrimeterError as exc:
        return _error(400, str(exc))
    except web.HTTPException as exc:
        if exc.status < 400 or not request.path.startswith("/api"):
            raise
        message = {413: f"the request body is larger than {MAX_BODY_BYTES} bytes"}.get(exc.status, exc.reason)
        return _error(exc.status, message)
    except asyncio.CancelledError:
        raise
    except Exception:
        log.exception("internal error answering %s %s", request.method, request.path)
        return _error(500, "internal error (the serve log has the details)")


async def security_headers(request: web.Request, response: web.StreamResponse) -> None:
    """SECURITY_HEADERS on every response: as on_response_prepare it also reaches the responses raised as
    exceptions (the page's redirect, the router's 404/405), which no middleware gets back."""
    response.headers.update(SECURITY_HEADERS)


@web.middleware
async def auth_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    if not request.path.startswith("/api"):
        return await handler(request)
    if not auth.token_matches(request.app[TOKEN], auth.presented_token(request)):
        return _error(401, "no or wrong token: open the link `trimeter serve --show-token` prints, or send "
                           "`Authorization: Bearer <token>`")
    guarded = request.method in auth.UNSAFE_METHODS or request.path == "/api/events"
    if guarded and (why := auth.cross_origin(request)):
        return _error(403, f"refused: a request from another site's page ({why})")
    if request.content_length is not None and request.content_length > MAX_BODY_BYTES:
        return _error(413, f"the request body is larger than {MAX_BODY_BYTES} bytes")
    return await handler(request)


# ------------------------------------------------------------------------------------- helpers
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


def _query_int(request: web.Request, key: str, default: int) -> int:
    text = request.query.get(key)
    if text is None:
        return default
    try:
        return int(text)
    except ValueError:
        raise ApiError(400, f"{key}: {text!r} is not an integer") from None


async def _blocking(request: web.Request, fn: Callable[..., T], *args: object) -> T:
    """Run file-system / SQLite / CPU work off the event loop (one thread: one SQLite connection)."""
    return await asyncio.get_running_loop().run_in_executor(request.app[STATE]["executor"], fn, *args)


async def _device_call(request: web.Request, fn: Callable[[Service], T]) -> T:
    if stopped := request.app[JOBS].stopped:  # nothing would ever run the call: say why now, not after a timeout
        raise ApiError(503, f"the instrument loop has stopped: {stopped}")
    future = request.app[JOBS].call(fn)
    try:
        return await asyncio.wait_for(asyncio.wrap_future(future), DEVICE_CALL_TIMEOUT_S)
    except asyncio.TimeoutError:
        future.cancel()
        raise ApiError(503, f"the instrument did not answer within {DEVICE_CALL_TIMEOUT_S:g} s "
                            "(not connected?)") from None


def _measurement_dir(request: web.Request) -> Path:
    measurement_id = request.match_info["id"]
    history = request.app[HISTORY]
    if not is_measurement_id(measurement_id):
        raise ApiError(400, f"{measurement_id!r} is not a measurement id (a results directory's name)")
    path = real_subdirectory(history.root, measurement_id)
    if path is None:  # missing, or not a real directory of the results root (a link is never followed)
        raise ApiError(404, f"no measurement {measurement_id!r}")
    return path


def _accepted(job: Job) -> web.Response:
    return web.json_response({"job": job.to_json()}, status=202, headers={"Location": f"/api/jobs/{job.id}"})


def map_catalog(settings: HostSettings) -> dict[str, Path]:
    """The maps the web page may name (shipped ones and the host config's), by name. Never a path from a
    request: a client names a map, the host knows where it is."""
    catalog = {p.stem: p for p in shipped_maps()}
    for configured in (settings.map, settings.second_map):
        if configured:
            try:
                path = find_map(configured)
                catalog[AppearanceMap.load(path).name] = path
            except TrimeterError:
                continue  # `serve` refuses it at start; here it is simply not offered
    return catalog


# -------------------------------------------------------------------------------------- routes
routes = web.RouteTableDef()


@routes.get("/")
async def index(request: web.Request) -> web.StreamResponse:
    token = request.query.get("token")
    if token is not None:
        if not auth.token_matches(request.app[TOKEN], token):
            return web.Response(status=401, text="wrong token: use the link `trimeter serve --show-token` prints\n")
        response = web.HTTPFound("/")
        response.set_cookie(auth.COOKIE, token, httponly=True, samesite="Strict", path="/",
                            max_age=400 * 24 * 3600)
        raise response
    if not auth.token_matches(request.app[TOKEN], request.cookies.get(auth.COOKIE)):
        return web.Response(status=401, content_type="text/html", text=(
            "<!doctype html><title>trimeter</title><p>Open this page with its token: "
            "<code>trimeter serve --show-token</code> prints the link.</p>"))
    return web.Response(text=_static_text("index.html"), content_type="text/html",
                        headers={"Cache-Control": "no-store"})


def _static_text(name: str) -> str:
    return (STATIC / name).read_text()


@routes.get("/api/openapi.json")
async def openapi_route(request: web.Request) -> web.StreamResponse:
    return web.json_response(openapi())


@routes.get("/api/status")
async def status(request: web.Request) -> web.StreamResponse:
    return web.json_response(request.app[JOBS].status())


@routes.get("/api/jobs/{job_id}")
async def job_route(request: web.Request) -> web.StreamResponse:
    job = request.app[JOBS].job(request.match_info["job_id"])
    if job is None:
        raise ApiError(404, f"no job {request.match_info['job_id']!r} (the last {len(request.app[JOBS].recent)} "
                            f"are kept)")
    return web.json_response({"job": job.to_json()})


@routes.post("/api/calibrate")
async def calibrate(request: web.Request) -> web.StreamResponse:
    body = await json_body(request, ("holder_empty",))
    holder_empty = body.get("holder_empty", False)
    if not isinstance(holder_empty, bool):
        raise ApiError(400, f"holder_empty: {holder_empty!r} is not true or false")
    jobs = request.app[JOBS]
    service = jobs.service

    def ask(job: Job) -> str:
        service.ask_to_calibrate("a calibration was asked for on the web page")
        job.message = "empty the sample holder, then confirm (or press the button)"
        return "asked"

    def confirmed(job: Job) -> str:
        if service.pattern != EMPTY_HOLDER:  # answered meanwhile (the button, another client)
            job.message = "the instrument was no longer asking for an empty holder; nothing was done"
            return "refused"
        service.calibration_requested = service.calibration_requested or "a calibration was confirmed on the web page"
        return service.handle_press()

    if holder_empty and service.pattern != EMPTY_HOLDER:
        raise ApiError(409, "the instrument is not asking for an empty holder: POST /api/calibrate without "
                            "holder_empty first, empty the holder, then confirm")
    return _accepted(jobs.submit("calibrate", body, confirmed if holder_empty else ask))


def _unresolved(samples: list[tuple[float, str | None]], service: Service) -> str | None:
    """Why these samples cannot be fitted here (None: they can). A DeviceError (no table in the device)
    is answered, not raised into the worker, which would take it for a lost link; a link really lost is
    found by the loop's next poll."""
    try:
        service.resolve_samples(samples)
    except DeviceError as exc:
        return str(exc)
    return None


@routes.post("/api/measure")
async def measure(request: web.Request) -> web.StreamResponse:
    body = await json_body(request, ("label", "thickness_mm", "second_thickness_mm"))
    jobs = request.app[JOBS]
    service = jobs.service
    settings = service.settings
    label = body.get("label")
    if label is not None and (not isinstance(label, str) or not LABEL.fullmatch(label)):
        raise ApiError(400, f"label: {label!r} must be 1-64 letters, digits, '.', '_' or '-', starting with a letter "
                            f"or digit (it names the results directory)")
    thickness = number(body, "thickness_mm", default=settings.thickness_mm, maximum=MAX_THICKNESS_MM)
    second = number(body, "second_thickness_mm", default=None, maximum=MAX_THICKNESS_MM, allow_zero=True)
    configured = dict(reversed(settings.serve_samples))  # thickness → the host config's map for it, if any
    samples = [(t, configured.get(t)) for t in (thickness, second) if t]
    if jobs.current is not None:  # before the check below, which would wait for the worker
        raise Busy(jobs.current)
    # resolved now, as the job will (a sample without a configured map: the instrument's table, read on the
    # worker thread that owns the device link), so a thickness nothing here fits is a 400, not a failed job
    if all(m for _, m in samples):
        await _blocking(request, lambda: [map_for_thickness(t, m) for t, m in samples])
    elif problem := await _device_call(request, functools.partial(_unresolved, samples)):
        raise ApiError(400, problem)
    if service.pattern == EMPTY_HOLDER:
        raise ApiError(409, "a calibration is due: the instrument asks for an empty holder first "
                            "(confirm with POST /api/calibrate {\"holder_empty\": true})")

    def run(job: Job) -> str:
        return service.handle_press(samples, label)

    return _accepted(jobs.submit("measure", {"label": label, "thicknesses_mm": [t for t, _ in samples]}, run))


@routes.post("/api/next-sample")
async def next_sample(request: web.Request) -> web.StreamResponse:
    await json_body(request, ())
    service = request.app[JOBS].service
    if service.pattern != NEXT_SAMPLE:
        raise ApiError(409, "the instrument is not waiting for a next sample")
    service.confirm_next_sample()
    return web.json_response({"confirmed": True})


@routes.get("/api/maps")
async def maps_route(request: web.Request) -> web.StreamResponse:
    """The maps a refit may name and the methods; and, to see what else this host holds, the tables read
    from instruments into its cache (headers only; a file that is no table is listed with a note)."""
    catalog = await _blocking(request, map_catalog, request.app[JOBS].service.settings)
    tables = await _blocking(request, cached_tables)
    return web.json_response({"maps": sorted(catalog), "methods": list(METHODS),
                              "instrument_tables": [{**table, "source": "instrument cache"} for table in tables]})


# ---------------------------------------------------------------------------------- history
def _search_args(request: web.Request) -> dict:
    q = request.query
    flagged = q.get("flagged")
    if flagged is not None and flagged.lower() not in ("true", "false", "yes", "no", "1", "0"):
        raise ApiError(400, f"flagged: {flagged!r} is not true or false")
    return {"label": q.get("label") or None, "instrument": q.get("instrument") or None,
            "since": parse_day_or_time(q["since"], "since") if q.get("since") else None,
            "until": parse_day_or_time(q["until"], "until", end=True) if q.get("until") else None,
            "flagged": None if flagged is None else flagged.lower() in ("true", "yes", "1"),
            "flag": q.get("flag") or None}


def _spreadsheet_safe(value: object) -> object:
    """A text cell a spreadsheet would run as a formula (a label from the CLI may start with '=') is quoted."""
    if value is None:
        return ""
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + value
    return value


@routes.get("/api/measurements")
async def measurements(request: web.Request) -> web.StreamResponse:
    args = _search_args(request)
    history = request.app[HISTORY]
    if request.query.get("format") == "csv":
        def export() -> list[dict]:
            rows, offset = [], 0
            while True:
                page, total = history.search(**args, limit=500, offset=offset)
                rows += page
                offset += len(page)
                if not page or offset >= total:
                    return rows
        rows = await _blocking(request, export)
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(CSV_COLUMNS)
        for row in rows:
            writer.writerow([_spreadsheet_safe(" ".join(map(str, v)) if isinstance(v, list) else v)
                             for v in (row[c] for c in CSV_COLUMNS)])
        return web.Response(text=text.getvalue(), content_type="text/csv",
                            headers={"Content-Disposition": 'attachment; filename="trimeter-history.csv"'})
    limit, offset = _query_int(request, "limit", 50), _query_int(request, "offset", 0)
    rows, total = await _blocking(request, lambda: history.search(**args, limit=limit, offset=offset))
    return web.json_response({"measurements": rows, "total": total, "limit": limit, "offset": offset})


def _details(history: History, path: Path) -> dict:
    row = history.get(path.name) or history.add(path)
    if row is None:
        raise ApiError(404, f"{path.name} has no readable measurement.json")
    from trimeter.results.reader import load, read_record

    out: dict[str, object] = {"measurement": row}
    problems: list[str] = []
    try:  # a record with a damaged file is shown with what it has, and says what it lacks
        out["meta"] = read_record(path)
    except InputError as exc:
        out["meta"] = None
        problems.append(str(exc))
    try:
        stored = load(path)
        out["parameters"] = stored.parameters_document()
        flags = stored.flags.tolist()
    except (InputError, OverflowError) as exc:
        out["parameters"], flags = None, []
        problems.append(str(exc))
    out["problems"] = problems
    counts: dict[str, int] = {}
    for value in flags:
        for name in describe(value).split("|"):
            if name != "NONE":
                counts[name] = counts.get(name, 0) + 1
    out["flag_counts"] = counts
    out["advice"] = advice(flags, max(1, len(row["thicknesses_mm"])))
    out["files"] = [p.name for p in regular_files(path)]
    return out


def _flag_words(parameters: object) -> list[int] | None:
    """The combined fit's flag words of a parameters.json, or None when it holds no list of them (a flag
    word is a non-negative integer that fits the 64-bit words the index stores)."""
    combined = parameters.get("combined") if isinstance(parameters, dict) else None
    flags = combined.get("flags") if isinstance(combined, dict) else None
    if not isinstance(flags, list) or not all(type(v) is int and 0 <= v < 2**63 for v in flags):
        return None
    return flags


@routes.get("/api/measurements/{id}")
async def measurement(request: web.Request) -> web.StreamResponse:
    path = _measurement_dir(request)
    return web.json_response(await _blocking(request, _details, request.app[HISTORY], path))


@routes.get("/api/measurements/{id}/files/{name}")
async def measurement_file(request: web.Request) -> web.StreamResponse:
    path = _measurement_dir(request)
    name = request.match_info["name"]
    if "/" in name or "\\" in name or ".." in name or name.startswith(".") or "\0" in name:
        raise ApiError(400, f"{name!r} is not a file name (no paths, no '..')")
    if len(name.encode("utf-8", "surrogatepass")) > NAME_MAX:
        raise ApiError(404, f"{path.name} has no file {name[:40]!r}… (longer than any file name)")
    target = path / name

    def read() -> bytes | None:
        try:  # opened without following a link, refused unless a regular file: never a read outside the record
            return _record_file_bytes(target)
        except (InputError, OSError):
            return None

    data = await _blocking(request, read)
    if data is None:
        raise ApiError(404, f"{path.name} has no file {name!r}")
    disposition = "inline" if target.suffix in (".png", ".json") else "attachment"
    content_type = mimetypes.guess_type(name)[0] or "application/octet-stream"
    return web.Response(body=data, content_type=content_type,
                        headers={"Content-Disposition": f'{disposition}; filename="{name}"',
                                 "Cache-Control": "no-cache"})


def _record_file_bytes(path: Path) -> bytes:
    """A results directory's file, if it is a regular file (not a link, FIFO or device) within the size limit."""
    with open_checked(path, max_bytes=MAX_RESULT_FILE_BYTES, follow_symlinks=False, binary=True) as f:
        data: bytes = f.read(MAX_RESULT_FILE_BYTES + 1)
    return data


def _zip(path: Path) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as z:
        for file in regular_files(path):
            try:
                data = _record_file_bytes(file)
            except (InputError, OSError):  # replaced by something else meanwhile: left out, as a link would be
                continue
            z.writestr(f"{path.name}/{file.name}", data)
    return buffer.getvalue()


@routes.get("/api/measurements/{id}/zip")
async def measurement_zip(request: web.Request) -> web.StreamResponse:
    path = _measurement_dir(request)
    data = await _blocking(request, _zip, path)
    return web.Response(body=data, content_type="application/zip",
                        headers={"Content-Disposition": f'attachment; filename="{path.name}.zip"'})


@routes.post("/api/measurements/{id}/refit")
async def refit_route(request: web.Request) -> web.StreamResponse:
    from trimeter.web.refit import paper_refit_problem, recorded_maps, refit

    path = _measurement_dir(request)
    body = await json_body(request, ("maps", "method"))
    jobs = request.app[JOBS]
    method = body.get("method", jobs.service.settings.method)
    if not isinstance(method, str) or method not in METHODS:
        raise ApiError(400, f"method: {method!r} is not one of {', '.join(METHODS)}")
    names = body.get("maps")
    catalog = await _blocking(request, map_catalog, jobs.service.settings)
    if names is not None:
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise ApiError(400, "maps: a list of map names, one per thickness")
        if unknown := [n for n in names if n not in catalog]:
            raise ApiError(400, f"maps: {', '.join(map(repr, unknown))} not known here "
                                f"(GET /api/maps lists them: {', '.join(sorted(catalog))})")

    def resolve() -> tuple[list[str], list[MapRef]]:
        from trimeter.results.reader import read_record

        if names:
            return names, [AppearanceMap.load(catalog[name]) for name in names]
        meta = read_record(path)
        return meta.get("maps") or [], recorded_maps(meta, catalog, functools.partial(_instrument_table, jobs))

    resolved: tuple[list[str], list[MapRef]] | None = None
    if method == "paper":  # its cost is known before it runs: too large a one is refused, not started
        resolved = await _blocking(request, resolve)
        if problem := await _blocking(request, paper_refit_problem, path, resolved[1]):
            raise ApiError(400, problem)

    def run(job: Job) -> str:
        chosen, maps = resolved or resolve()
        # beside the instrument's queue and in a process of its own: a slow or stuck fit neither holds the
        # instrument nor runs past the limit
        new = run_with_time_limit(refit, (path, maps, method), REFIT_TIME_LIMIT_S, "the re-fit")
        jobs.on_measurement(new)
        job.measurement = new.name
        job.message = f"re-fitted with {', '.join(chosen)} ({method}) into {new.name}"
        return "refitted"

    return _accepted(jobs.run_apart("refit", {"of": path.name, "maps": names, "method": method}, run))


def _instrument_table(jobs: Jobs) -> DeviceTable:
    """The instrument's active table, read on the worker thread that owns the link (from another thread)."""
    future = jobs.call(lambda service: service.instrument_table())
    try:
        return future.result(DEVICE_CALL_TIMEOUT_S)
    except concurrent.futures.TimeoutError:
        future.cancel()
        raise DeviceError(f"the instrument did not answer within {DEVICE_CALL_TIMEOUT_S:g} s") from None


# ----------------------------------------------------------------------------------- config
@routes.get("/api/config")
async def get_config(request: web.Request) -> web.StreamResponse:
    jobs = request.app[JOBS]
    device, source = jobs.device_config, "cached"
    if jobs.current is None and jobs.service.device is not None:
        config = await _device_call(request, lambda service: service.connected_device().config())
        jobs.set_device_config(config)
        device, source = jobs.device_config, "read"
    return web.json_response({"host": jobs.service.settings.as_dict(), "host_file": str(HostSettings.path()),
                              "device": device, "device_source": source, "device_writable": list(CONFIG_NAMES)})


@routes.put("/api/config")
async def put_config(request: web.Request) -> web.StreamResponse:
    body = await json_body(request, ("host", "device", "save"))
    jobs = request.app[JOBS]
    host, device, save = body.get("host") or {}, body.get("device") or {}, body.get("save", False)
    if not isinstance(host, dict) or not isinstance(device, dict) or not isinstance(save, bool):
        raise ApiError(400, "host and device must be objects of NAME: value, save true or false")
    # every check before anything changes: a bad item leaves both configurations as they were
    stored, running = HostSettings.load(), copy.deepcopy(jobs.service.settings)
    stored.update(host, source="PUT /api/config")
    running.update(host, source="PUT /api/config")
    if unknown := [n for n in device if n not in CONFIG_NAMES]:
        raise ApiError(400, f"not device configuration items: {', '.join(unknown)} (see device_writable)")
    for name, value in device.items():
        encode(regs.BY_NAME[name], value)
    if (device or save) and jobs.current is not None:
        raise Busy(jobs.current)
    if device or save:  # the device first: when it refuses, the host's part is not saved either
        def write(service: Service) -> dict:
            connected = service.connected_device()
            if device:
                connected.write_config(device)
            if save:
                connected.command("save_config")
                connected.wait_idle(10.0)
            return connected.config()

        if jobs.service.device is None:
            raise ApiError(503, "the instrument is not connected")
        jobs.set_device_config(await _device_call(request, write))
    if host:
        await _blocking(request, stored.save)
        for key in host:  # the running loop reads its settings object: changed in place
            setattr(jobs.service.settings, key, getattr(running, key))
    return web.json_response({"host": jobs.service.settings.as_dict(), "device": jobs.device_config,
                              "saved": save})


# ----------------------------------------------------------------------------------- events
@routes.get("/api/events")
async def events(request: web.Request) -> web.StreamResponse:
    ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=4096)
    await ws.prepare(request)
    queue: asyncio.Queue = asyncio.Queue(EVENT_QUEUE)
    clients: set = request.app[STATE]["clients"]
    clients.add(queue)
    receiver = getter = None
    try:
        await ws.send_json({"type": "status", "status": request.app[JOBS].status()})
        receiver = asyncio.ensure_future(ws.receive())
        while not ws.closed:
            getter = asyncio.ensure_future(queue.get())
            done, _ = await asyncio.wait({getter, receiver}, return_when=asyncio.FIRST_COMPLETED)
            if receiver in done:
                getter.cancel()
                message = receiver.result()
                if message.type in (WSMsgType.CLOSE, WSMsgType.CLOSED, WSMsgType.CLOSING, WSMsgType.ERROR):
                    break
                receiver = asyncio.ensure_future(ws.receive())  # clients have nothing to say: ignored
                continue
            record = getter.result()
            if record is None:   # fell too far behind
                await ws.close(message=b"too slow")
                break
            await ws.send_json(record)
    finally:  # also when a send fails on a vanished client: no task left pending on its socket
        for task in (receiver, getter):
            if task is not None:
                task.cancel()
        clients.discard(queue)
    return ws


def _broadcast(app: web.Application, record: dict) -> None:
    """On the event loop: hand one record to every websocket client."""
    for queue in list(app[STATE]["clients"]):
        try:
            queue.put_nowait(record)
        except asyncio.QueueFull:
            app[STATE]["clients"].discard(queue)
            while not queue.empty():
                queue.get_nowait()
            queue.put_nowait(None)


async def _notify(app: web.Application, url: str, record: dict) -> None:
    try:
        async with app[STATE]["http"].post(url, json=record) as response:
            if response.status >= 400:
                log.warning("webhook %s answered %s", url, response.status)
    except Exception as exc:  # a notification must never disturb the instrument
        log.warning("webhook %s failed: %s", url, exc)


def webhook_record(job: dict) -> dict | None:
    """The notification for a finished job (done / failed / flagged), or None for one not worth one."""
    if job["state"] not in ("done", "failed") or job["outcome"] == "asked":
        return None
    event = "failed" if job["state"] == "failed" else "flagged" if job["flagged"] else "done"
    return {"event": event, "job": job, "measurement": job["measurement"]}


# ---------------------------------------------------------------------------------- the app
def create_app(jobs: Jobs, history: History, token: str, *, webhook: str | None = None) -> web.Application:
    app = web.Application(middlewares=[errors_middleware, auth_middleware], client_max_size=MAX_BODY_BYTES)
    app[JOBS], app[HISTORY], app[TOKEN] = jobs, history, token
    app[STATE] = {"clients": set(), "executor": ThreadPoolExecutor(1, thread_name_prefix="trimeter-web-files")}
    app.add_routes(routes)
    library_routes.register(app)
    app.router.add_static("/static/", STATIC, show_index=False)
    app.on_response_prepare.append(security_headers)

    async def started(app: web.Application) -> None:
        loop = asyncio.get_running_loop()
        app[STATE]["http"] = ClientSession(timeout=ClientTimeout(total=WEBHOOK_TIMEOUT_S))

        def listener(record: dict) -> None:   # on the worker thread
            loop.call_soon_threadsafe(_broadcast, app, record)
            if webhook and record.get("type") == "job" and (note := webhook_record(record["job"])):
                asyncio.run_coroutine_threadsafe(_notify(app, webhook, note), loop)

        app[STATE]["listener"] = listener
        jobs.listeners.append(listener)

    async def stopping(app: web.Application) -> None:
        jobs.listeners.remove(app[STATE]["listener"])
        for queue in list(app[STATE]["clients"]):
            queue.put_nowait(None) if not queue.full() else None
        await app[STATE]["http"].close()
        app[STATE]["executor"].shutdown(wait=False)

    app.on_startup.append(started)
    app.on_cleanup.append(stopping)
    return app


def create_lab_app(lab: list[tuple[Instrument, Jobs]], history: History, token: str, *,
                   webhook: str | None = None) -> web.Application:
    """Several instruments (trimeter.web.instruments_routes): the root API is the first one's, every one's whole
    API under /instruments/{name}/; the webhook goes out from the instruments' own apps (once per job)."""
    return instruments_routes.mount(create_app(lab[0][1], history, token), lab,
                                    lambda jobs: create_app(jobs, history, token, webhook=webhook))


class ClientErrorsInOneLine(logging.Filter):
    """aiohttp logs a request it could not parse (malformed headers, a Content-Encoding it cannot decode) with a
    traceback at ERROR, though it answered the client 400, and so a body it drains after the answer that turns
    out undecodable: a client's mistake is one warning line here."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        client_error = isinstance(exc, HttpProcessingError) and 400 <= (exc.code or 400) < 500
        if client_error or isinstance(exc, RequestPayloadError):
            record.msg = f"{record.getMessage()}: {' '.join(str(getattr(exc, 'message', exc)).split())}"
            record.args, record.exc_info, record.exc_text = (), None, None
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True


CLIENT_ERRORS_FILTER = ClientErrorsInOneLine()


class WebServer:
    """The app on its own thread and event loop (the instrument's worker has another thread; the main
    thread waits for Ctrl-C)."""

    def __init__(self, app: web.Application, host: str, port: int, *, header_timeout_s: float = HEADER_TIMEOUT_S
                 ) -> None:
        self.app, self.host, self.port = app, host, port
        self.header_timeout_s = header_timeout_s
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="trimeter-web", daemon=True)
        self.url = ""

    def start(self) -> "WebServer":
        server_log = logging.getLogger("aiohttp.server")
        if CLIENT_ERRORS_FILTER not in server_log.filters:
            server_log.addFilter(CLIENT_ERRORS_FILTER)
        self._thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise InputError(f"--http {self.host}:{self.port}: cannot listen ({self._error})")
        return self

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        runner = web.AppRunner(self.app, access_log=None, handle_signals=False, keepalive_timeout=self.header_timeout_s)
        try:
            self._loop.run_until_complete(runner.setup())
            site = web.TCPSite(runner, self.host, self.port, backlog=256)
            self._loop.run_until_complete(site.start())
            port = runner.addresses[0][1]
            host = f"[{self.host}]" if ":" in self.host else self.host
            self.url = f"http://{host}:{port}"
        except BaseException as exc:
            self._error = exc
            self._ready.set()
            self._loop.run_until_complete(runner.cleanup())
            return
        self._ready.set()
        self._loop.run_forever()
        self._loop.run_until_complete(runner.cleanup())
        self._loop.close()

    def close(self) -> None:
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(15)


def parse_bind(text: str) -> tuple[str, int]:
    """`HOST:PORT`, `[IPv6]:PORT` or `PORT` (then 127.0.0.1)."""
    match = re.fullmatch(r"(?:\[([0-9A-Fa-f:.]+)\]|([^:\[\]]*)):(\d{1,5})|(\d{1,5})", text.strip())
    if not match:
        raise InputError(f"--http: {text!r} is not HOST:PORT (e.g. 127.0.0.1:8080, 0.0.0.0:8080 for the LAN)")
    host = match[1] or match[2] or "127.0.0.1"
    port = int(match[3] or match[4])
    if port > 65535:
        raise InputError(f"--http: port {port} is not within 0..65535")
    return host, port


def openapi() -> dict:
    """The API's OpenAPI 3.1 description (served at /api/openapi.json)."""
    def op(summary: str, *, body: dict | None = None, params: Sequence[tuple[str, str, str, str]] = (),
           responses: dict | None = None) -> dict:
        out = {"summary": summary, "responses": {"200": {"description": "OK"}, "401": {"description": "no or wrong "
                                                                                                         "token"},
                                                 **(responses or {})}}
        if body:
            out["requestBody"] = {"content": {"application/json": {"schema": {"type": "object", "properties": body,
                                                                              "additionalProperties": False}}}}
        if params:
            out["parameters"] = [{"name": n, "in": where, "required": where == "path", "schema": {"type": t},
                                  "description": d} for n, where, t, d in params]
        return out

    job = {"202": {"description": "accepted: {job}, Location /api/jobs/{id}"},
           "409": {"description": "a job is queued or running: {error: {job}}"}}
    mid = ("id", "path", "string", "a results directory's name")
    search = [("label", "query", "string", "part of the label"), ("since", "query", "string", "YYYY-MM-DD or ISO time"),
              ("until", "query", "string", "YYYY-MM-DD (inclusive) or ISO time"),
              ("instrument", "query", "string", "only those of the instrument of this name"),
              ("flagged", "query", "boolean", "only measurements with (true) / without (false) flagged bins"),
              ("flag", "query", "string", "only those with this FitFlag (e.g. UNDERDETERMINED)"),
              ("limit", "query", "integer", "page size, 1..500 (default 50)"), ("offset", "query", "integer", ""),
              ("format", "query", "string", "csv: every match as CSV")]
    number_ = {"type": "number"}
    return {
        "openapi": "3.1.0",
        "info": {"title": "trimeter", "version": "1",
                 "description": "The instrument on the LAN. Errors: {error: {status, message}}. Access: cookie "
                                "trimeter_token or Authorization: Bearer."},
        "components": {"securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"},
                                           "cookie": {"type": "apiKey", "in": "cookie", "name": auth.COOKIE}}},
        "security": [{"bearer": []}, {"cookie": []}],
        "paths": {
            "/api/status": {"get": op("state, current job, step and progress, lamp drift, calibration age, device "
                                      "identity, active map table")},
            "/api/jobs/{job_id}": {"get": op("one job (the current or one of the last 20)",
                                             params=[("job_id", "path", "string", "")])},
            "/api/calibrate": {"post": op("ask for an empty holder; with holder_empty: true (while asked) check "
                                          "the holder, warm up and calibrate", body={"holder_empty":
                                                                                    {"type": "boolean"}},
                                          responses=job)},
            "/api/measure": {"post": op("measure the sample(s) in the holder", body={
                "label": {"type": "string"}, "thickness_mm": number_, "second_thickness_mm": number_},
                responses=job)},
            "/api/next-sample": {"post": op("the next sample is in (while asked for, with two thicknesses)",
                                            responses={"409": {"description": "not asked for"}})},
            "/api/maps": {"get": op("maps a refit may name, the methods, and the instrument tables in this host's "
                                    "cache (name, parent map's SHA-256, n, ℓ, geometry, size; a note for a "
                                    "corrupt file)")},
            "/api/measurements": {"get": op("search the history, newest first", params=search)},
            "/api/measurements/{id}": {"get": op("one measurement: index row, measurement.json, parameters, "
                                                 "flags in words, files", params=[mid])},
            "/api/measurements/{id}/files/{name}": {"get": op("one file of it", params=[
                mid, ("name", "path", "string", "a file name from `files`")])},
            "/api/measurements/{id}/zip": {"get": op("its whole directory as a zip", params=[mid])},
            "/api/measurements/{id}/refit": {"post": op("fit its capture again (another map or method) into a new "
                                                        "record", params=[mid], responses=job, body={
                                                            "maps": {"type": "array", "items": {"type": "string"}},
                                                            "method": {"enum": list(METHODS)}})},
            "/api/config": {"get": op("host and device configuration"),
                            "put": op("change host settings and/or device items (all checked first; nothing "
                                      "changes on an error); save: store the device's in its flash", body={
                                          "host": {"type": "object"}, "device": {"type": "object"},
                                          "save": {"type": "boolean"}})},
            "/api/events": {"get": op("websocket: the service's events, progress and jobs as JSON, live")},
            "/api/openapi.json": {"get": op("this description")},
            **library_routes.OPENAPI_PATHS,
            **instruments_routes.OPENAPI_PATHS,
        },
    }
