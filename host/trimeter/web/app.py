"""`trimeter serve --http`: the instrument on the LAN — a JSON API, a live event websocket and a page.

aiohttp: one dependency that is both the server (HTTP/1.1, websockets, file responses) and the client
(webhooks, `trimeter bench http`), running on plain asyncio in the serve process next to the
instrument's worker thread; no ASGI server or framework layer to configure. The API is the product
and the page (static/) one client of it; every answer is JSON, errors as {"error": {"status",
"message"}}. See trimeter.web.openapi for the endpoints, trimeter.web.auth for access, trimeter.web.jobs for
how the button and the page share the instrument.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from aiohttp import web

from trimeter.sequences.instruments import Instrument
from trimeter.web import (auth, config_routes, events, history_routes, instruments_routes, job_routes, library_routes,
                          refit_routes)
from trimeter.web.handler_tools import HISTORY, JOBS, MAX_BODY_BYTES, STATE, TOKEN
from trimeter.web.history import History
from trimeter.web.jobs import Jobs
from trimeter.web.middleware import auth_middleware, errors_middleware, security_headers
from trimeter.web.openapi import openapi

STATIC = Path(__file__).resolve().parent / "static"   # package data (pyproject)

routes = web.RouteTableDef()   # the page and the API's description; the API's own routes are in ROUTE_TABLES


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


# Every route of one instrument's app, by concern (the library's and the static files' are added by create_app).
ROUTE_TABLES = (routes, job_routes.routes, refit_routes.routes, history_routes.routes, config_routes.routes,
                events.routes)


def create_app(jobs: Jobs, history: History, token: str, *, webhook: str | None = None) -> web.Application:
    app = web.Application(middlewares=[errors_middleware, auth_middleware], client_max_size=MAX_BODY_BYTES)
    app[JOBS], app[HISTORY], app[TOKEN] = jobs, history, token
    app[STATE] = {"executor": ThreadPoolExecutor(1, thread_name_prefix="trimeter-web-files")}
    for table in ROUTE_TABLES:
        app.add_routes(table)
    library_routes.register(app)
    app.router.add_static("/static/", STATIC, show_index=False)
    app.on_response_prepare.append(security_headers)
    events.attach(app, jobs, webhook)

    async def stopping(app: web.Application) -> None:
        app[STATE]["executor"].shutdown(wait=False)

    app.on_cleanup.append(stopping)
    return app


def create_lab_app(lab: list[tuple[Instrument, Jobs]], history: History, token: str, *,
                   webhook: str | None = None) -> web.Application:
    """Several instruments (trimeter.web.instruments_routes): the root API is the first one's, every one's whole
    API under /instruments/{name}/; the webhook goes out from the instruments' own apps (once per job)."""
    return instruments_routes.mount(create_app(lab[0][1], history, token), lab,
                                    lambda jobs: create_app(jobs, history, token, webhook=webhook))

