"""The several-instruments API is described in the OpenAPI document the app serves, with the history's filter."""

from trimeter.web.openapi import openapi


def test_the_instruments_routes_and_the_instrument_filter_are_described():
    spec = openapi()
    assert {"/api/instruments", "/instruments/{name}/api/..."} <= set(spec["paths"])
    search = spec["paths"]["/api/measurements"]["get"]["parameters"]
    assert "instrument" in [p["name"] for p in search]
