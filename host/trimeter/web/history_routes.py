"""The measurement history over the API: search (JSON pages, or every match as CSV), one measurement's record
and flags in words, one of its files, and its whole directory as a zip. Read-only: a record is never changed."""

from __future__ import annotations

import csv
import io
import mimetypes
import zipfile
from pathlib import Path

from aiohttp import web

from trimeter.errors import InputError
from trimeter.inversion.flags import advice, describe
from trimeter.paths import NAME_MAX, regular_files
from trimeter.tables import MAX_RESULT_FILE_BYTES, open_checked
from trimeter.web.handler_tools import HISTORY, ApiError, blocking, measurement_dir, query_int
from trimeter.web.history import History, parse_day_or_time

CSV_COLUMNS = ("id", "written_utc", "label", "thicknesses_mm", "maps", "method", "bins", "flagged_bins",
               "flag_names", "incomplete", "refit_of")

routes = web.RouteTableDef()


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
        rows = await blocking(request, export)
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(CSV_COLUMNS)
        for row in rows:
            writer.writerow([_spreadsheet_safe(" ".join(map(str, v)) if isinstance(v, list) else v)
                             for v in (row[c] for c in CSV_COLUMNS)])
        return web.Response(text=text.getvalue(), content_type="text/csv",
                            headers={"Content-Disposition": 'attachment; filename="trimeter-history.csv"'})
    limit, offset = query_int(request, "limit", 50), query_int(request, "offset", 0)
    rows, total = await blocking(request, lambda: history.search(**args, limit=limit, offset=offset))
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


@routes.get("/api/measurements/{id}")
async def measurement(request: web.Request) -> web.StreamResponse:
    path = measurement_dir(request)
    return web.json_response(await blocking(request, _details, request.app[HISTORY], path))


@routes.get("/api/measurements/{id}/files/{name}")
async def measurement_file(request: web.Request) -> web.StreamResponse:
    path = measurement_dir(request)
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

    data = await blocking(request, read)
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
    path = measurement_dir(request)
    data = await blocking(request, _zip, path)
    return web.Response(body=data, content_type="application/zip",
                        headers={"Content-Disposition": f'attachment; filename="{path.name}.zip"'})

