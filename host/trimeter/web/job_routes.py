"""The instrument's work, asked for over the API: its status, its jobs, a calibration, a measurement and the
confirmation of a next sample (trimeter.web.jobs: the button and the page share the instrument)."""

from __future__ import annotations

import functools
import re
from typing import TYPE_CHECKING

from aiohttp import web

from trimeter.errors import DeviceError
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.service import EMPTY_HOLDER, NEXT_SAMPLE
from trimeter.web.handler_tools import JOBS, ApiError, accepted, blocking, device_call, json_body, number
from trimeter.web.jobs import Busy, Job

if TYPE_CHECKING:
    from trimeter.sequences.service import Service

LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
MAX_THICKNESS_MM = 100.0

routes = web.RouteTableDef()


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
    return accepted(jobs.submit("calibrate", body, confirmed if holder_empty else ask))


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
        await blocking(request, lambda: [map_for_thickness(t, m) for t, m in samples])
    elif problem := await device_call(request, functools.partial(_unresolved, samples)):
        raise ApiError(400, problem)
    if service.pattern == EMPTY_HOLDER:
        raise ApiError(409, "a calibration is due: the instrument asks for an empty holder first "
                            "(confirm with POST /api/calibrate {\"holder_empty\": true})")

    def run(job: Job) -> str:
        return service.handle_press(samples, label)

    return accepted(jobs.submit("measure", {"label": label, "thicknesses_mm": [t for t, _ in samples]}, run))


@routes.post("/api/next-sample")
async def next_sample(request: web.Request) -> web.StreamResponse:
    await json_body(request, ())
    service = request.app[JOBS].service
    if service.pattern != NEXT_SAMPLE:
        raise ApiError(409, "the instrument is not waiting for a next sample")
    service.confirm_next_sample()
    return web.json_response({"confirmed": True})

