"""The API's OpenAPI 3.1 description, served at /api/openapi.json and rendered into docs/reference/http-api.md
(tools/gen_docs.py)."""

from __future__ import annotations

from collections.abc import Sequence

from trimeter.inversion.methods import METHODS
from trimeter.web import auth, instruments_routes, library_routes


def openapi() -> dict:
    """The API's OpenAPI 3.1 description (served at /api/openapi.json)."""
    def op(summary: str, *, body: dict | None = None, params: Sequence[tuple[str, str, str, str]] = (),
           responses: dict | None = None) -> dict:
        out = {"summary": summary, "responses": {"200": {"description": "OK"}, "401": {"description": "no or wrong "
                                                                                                         "token"},
                                                 **(responses or {})}}
        if body:
            out["requestBody"] = {"content": {"application/json": {"schema": {"type": "object", "properties": body,
                                                                              "additionalProperties": False}}}}
        if params:
            out["parameters"] = [{"name": n, "in": where, "required": where == "path", "schema": {"type": t},
                                  "description": d} for n, where, t, d in params]
        return out

    job = {"202": {"description": "accepted: {job}, Location /api/jobs/{id}"},
           "409": {"description": "a job is queued or running: {error: {job}}"}}
    mid = ("id", "path", "string", "a results directory's name")
    search = [("label", "query", "string", "part of the label"), ("since", "query", "string", "YYYY-MM-DD or ISO time"),
              ("until", "query", "string", "YYYY-MM-DD (inclusive) or ISO time"),
              ("instrument", "query", "string", "only those of the instrument of this name"),
              ("flagged", "query", "boolean", "only measurements with (true) / without (false) flagged bins"),
              ("flag", "query", "string", "only those with this FitFlag (e.g. UNDERDETERMINED)"),
              ("limit", "query", "integer", "page size, 1..500 (default 50)"), ("offset", "query", "integer", ""),
              ("format", "query", "string", "csv: every match as CSV")]
    number_ = {"type": "number"}
    return {
        "openapi": "3.1.0",
        "info": {"title": "trimeter", "version": "1",
                 "description": "The instrument on the LAN. Errors: {error: {status, message}}. Access: cookie "
                                "trimeter_token or Authorization: Bearer."},
        "components": {"securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"},
                                           "cookie": {"type": "apiKey", "in": "cookie", "name": auth.COOKIE}}},
        "security": [{"bearer": []}, {"cookie": []}],
        "paths": {
            "/api/status": {"get": op("state, current job, step and progress, lamp drift, calibration age, device "
                                      "identity, active map table")},
            "/api/jobs/{job_id}": {"get": op("one job (the current or one of the last 20)",
                                             params=[("job_id", "path", "string", "")])},
            "/api/calibrate": {"post": op("ask for an empty holder; with holder_empty: true (while asked) check "
                                          "the holder, warm up and calibrate", body={"holder_empty":
                                                                                    {"type": "boolean"}},
                                          responses=job)},
            "/api/measure": {"post": op("measure the sample(s) in the holder", body={
                "label": {"type": "string"}, "thickness_mm": number_, "second_thickness_mm": number_},
                responses=job)},
            "/api/next-sample": {"post": op("the next sample is in (while asked for, with two thicknesses)",
                                            responses={"409": {"description": "not asked for"}})},
            "/api/maps": {"get": op("maps a refit may name, the methods, and the instrument tables in this host's "
                                    "cache (name, parent map's SHA-256, n, ℓ, geometry, size; a note for a "
                                    "corrupt file)")},
            "/api/measurements": {"get": op("search the history, newest first", params=search)},
            "/api/measurements/{id}": {"get": op("one measurement: index row, measurement.json, parameters, "
                                                 "flags in words, files", params=[mid])},
            "/api/measurements/{id}/files/{name}": {"get": op("one file of it", params=[
                mid, ("name", "path", "string", "a file name from `files`")])},
            "/api/measurements/{id}/zip": {"get": op("its whole directory as a zip", params=[mid])},
            "/api/measurements/{id}/refit": {"post": op("fit its capture again (another map or method) into a new "
                                                        "record", params=[mid], responses=job, body={
                                                            "maps": {"type": "array", "items": {"type": "string"}},
                                                            "method": {"enum": list(METHODS)}})},
            "/api/config": {"get": op("host and device configuration"),
                            "put": op("change host settings and/or device items (all checked first; nothing "
                                      "changes on an error); save: store the device's in its flash", body={
                                          "host": {"type": "object"}, "device": {"type": "object"},
                                          "save": {"type": "boolean"}})},
            "/api/events": {"get": op("websocket: the service's events, progress and jobs as JSON, live")},
            "/api/openapi.json": {"get": op("this description")},
            **library_routes.OPENAPI_PATHS,
            **instruments_routes.OPENAPI_PATHS,
        },
    }
