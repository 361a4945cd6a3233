"""The service's events out of the serve process: live to every websocket client of /api/events, and a finished
job's outcome to the webhook (`serve --webhook`)."""

from __future__ import annotations

import asyncio
import logging

from aiohttp import ClientSession, ClientTimeout, WSMsgType, web

from trimeter.web.handler_tools import JOBS, STATE
from trimeter.web.jobs import Jobs

log = logging.getLogger("trimeter.web")

EVENT_QUEUE = 256                   # events buffered per websocket client; a client that falls further behind is closed
WEBHOOK_TIMEOUT_S = 5.0

routes = web.RouteTableDef()


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


def attach(app: web.Application, jobs: Jobs, webhook: str | None) -> None:
    """While `app` runs: every event of `jobs` to its websocket clients, and a finished job's outcome to
    `webhook`."""
    app[STATE]["clients"] = set()

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

    app.on_startup.append(started)
    app.on_cleanup.append(stopping)
