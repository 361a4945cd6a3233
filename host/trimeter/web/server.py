"""The web app served: on its own thread and event loop, at the address `--http` names, with client errors
logged in one line."""

from __future__ import annotations

import asyncio
import logging
import re
import threading

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web_protocol import RequestPayloadError

from trimeter.errors import InputError

# A connection must complete its request's headers within this of opening or of its previous answer (aiohttp's
# keep-alive timer, which also runs until the first request): a client sending them slowly is dropped.
HEADER_TIMEOUT_S = 15.0


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


SHUTDOWN_S = 2.0


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
        # On close, requests in flight get SHUTDOWN_S to finish (aiohttp's own default, 60 s, outlasts close()'s
        # wait for the thread and leaves their handlers pending when the process exits)
        runner = web.AppRunner(self.app, access_log=None, handle_signals=False, keepalive_timeout=self.header_timeout_s,
                               shutdown_timeout=SHUTDOWN_S)
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
        # a kept-alive connection's handler may still wait for its next request: end it before the loop closes
        pending = asyncio.all_tasks(self._loop)
        for task in pending:
            task.cancel()
        self._loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
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

