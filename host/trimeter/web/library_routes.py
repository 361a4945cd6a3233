"""The material library on the page: GET /api/library (the materials) and GET /api/library/{name} (one
material: its combined spectra with std and spread, its members, and each member's own estimate where
its results directory is here, for the overlay). Read-only: materials are made with `trimeter library`.

Registered by `register(app)` (one line in trimeter.web.app.create_app); the app's middlewares (access,
errors as the JSON envelope, security headers) apply as to every other route.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
from aiohttp import web

from trimeter.errors import InputError

LIBRARY_DB = web.AppKey("library_db", Path)
SPECTRA = ("wavelength_nm", "alpha", "alpha_std", "alpha_spread", "sigma_t", "sigma_t_std", "sigma_t_spread", "g",
           "g_std", "g_spread", "members", "flags")


def _numbers(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, float)]


def _summaries(db: Path) -> dict:
    from trimeter.library.store import Library

    if not db.exists():  # no library yet: an empty list, and no file made by a read
        return {"materials": [], "library": str(db)}
    with Library(db) as lib:
        return {"materials": lib.summaries(), "library": str(db)}


def _material(db: Path, name: str) -> dict:
    from trimeter.library.store import Library, check_name
    from trimeter.results.reader import load

    check_name(name)
    if not db.exists():
        raise web.HTTPNotFound(reason=f"no material {name!r}: the library is empty")
    with Library(db) as lib:
        if name not in lib.names():
            raise web.HTTPNotFound(reason=f"no material {name!r} in the library")
        m = lib.get(name)
    doc = m.document
    members = []
    for record in doc.members:
        entry = {k: record[k] for k in ("measurement", "thicknesses_mm", "method", "maps", "written_utc", "label")}
        entry["here"] = False
        if m.origin == "local":
            try:
                own = load(record["path"])
                entry["here"] = True
                entry["parameters"] = {"wavelength_nm": _numbers(own.wavelength_nm),
                                       **{k: _numbers(getattr(own, k)) for k in ("alpha", "sigma_t", "g")}}
            except InputError:
                pass   # gone since it was added: shown as missing, the material stays
        members.append(entry)
    return {"name": doc.name, "origin": m.origin, "notes": doc.notes, "tags": doc.tags,
            "created_utc": doc.created_utc, "combination": doc.combination,
            "spectra": {k: _numbers(doc.columns[k]) for k in SPECTRA}, "members": members,
            "member_problems": m.missing_members()}


async def library_route(request: web.Request) -> web.StreamResponse:
    db = request.app[LIBRARY_DB]
    return web.json_response(await asyncio.get_running_loop().run_in_executor(None, _summaries, db))


async def material_route(request: web.Request) -> web.StreamResponse:
    db, name = request.app[LIBRARY_DB], request.match_info["name"]
    return web.json_response(await asyncio.get_running_loop().run_in_executor(None, _material, db, name))


def register(app: web.Application, db_path: Path | None = None) -> None:
    """Add the library's routes to `app`, reading the library at `db_path` (default: beside the history)."""
    from trimeter.library.store import default_path

    app[LIBRARY_DB] = Path(db_path) if db_path is not None else default_path()
    app.router.add_get("/api/library", library_route)
    app.router.add_get("/api/library/{name}", material_route)


_RESPONSES = {"200": {"description": "OK"}, "401": {"description": "no or wrong token"}}
OPENAPI_PATHS = {
    "/api/library": {"get": {"summary": "the material library: every material's name, members, tags",
                             "responses": _RESPONSES}},
    "/api/library/{name}": {"get": {
        "summary": "one material: combined spectra (std, spread between repeats), members and their own estimates",
        "parameters": [{"name": "name", "in": "path", "required": True, "schema": {"type": "string"},
                        "description": "the material's name"}],
        "responses": {**_RESPONSES, "404": {"description": "no such material"}}}},
}
