"""Fitting a stored measurement again over the API: the maps a re-fit may name (GET /api/maps) and the re-fit
itself (POST /api/measurements/{id}/refit), run beside the instrument in a child process (trimeter.web.refit
does the fit)."""

from __future__ import annotations

import concurrent.futures
import functools
from pathlib import Path
from typing import TYPE_CHECKING

from aiohttp import web

from trimeter.device.table_cache import cached_tables
from trimeter.errors import DeviceError, TrimeterError
from trimeter.formats.appearance import AppearanceMap, find_map, shipped_maps
from trimeter.formats.device_table import DeviceTable
from trimeter.inversion.methods import METHODS
from trimeter.sequences.settings import HostSettings
from trimeter.web.handler_tools import (DEVICE_CALL_TIMEOUT_S, JOBS, ApiError, accepted, blocking, json_body,
                                        measurement_dir)
from trimeter.web.isolated import run_with_time_limit
from trimeter.web.jobs import Job, Jobs

if TYPE_CHECKING:
    from trimeter.domain.measurement import MapRef

REFIT_TIME_LIMIT_S = 300.0          # a re-fit runs in a child process, stopped at this

routes = web.RouteTableDef()


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


@routes.get("/api/maps")
async def maps_route(request: web.Request) -> web.StreamResponse:
    """The maps a refit may name and the methods; and, to see what else this host holds, the tables read
    from instruments into its cache (headers only; a file that is no table is listed with a note)."""
    catalog = await blocking(request, map_catalog, request.app[JOBS].service.settings)
    tables = await blocking(request, cached_tables)
    return web.json_response({"maps": sorted(catalog), "methods": list(METHODS),
                              "instrument_tables": [{**table, "source": "instrument cache"} for table in tables]})


@routes.post("/api/measurements/{id}/refit")
async def refit_route(request: web.Request) -> web.StreamResponse:
    from trimeter.web.refit import paper_refit_problem, recorded_maps, refit

    path = measurement_dir(request)
    body = await json_body(request, ("maps", "method"))
    jobs = request.app[JOBS]
    method = body.get("method", jobs.service.settings.method)
    if not isinstance(method, str) or method not in METHODS:
        raise ApiError(400, f"method: {method!r} is not one of {', '.join(METHODS)}")
    names = body.get("maps")
    catalog = await blocking(request, map_catalog, jobs.service.settings)
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
        resolved = await blocking(request, resolve)
        if problem := await blocking(request, paper_refit_problem, path, resolved[1]):
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

    return accepted(jobs.run_apart("refit", {"of": path.name, "maps": names, "method": method}, run))


def _instrument_table(jobs: Jobs) -> DeviceTable:
    """The instrument's active table, read on the worker thread that owns the link (from another thread)."""
    future = jobs.call(lambda service: service.instrument_table())
    try:
        return future.result(DEVICE_CALL_TIMEOUT_S)
    except concurrent.futures.TimeoutError:
        future.cancel()
        raise DeviceError(f"the instrument did not answer within {DEVICE_CALL_TIMEOUT_S:g} s") from None

