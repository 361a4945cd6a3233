"""Several instruments on one page: GET /api/instruments (each one's state, calibration age, active table and
jobs), and each instrument's whole API under /instruments/{name}/ (…/api/status, …/api/calibrate,
…/api/measure, …/api/jobs/{id}, …/api/events), served by the same app as a single instrument's, mounted once per
instrument. The root API (/api/status, /api/calibrate …) is the first instrument's, so a page or script made for
one instrument keeps working; the history is shared, each measurement tagged with its instrument.
"""

from __future__ import annotations

from collections.abc import Callable

from aiohttp import web

from trimeter.sequences.instruments import Instrument
from trimeter.web.jobs import Jobs

INSTRUMENTS = web.AppKey("instruments", list)
OPENAPI_PATHS = {
    "/api/instruments": {"get": {
        "summary": "serve with several instruments: each one's name, port, Modbus address, API prefix and status (as "
                   "/api/status); the root API is the first instrument's",
        "responses": {"200": {"description": "OK"}, "404": {"description": "one instrument only"}}}},
    "/instruments/{name}/api/...": {"get": {
        "summary": "that instrument's whole API (status, jobs, calibrate, measure, next-sample, events, config …), "
                   "as the root API is the first one's",
        "parameters": [{"name": "name", "in": "path", "required": True, "schema": {"type": "string"},
                        "description": "the instrument's name"}],
        "responses": {"200": {"description": "OK"}}}},
}


def instrument_status(instrument: Instrument, jobs: Jobs) -> dict:
    return {"name": instrument.name, "port": instrument.port, "address": instrument.address,
            "api": f"/instruments/{instrument.name}/api/", **jobs.status()}


async def instruments_route(request: web.Request) -> web.StreamResponse:
    return web.json_response({"instruments": [instrument_status(i, jobs) for i, jobs in request.app[INSTRUMENTS]]})


def mount(app: web.Application, lab: list[tuple[Instrument, Jobs]],
          instrument_app: Callable[[Jobs], web.Application]) -> web.Application:
    """`app` (the first instrument's) with GET /api/instruments and every instrument's `instrument_app(jobs)` mounted
    under /instruments/{name}/ (trimeter.web.app.create_lab_app)."""
    app[INSTRUMENTS] = list(lab)
    app.router.add_get("/api/instruments", instruments_route)
    for instrument, jobs in lab:
        app.add_subapp(f"/instruments/{instrument.name}/", instrument_app(jobs))
    return app
