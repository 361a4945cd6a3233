"""Closing the web server ends every connection's handler within its shutdown grace: a client still sending a
request body when the server closes leaves no task pending (asyncio would log "Task was destroyed but it is
pending!" for each at the process's exit), and close() does not wait for aiohttp's own 60 s."""

from __future__ import annotations

import asyncio
import socket
import time

from aiohttp import web

from trimeter.web.server import SHUTDOWN_S, WebServer


async def _read_body(request: web.Request) -> web.Response:
    await request.read()
    return web.Response(text="read")


def test_a_request_still_arriving_at_close_is_ended_and_leaves_no_pending_task():
    app = web.Application()
    app.router.add_post("/upload", _read_body)
    server = WebServer(app, "127.0.0.1", 0).start()
    host, port = server.url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=5) as sock:
        sock.sendall(b"POST /upload HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\nthe first bytes")
        time.sleep(0.2)  # the handler now waits for the rest of the body
        started = time.monotonic()
        server.close()
        assert time.monotonic() - started < SHUTDOWN_S + 5
        assert server._loop.is_closed()
        assert not [task for task in asyncio.all_tasks(server._loop) if not task.done()]
