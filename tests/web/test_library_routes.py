"""The Library view's JSON: GET /api/library and /api/library/{name} on an app with the library's routes
(as create_app registers them), behind the page's token."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path
from urllib.parse import quote

import numpy as np
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer

from browser_support import chrome, needs_browser
from library_support import fit_result, write_member
from trimeter.library.store import Library
from trimeter.web import library_routes
from trimeter.web.handler_tools import TOKEN
from trimeter.web.middleware import auth_middleware, errors_middleware

TOKEN_VALUE = "t" * 43


def _get(app: web.Application, path: str, token: str | None = TOKEN_VALUE):
    async def go():
        async with TestClient(TestServer(app)) as client:
            headers = {"Authorization": f"Bearer {token}"} if token else {}
            response = await client.get(path, headers=headers)
            return response.status, await response.json()
    return asyncio.run(go())


def _app(db: Path) -> web.Application:
    app = web.Application(middlewares=[errors_middleware, auth_middleware])
    app[TOKEN] = TOKEN_VALUE
    library_routes.register(app, db)
    return app


def test_materials_members_and_overlays(tmp_path):
    members = [write_member(tmp_path / "r", fit_result(0.9, 2.0, 0.5)),
               write_member(tmp_path / "r", fit_result(0.92, 2.1, 0.5))]
    with Library(tmp_path / "library.sqlite") as lib:
        lib.add("cyan batch 3", members, tags=["ink"])
    app = _app(tmp_path / "library.sqlite")
    status, body = _get(app, "/api/library")
    assert status == 200 and [m["name"] for m in body["materials"]] == ["cyan batch 3"]
    assert body["materials"][0]["members"] == 2 and body["materials"][0]["tags"] == ["ink"]
    status, body = _get(_app(tmp_path / "library.sqlite"), f"/api/library/{quote('cyan batch 3')}")
    assert status == 200 and body["combination"]["method"] == "inverse-variance"
    assert np.allclose(body["spectra"]["alpha"], 0.91, atol=1e-9)
    assert all(m["here"] and len(m["parameters"]["alpha"]) == len(body["spectra"]["alpha"]) for m in body["members"])
    shutil.rmtree(members[0])   # a member gone: shown as missing, the material still answers
    status, body = _get(_app(tmp_path / "library.sqlite"), f"/api/library/{quote('cyan batch 3')}")
    assert status == 200 and not body["members"][0]["here"] and "no longer exists" in body["member_problems"][0]


def test_errors_and_access(tmp_path):
    app = _app(tmp_path / "none.sqlite")
    assert _get(app, "/api/library") == (200, {"materials": [], "library": str(tmp_path / "none.sqlite")})
    assert not (tmp_path / "none.sqlite").exists()   # a read makes no file
    status, body = _get(_app(tmp_path / "none.sqlite"), "/api/library/cyan")
    assert status == 404 and "no material 'cyan'" in body["error"]["message"]
    status, body = _get(_app(tmp_path / "none.sqlite"), f"/api/library/{quote('../x')}")
    assert status in (400, 404)
    assert _get(_app(tmp_path / "none.sqlite"), "/api/library", token=None)[0] == 401


def test_create_app_registers_them_and_describes_them():
    from trimeter.web.openapi import openapi

    assert {"/api/library", "/api/library/{name}"} <= set(openapi()["paths"])




def _page_app(db: Path) -> web.Application:
    """The page's files, the library's routes and the page's security headers (no instrument)."""
    from trimeter.web.app import STATIC
    from trimeter.web.middleware import security_headers

    app = web.Application(middlewares=[errors_middleware])
    async def index(request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / "index.html")

    app.router.add_get("/", index)
    app.router.add_static("/static/", STATIC)
    app.on_response_prepare.append(security_headers)
    library_routes.register(app, db)
    return app


@needs_browser
def test_the_library_view_in_a_browser(tmp_path):
    """The list, one material's plot with its members overlaid and a missing member, no console error."""
    import threading

    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as EC
    from selenium.webdriver.support.ui import WebDriverWait

    members = [write_member(tmp_path / "r", fit_result(0.9 - 0.01 * i, 2.0 + 0.1 * i, 0.5)) for i in range(3)]
    with Library(tmp_path / "library.sqlite") as lib:
        lib.add("cyan batch 3", members, tags=["ink"])
    shutil.rmtree(members[2])
    loop = asyncio.new_event_loop()
    runner = web.AppRunner(_page_app(tmp_path / "library.sqlite"))
    loop.run_until_complete(runner.setup())
    site = web.TCPSite(runner, "127.0.0.1", 0)
    loop.run_until_complete(site.start())
    port = runner.addresses[0][1]
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    driver = chrome("1280,1100")
    try:
        wait = WebDriverWait(driver, 20)
        driver.get(f"http://127.0.0.1:{port}/#/library")
        link = wait.until(EC.element_to_be_clickable((By.LINK_TEXT, "cyan batch 3")))
        link.click()
        wait.until(EC.presence_of_element_located((By.CSS_SELECTOR, "#l-members tr")))
        rows = driver.find_elements(By.CSS_SELECTOR, "#l-members tr")
        assert len(rows) == 3 and "missing" in rows[2].text
        assert len(driver.find_elements(By.CSS_SELECTOR, "#l-plot path")) > 10   # bands, lines, members
        assert "no longer exists" in driver.find_element(By.ID, "l-problems").text
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"
                  and "/api/events" not in e["message"] and "favicon" not in e["message"]]  # no instrument here
        assert not errors, errors
    finally:
        driver.quit()
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.run_until_complete(runner.cleanup())
        loop.close()
