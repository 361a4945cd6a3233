"""A host with no map files at all (HOME, XDG dirs and the working directory in a temporary place, the
package's maps directory empty, any map file read an error): the pipeline and the web page measure with
the table the instrument carries, record its identity, and re-fit a stored measurement with that same
table, from the host's cache or, once that is gone, from the instrument; nowhere is a clear error."""

from __future__ import annotations

import json

import pytest

from conftest import web_instrument
from hil_support import HIL_MAP, SAMPLE, THICKNESS_MM
from trimeter.formats.appearance import AppearanceMap


@pytest.fixture(scope="module")
def hil_map():
    return AppearanceMap.load(HIL_MAP)


@pytest.fixture(scope="module")
def table(hil_map):
    from trimeter.inversion.table_builder import build_from_map

    return build_from_map(hil_map)


@pytest.fixture(scope="module")
def web(tmp_path_factory, hil_map, table):
    from trimeter.formats import appearance, container

    root = tmp_path_factory.mktemp("nomaps")
    with pytest.MonkeyPatch.context() as patch:
        for name in ("HOME", "XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME", "XDG_STATE_HOME"):
            patch.setenv(name, str(root / name.lower()))
        patch.delenv("TRIMETER_CACHE_DIR", raising=False)
        (root / "cwd").mkdir()
        patch.chdir(root / "cwd")
        with web_instrument(root, map_table=table.to_bytes(), host_map=False, twin_map=hil_map) as instrument:
            def no_map_file(*args, **kwargs):
                raise AssertionError("a map file was read")

            # after the twin is up: it renders its samples with the map, the host must not need one
            (root / "no-maps").mkdir()
            patch.setattr(appearance, "MAPS_DIR", root / "no-maps")
            patch.setattr(AppearanceMap, "load", no_map_file)
            patch.setattr(container, "read_container", no_map_file)
            instrument.wait_state("asking_empty_holder")
            calibrated = instrument.calibrate()
            assert calibrated["outcome"] == "calibrated", calibrated
            instrument.twin.control.insert_sample(SAMPLE, THICKNESS_MM)
            yield instrument


def _record(web, measurement_id: str) -> dict:
    return json.loads((web.history.root / measurement_id / "measurement.json").read_text())


def _refit(web, measurement_id: str) -> dict:
    answer = web.call("POST", f"/api/measurements/{measurement_id}/refit", {})
    assert answer.status == 202, answer.body
    return web.wait_job(answer.json["job"]["id"])


def test_the_pipeline_measures_with_the_instruments_table(web, table):
    from trimeter.device.table_cache import instrument_table
    from trimeter.sequences.measure import measure, resolve_samples
    from trimeter.sequences.steps import Runner

    def pipeline(service):  # on the jobs' worker thread, which owns the device link
        device = service.connected_device()
        samples = resolve_samples([(THICKNESS_MM, None)], instrument_table=lambda: instrument_table(device)[0])
        runner = Runner(device, service.spectrometer, device_clock=service.device_clock)
        return measure(runner, service.calibration, samples, service.settings, label="pipeline")

    outcome = web.jobs.call(pipeline).result(timeout=120)
    meta = json.loads((outcome.path / "measurement.json").read_text())
    assert meta["map_checksums"] == [table.sha256] and meta["maps"] == [table.name]
    assert (web.root / "xdg_cache_home" / "trimeter" / "device-tables" / f"{table.sha256}.tlut").is_file()


def test_a_web_measurement_fits_with_the_instruments_table_and_refits_with_it(web, table):
    assert web.call("GET", "/api/maps").json["maps"] == []
    answer = web.call("POST", "/api/measure", {"label": "nomaps"})
    assert answer.status == 202, answer.body
    job = web.wait_job(answer.json["job"]["id"])
    assert job["outcome"] in ("measured", "flagged"), job
    measured = job["measurement"]
    meta = _record(web, measured)
    assert meta["map_checksums"] == [table.sha256] and meta["device_map_table"]["matches_fit_table"]
    assert web.call("GET", "/api/status").json["map_table"]["matches_fit_table"]

    refitted = _refit(web, measured)  # the table from the host's cache
    assert refitted["outcome"] == "refitted", refitted
    assert _record(web, refitted["measurement"])["map_checksums"] == [table.sha256]

    cached = web.root / "xdg_cache_home" / "trimeter" / "device-tables" / f"{table.sha256}.tlut"
    cached.unlink()
    again = _refit(web, measured)  # gone from the cache: read from the instrument, which still carries it
    assert again["outcome"] == "refitted", again
    assert _record(web, again["measurement"])["map_checksums"] == [table.sha256] and cached.is_file()

    record = web.history.root / measured / "measurement.json"
    other = dict(meta, map_checksums=["0" * 64])  # a table neither the cache nor the instrument holds
    record.write_text(json.dumps(other))
    refused = _refit(web, measured)
    assert refused["state"] == "failed" and "neither in this host's table cache, nor the instrument's active " \
                                            "table, nor a map here" in refused["message"], refused
    record.write_text(json.dumps(dict(meta, map_checksums=["../../etc/passwd"])))
    assert _refit(web, measured)["state"] == "failed"
