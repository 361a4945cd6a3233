"""Three twins on one simulated RS-485 bus, served by one host and one page (`serve` with [[instruments]]):
each calibrated and measured through its own API under /instruments/{name}/, the history tagged by instrument,
and a link fault on one instrument's branch of the bus that the other two do not feel. Prints the cycle time of
a measurement on each of three instruments measuring at once against one measuring alone (the bus throughput)."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from hil_support import HIL_MAP, SAMPLE, THICKNESS_MM, TIME_SCALE
from lab_support import NAMES, served_lab
from trimeter.bench._rig import host_dirs
from trimeter.results.reader import read_parameters
from trimeter.sequences.instruments import Lab
from trimeter.sequences.settings import HostSettings

FAULTY = "middle"
# Link faults on the middle instrument's branch only: its requests are retried on the shared bus, and a drained
# late reply or a garbled one must never reach another instrument's request.
FAULTS = {"corrupt": 0.002, "drop": 0.03}


def _link(results_dir) -> dict:
    """One measurement's Modbus requests (its own, from its timing) and the bus wait its instrument has had so far."""
    record = json.loads((results_dir / "measurement.json").read_text())
    timing = record["timing"]
    return {"wall_s": round(timing["wall_s"], 2), "requests": timing["requests"],
            "request_wall_s": round(timing["request_wall_s"], 2), "retries": timing["request_retries"],
            "bus_wait_s_so_far": round(record["link"]["bus_wait_s"], 2)}


def _errors(results_dir, truth) -> dict:
    """p95 |error| of σt (relative) and α over 420-720 nm, and the fraction of non-finite α bins."""
    p = read_parameters(results_dir)[0]
    wl = p.wavelengths_nm
    band = (wl >= 420) & (wl <= 720)
    alpha = np.interp(wl, truth["wavelengths_nm"], truth["alpha"])[band]
    sigma_t = np.interp(wl, truth["wavelengths_nm"], truth["sigma_t"])[band]
    return {"nan": float(np.mean(~np.isfinite(p.alpha[band]))),
            "sigma_t": float(np.nanpercentile(np.abs(p.sigma_t[band] / sigma_t - 1), 95)),
            "alpha": float(np.nanpercentile(np.abs(p.alpha[band] - alpha), 95))}


@pytest.fixture
def lab_page(request, tmp_path):
    if request.config.getoption("--port"):
        pytest.skip("needs the twin (three instruments on one simulated bus)")
    with served_lab(tmp_path, {FAULTY: FAULTS}) as served:
        yield served


def test_three_instruments_on_one_bus_calibrate_and_measure_from_one_page_and_a_fault_stays_on_its_own(lab_page):
    page, twins, results = lab_page
    status, listing = page.call("GET", "/api/instruments")
    assert status == 200
    assert [(i["name"], i["address"]) for i in listing["instruments"]] == [(n, twins[n].address) for n in NAMES]
    assert len({i["port"] for i in listing["instruments"]}) == 1  # one bus
    for name in NAMES:
        page.wait_state(name, "asking_empty_holder")  # no calibration yet: each asks for an empty holder

    with ThreadPoolExecutor(3) as pool:  # calibrated side by side, on one bus
        calibrations = dict(zip(NAMES, pool.map(page.calibrate, NAMES), strict=True))
    for name, job in calibrations.items():
        assert job["state"] == "done" and job["outcome"] == "calibrated", (name, job)

    for twin in twins.values():
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
    alone, alone_s = page.measure("left")  # the baseline: one instrument measuring while the others idle
    assert alone["state"] == "done", alone
    with ThreadPoolExecutor(3) as pool:
        together = dict(zip(NAMES, pool.map(page.measure, NAMES), strict=True))
    cycle = {name: round(seconds, 2) for name, (_, seconds) in together.items()}
    links = {name: _link(results / job["measurement"]) for name, (job, _) in together.items() if job["measurement"]}
    print(f"\nbus throughput (twin, time scale {TIME_SCALE:g}): one measurement alone {alone_s:.2f} s "
          f"(link {_link(results / alone['measurement'])}); three at once on one bus {cycle} s each, "
          f"{max(cycle.values()) / alone_s:.2f}x the one alone; links {links}; faults on {FAULTY}: {FAULTS}")

    listing = page.call("GET", "/api/instruments")[1]["instruments"]
    for name, (job, _) in together.items():
        assert job["state"] == "done" and job["measurement"], (name, job["outcome"], job["message"])
        errors = _errors(results / job["measurement"], twins[name].control.truth())
        assert errors["nan"] == 0 and errors["sigma_t"] < 0.02 and errors["alpha"] < 0.05, (name, errors)
        shown = next(i for i in listing if i["name"] == name)
        assert shown["calibration"]["age_s"] is not None and shown["last_measurement"] == job["measurement"]
        assert job["id"] in [j["id"] for j in shown["recent_jobs"]]

    counters = twins[FAULTY].control.state()["counters"]
    assert counters["replies_dropped"] + counters["bytes_corrupted"] > 5, counters  # the fault really happened
    for name in NAMES:  # the others' branches carried no fault at all
        if name != FAULTY:
            clean = twins[name].control.state()["counters"]
            assert clean["replies_dropped"] == clean["bytes_corrupted"] == 0, (name, clean)

    # the history: every measurement tagged with the instrument that made it, and searchable by it
    history = page.call("GET", "/api/measurements?limit=50")[1]
    tags = {row["id"]: row["instrument"] for row in history["measurements"]}
    for name, (job, _) in together.items():
        assert tags[job["measurement"]] == name
    only = page.call("GET", f"/api/measurements?instrument={FAULTY}")[1]["measurements"]
    assert {row["instrument"] for row in only} == {FAULTY} and len(only) == 1


def test_two_twins_answering_at_one_address_are_one_clear_error(request, tmp_path):
    if request.config.getoption("--port"):
        pytest.skip("needs the twin")
    from trimeter.errors import DeviceError
    from trimeter.twin.bus import TwinBus

    with host_dirs(tmp_path), TwinBus(addresses=[1, 2, 2], sample=None, time_scale=TIME_SCALE,
                                      appearance_map=str(HIL_MAP), state_dir=tmp_path / "bus") as bus:
        def lab_of(addresses: list[int]) -> Lab:
            settings = HostSettings()
            settings.set("instruments", [{"name": f"i{a}", "port": bus.modbus_port, "address": a,
                                          "spectrometer": t.spectrometer_url}
                                         for a, t in zip(addresses, bus.twins, strict=False)])
            return Lab(settings)

        lab = lab_of([1, 2])
        try:
            with pytest.raises(DeviceError, match=r"^instrument 'i2': address collision on the bus .*: more than one "
                                                  r"device answers at Modbus address 2"):
                lab.check_buses()
        finally:
            lab.close()
        lab = lab_of([1, 3])
        try:
            with pytest.raises(DeviceError, match=r"^instrument 'i3': no instrument answers at Modbus address 3"):
                lab.check_buses()
        finally:
            lab.close()


def test_serve_refuses_a_bus_with_two_instruments_at_one_address_in_one_line(request, tmp_path, capsys):
    if request.config.getoption("--port"):
        pytest.skip("needs the twin")
    from trimeter.cli import main
    from trimeter.twin.bus import TwinBus

    with host_dirs(tmp_path), TwinBus(addresses=[1, 1], sample=None, time_scale=TIME_SCALE,
                                      appearance_map=str(HIL_MAP), state_dir=tmp_path / "bus") as bus:
        settings = HostSettings()
        settings.set("instruments", [{"name": "a", "port": bus.modbus_port, "address": 1},
                                     {"name": "b", "port": bus.modbus_port, "address": 2}])
        settings.save()
        assert main(["serve"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("trimeter: error: instrument 'a': address collision on the bus"), err


def test_calibrate_and_measure_reach_one_instrument_of_the_bus_by_its_address(request, tmp_path, capsys):
    if request.config.getoption("--port"):
        pytest.skip("needs the twin")
    from trimeter.cli import main
    from trimeter.twin.bus import TwinBus

    with host_dirs(tmp_path), TwinBus(2, sample=None, thickness_mm=THICKNESS_MM, time_scale=TIME_SCALE,
                                      appearance_map=str(HIL_MAP), state_dir=tmp_path / "bus", seed=5) as bus:
        twin = bus.twin(2)
        where = ["--port", str(bus.modbus_port), "--address", "2", "--spectrometer", twin.spectrometer_url]
        assert main(["config", "set", "--host", "map", str(HIL_MAP)]) == 0
        assert main(["config", "set", "--host", "results_dir", str(tmp_path / "results")]) == 0
        assert main(["calibrate", *where]) == 0
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        assert main(["measure", *where, "--thickness", str(THICKNESS_MM), "--map", str(HIL_MAP)]) == 0
        other = bus.twin(1).control.state()
        assert other["spectrometer"]["acquisitions"] == 0  # the instrument at address 1 was never asked to measure
        (result,) = (tmp_path / "results").iterdir()
        errors = _errors(result, twin.control.truth())
        assert errors["nan"] == 0 and errors["sigma_t"] < 0.02, errors
