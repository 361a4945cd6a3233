"""The host's and the device's configuration over the API: read both, change either (everything checked before
anything changes), and store the device's in its flash."""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

from aiohttp import web

from trimeter import registers as regs
from trimeter.device.client import CONFIG_NAMES, encode
from trimeter.sequences.settings import HostSettings
from trimeter.web.handler_tools import JOBS, ApiError, blocking, device_call, json_body
from trimeter.web.jobs import Busy

if TYPE_CHECKING:
    from trimeter.sequences.service import Service

routes = web.RouteTableDef()


@routes.get("/api/config")
async def get_config(request: web.Request) -> web.StreamResponse:
    jobs = request.app[JOBS]
    device, source = jobs.device_config, "cached"
    if jobs.current is None and jobs.service.device is not None:
        config = await device_call(request, lambda service: service.connected_device().config())
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
        jobs.set_device_config(await device_call(request, write))
    if host:
        await blocking(request, stored.save)
        for key in host:  # the running loop reads its settings object: changed in place
            setattr(jobs.service.settings, key, getattr(running, key))
    return web.json_response({"host": jobs.service.settings.as_dict(), "device": jobs.device_config,
                              "saved": save})
