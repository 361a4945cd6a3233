"""The instrument carries its own inverse: on a twin whose storage holds a device table, `trimeter
measure` fits with that table by default (read from the active slot once, then from the cache by its
SHA-256) on a host with no map files at all; a declared thickness the table is not for, or no table,
is one clear error; `trimeter fit --on-device` agrees with `trimeter fit --table` on the same table."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from hil_support import SAMPLE, THICKNESS_MM, TIME_SCALE, twin_truth
from trimeter.cli import main
from trimeter.formats.appearance import AppearanceMap


@pytest.fixture
def no_maps_host(tmp_path, monkeypatch, hil_map):
    """Host config, data and cache under tmp_path, the working directory elsewhere; returns a function
    that takes every map file out of reach (after the twin, which renders with the map, is up)."""
    for name in ("DATA", "CONFIG", "CACHE"):
        monkeypatch.setenv(f"TRIMETER_{name}_DIR", str(tmp_path / name.lower()))
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")

    def out_of_reach() -> None:
        from trimeter.formats import container
        from trimeter.sequences import measure

        def no_map_file(*args, **kwargs):
            raise AssertionError("a map file was read")

        monkeypatch.setattr(AppearanceMap, "load", no_map_file)
        monkeypatch.setattr(container, "read_container", no_map_file)
        monkeypatch.setattr(measure, "shipped_maps", lambda: [])

    return out_of_reach


@pytest.fixture(scope="module")
def hil_map():
    from hil_support import HIL_MAP, build_hil_map

    return AppearanceMap.load(HIL_MAP) if HIL_MAP.exists() else build_hil_map(HIL_MAP)


@pytest.fixture
def table_file(tmp_path, hil_map):
    from trimeter.inversion.table_builder import build_from_map

    return build_from_map(hil_map).save(tmp_path / "hil.tlut")


def _twin(request, tmp_path, hil_map, **options):
    if request.config.getoption("--port"):
        pytest.skip("needs the twin (its storage seeded with a table)")
    from trimeter.twin import Twin

    return Twin(sample=None, thickness_mm=THICKNESS_MM, time_scale=TIME_SCALE, appearance_map=hil_map,
                state_dir=tmp_path / "twin", seed=3, **options)


def test_measure_fits_with_the_instruments_table_on_a_host_without_maps(request, tmp_path, hil_map, table_file,
                                                                          no_maps_host, capsys):
    from trimeter.formats.device_table import DeviceTable

    table = DeviceTable.load(table_file)
    with _twin(request, tmp_path, hil_map, map_table=table_file) as twin:
        no_maps_host()
        port = ["--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url]
        assert main(["config", "set", "--host", "warmup_threshold", "0.003"]) == 0
        assert main(["calibrate", *port]) == 0
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        capsys.readouterr()
        assert main(["measure", *port, "--thickness", "0.8"]) == 2  # not what the instrument's table is for
        err = capsys.readouterr().err
        assert f"map table {table.name} is for ℓ = 0.4 mm, not the declared 0.8 mm" in err and "--map" in err
        runs = []
        for label in ("first", "second"):
            assert main(["measure", *port, "--label", label]) == 0
            runs.append(capsys.readouterr().out)
        truth = twin_truth(twin, request)
    assert f"the instrument's map table {table.name}" in runs[0] and f"sha256 {table.sha256[:12]}" in runs[0]
    assert all("from the cache" in run for run in runs)  # read once, by the refused attempt
    assert (tmp_path / "cache" / "device-tables" / f"{table.sha256}.tlut").read_bytes() == table.to_bytes()
    results = Path([line.split(": ", 1)[1] for line in runs[1].splitlines() if line.startswith("results: ")][0])
    meta = json.loads((results / "measurement.json").read_text())
    assert meta["map_checksums"] == [table.sha256] and meta["device_map_table"]["matches_fit_table"]
    fitted = np.genfromtxt(results / "parameters.csv", delimiter=",", names=True)
    want = np.interp(fitted["wavelength_nm"], truth["wavelengths_nm"], truth["sigma_t"])
    band = (fitted["wavelength_nm"] > 420) & (fitted["wavelength_nm"] < 720)
    assert np.nanpercentile(np.abs(fitted["sigma_t"] / want - 1)[band], 95) < 0.02  # as with --map (test_hil)


def test_a_corrupt_cache_entry_is_read_again_and_no_table_is_a_clear_error(request, tmp_path, hil_map, table_file,
                                                                           no_maps_host, capsys):
    from trimeter.device import Device
    from trimeter.device.table_cache import cache_dir, instrument_table
    from trimeter.formats.device_table import DeviceTable

    table = DeviceTable.load(table_file)
    with _twin(request, tmp_path, hil_map, map_table=table_file) as twin, Device.open(twin.modbus_port) as device:
        first, slot, cached = instrument_table(device)
        assert (first.sha256, slot, cached) == (table.sha256, "A", False)
        entry = cache_dir() / f"{table.sha256}.tlut"
        damaged = bytearray(entry.read_bytes())
        damaged[1000] ^= 0xFF
        entry.write_bytes(bytes(damaged))
        again, _, cached = instrument_table(device)
        assert again.sha256 == table.sha256 and not cached and entry.read_bytes() == table.to_bytes()
    (tmp_path / "twin").rename(tmp_path / "twin-with-table")
    with _twin(request, tmp_path, hil_map) as twin:
        capsys.readouterr()
        assert main(["measure", "--port", twin.modbus_port, "--spectrometer", twin.spectrometer_url]) == 2
        assert "the device has no active map table: flash one" in capsys.readouterr().err
        measured = tmp_path / "one.csv"
        measured.write_text("wavelength_nm,I_b,I_w,I_c\n500,0.2,0.5,0.1\n")
        assert main(["fit", "--on-device", "--port", twin.modbus_port, "--input", str(measured)]) == 2
        assert "the device has no active map table" in capsys.readouterr().err


def _columns(path: Path) -> dict:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def test_fit_on_device_agrees_with_fit_from_the_same_table(request, tmp_path, hil_map, table_file, no_maps_host,
                                                          capsys):
    from trimeter.formats.device_table import DeviceTable

    table = DeviceTable.load(table_file)
    rng = np.random.default_rng(5)
    n = 48
    alpha, sigma_t, g = rng.uniform(0.3, 0.98, n), np.exp(rng.uniform(np.log(1.0), np.log(20.0), n)), \
        rng.uniform(0.0, 0.8, n)
    rho_b, rho_w = np.full(n, 0.04), np.full(n, 0.95)
    I_b, I_w, I_c = hil_map.query(alpha, sigma_t, g, rho_b, rho_w)
    measured = tmp_path / "meas.csv"
    with open(measured, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["wavelength_nm", "I_b", "I_w", "I_c", "rho_b", "rho_w"])
        writer.writerows(zip(np.linspace(400, 700, n), I_b, I_w, I_c, rho_b, rho_w, strict=True))
    host, device = tmp_path / "host.csv", tmp_path / "device.csv"
    with _twin(request, tmp_path, hil_map, map_table=table_file) as twin:
        no_maps_host()
        assert main(["fit", "--table", str(table_file), "--input", str(measured), "-o", str(host)]) == 0
        capsys.readouterr()
        assert main(["fit", "--on-device", "--port", twin.modbus_port, "--input", str(measured), "-o",
                     str(device)]) == 0
        err = capsys.readouterr().err
        assert main(["fit", "--on-device", "--port", twin.modbus_port, "--input", str(measured), "--json"]) == 0
        doc = json.loads(capsys.readouterr().out)
    assert f"fitted on the device with its table {table.name}, slot A, sha256 {table.sha256[:12]}" in err
    assert doc["table"]["sha256"] == table.sha256 and doc["table"]["source"] == "device"
    on_host, on_device = _columns(host), _columns(device)
    assert list(on_host) == list(on_device)  # the same columns, in the same order
    ok = np.isfinite(on_host["alpha"])
    np.testing.assert_array_equal(np.isfinite(on_device["alpha"]), ok)
    assert ok.all()  # every material inside the map is fitted, on both
    np.testing.assert_allclose(on_device["sigma_t_beer"], on_host["sigma_t_beer"], rtol=1e-9)
    assert "stds computed here from the same table" in err and "computed on the host" in doc["table"]["stds"]
    # the device returns no stds: they are the host's, from the same table at the device's parameters
    for column in ("alpha_std", "sigma_t_std", "g_std"):
        assert np.isfinite(on_device[column]).all(), column
        np.testing.assert_allclose(on_device[column], on_host[column], rtol=0.05)
    # one fit on both, the device's in single precision: the tolerances on every bin
    assert np.max(np.abs(on_device["alpha"] - on_host["alpha"])) <= 1e-3
    assert np.max(np.abs(on_device["sigma_t"] / on_host["sigma_t"] - 1)) <= 1e-3
    assert np.max(np.abs(on_device["g"] - on_host["g"])) <= 2e-3
