"""Every response of `serve --http` carries the browser-side protections (trimeter.web.middleware.SECURITY_HEADERS):
the page, its static files, API answers and errors, redirects. The browser test (test_browser.py) checks
that the page still works under that Content-Security-Policy."""

from __future__ import annotations

import re

import pytest

from conftest import idle_web
from trimeter.web.app import STATIC


@pytest.fixture(scope="module")
def web(tmp_path_factory):
    with idle_web(tmp_path_factory.mktemp("headers")) as instrument:
        yield instrument


def _assert_protected(answer) -> None:
    assert answer.headers["X-Content-Type-Options"] == "nosniff"
    assert answer.headers["X-Frame-Options"] == "DENY"
    assert answer.headers["Referrer-Policy"] == "no-referrer"
    policy = dict(d.strip().split(" ", 1) for d in answer.headers["Content-Security-Policy"].split(";"))
    assert policy["default-src"] == "'none'" and policy["frame-ancestors"] == "'none'"
    assert policy["script-src"] == policy["style-src"] == "'self'"  # nothing inline, nothing from outside
    assert "unsafe" not in answer.headers["Content-Security-Policy"]


@pytest.mark.parametrize(("what", "path", "status", "token"), [
    ("the page", "/", 200, "cookie"),
    ("the page without its token", "/", 401, None),
    ("the token link's redirect", "/?token=TOKEN", 302, None),
    ("the script", "/static/app.js", 200, None),
    ("the stylesheet", "/static/style.css", 200, None),
    ("a missing static file", "/static/nothing.js", 404, None),
    ("an API answer", "/api/status", 200, "bearer"),
    ("an API error", "/api/jobs/nope", 404, "bearer"),
    ("an API call without the token", "/api/status", 401, None),
    ("an unknown path", "/nowhere", 404, None),
])
def test_every_response_carries_the_security_headers(web, what, path, status, token):
    headers = {"Cookie": f"trimeter_token={web.token}"} if token == "cookie" else {}
    answer = web.call("GET", path.replace("TOKEN", web.token), token=web.token if token == "bearer" else None,
                      headers=headers, follow_redirects=False)
    assert answer.status == status, (what, answer.status, answer.body[:200])
    _assert_protected(answer)


def test_the_page_loads_nothing_inline():
    """What the policy relies on: the page's markup has no inline script, style or event handler."""
    html = (STATIC / "index.html").read_text()
    assert not re.search(r"<style|\sstyle\s*=|\son[a-z]+\s*=|javascript:", html, re.IGNORECASE)
    assert re.findall(r"<script[^>]*>", html) == ['<script src="/static/app.js">']
