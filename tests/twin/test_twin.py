"""The whole twin: the real firmware sim behind the fault proxy, the spectrometer pty, the control socket.

Modbus is spoken with hand-built RTU frames (trimeter.twin._rtu; the twin is tested below the device client).
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from trimeter import registers
from trimeter.cli import main
from trimeter.errors import DeviceError, InputError
from trimeter.spectrometer import open_spectrometer
from trimeter.twin import FaultConfig, Twin, TwinClient
from trimeter.twin._rtu import RtuMaster


def Rtu(port, timeout=1.0):
    return RtuMaster(port, timeout_s=timeout)


def _find(name):
    """A register's address, from the generated register map."""
    for value in vars(registers).values():
        if isinstance(value, (list, tuple)):
            for r in value:
                if getattr(r, "name", None) == name:
                    return r.address
    raise KeyError(name)


# multiprocessing's resource tracker and forkserver are started once per process by the first 'spawn' or
# 'forkserver' child (e.g. a Dask LocalCluster's workers in an earlier test module) and by design live until
# this process exits: stdlib helpers, not leaks.
_STDLIB_HELPERS = ("from multiprocessing.resource_tracker import main", "from multiprocessing.forkserver import main")


def _children():
    """Our live child processes (zombies and the stdlib's multiprocessing helpers excluded), as
    {pid: command line} so a failure names the leftover."""
    me, kids = os.getpid(), {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmdline = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        if int(fields[1]) == me and fields[0] != "Z" and not any(h in cmdline for h in _STDLIB_HELPERS):
            kids[int(pid)] = cmdline
    return kids


def _open_fds() -> dict[str, str]:
    """This process's open file descriptors and what each points to (event fds too: a thread an earlier test
    left running, e.g. a notebook kernel's heartbeat, would swap them meanwhile, and that is a leak to fix)."""
    fds = {}
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listing's own descriptor, closed by now
            fds[fd] = os.readlink(f"/proc/self/fd/{fd}")
    return fds


def test_start_stop_leaves_no_process_thread_fd_or_link(ideal_map, tmp_path):
    gc.collect()  # an earlier test's garbage closes its descriptors now, not in the middle of this count
    fds_before, threads_before = _open_fds(), threading.active_count()
    starts, stops = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        twin = Twin(time_scale=20, appearance_map=ideal_map, state_dir=tmp_path / "twin").start()
        starts.append(time.perf_counter() - t0)
        pid = twin._process.pid
        assert os.path.realpath(tmp_path / "twin" / "modbus") == twin.modbus_port
        t0 = time.perf_counter()
        twin.close()
        stops.append(time.perf_counter() - t0)
        assert twin._process.poll() == 0  # exited cleanly on SIGTERM, and reaped
        assert not os.path.exists(f"/proc/{pid}")
    assert _children() == {}
    assert threading.active_count() == threads_before
    gc.collect()
    fds_after = _open_fds()
    assert fds_after == fds_before, (f"opened: {dict(fds_after.items() - fds_before.items())}, "
                                     f"closed: {dict(fds_before.items() - fds_after.items())}, "
                                     f"threads: {[t.name for t in threading.enumerate()]}")
    assert not (tmp_path / "twin" / "modbus").exists() and not (tmp_path / "twin" / "spectrometer").exists()
    assert (tmp_path / "twin" / "storage.bin").exists()  # kept: config persists across restarts
    print(f"twin start {np.median(starts) * 1e3:.0f} ms, stop {np.median(stops) * 1e3:.0f} ms (median of 3)")


def test_a_bad_sample_fails_before_anything_is_launched(ideal_map):
    with pytest.raises(InputError, match="sample must be one of"):
        Twin(sample="unobtainium", appearance_map=ideal_map).start()
    assert _children() == {}


def test_modbus_through_the_proxy_and_the_spectrometer_follow_the_plant(ideal_map):
    with Twin(time_scale=20, appearance_map=ideal_map, seed=3) as twin:
        rtu = Rtu(twin.modbus_port)
        try:
            ident = rtu.read_input(_find("vendor_id"), 5)
            assert ident == [registers.VENDOR_ID, registers.MODEL_ID, *registers.FIRMWARE_VERSION]
            with open_spectrometer(twin.spectrometer_url) as spec:
                spec.integration_time_us = 200_000
                dark = spec.intensities()
                # open both panel shutters and light both panels (coils 0,1 and 3,4)
                assert rtu.write_coils(_find("shutter_panel_left_open"), [True, True, False, True, True, False])
                deadline = time.monotonic() + 5
                shutters = lambda: twin.control.state()["plant"]["shutters"]  # noqa: E731
                while not all(shutters()[k]["open"] for k in ("panel_left", "panel_right")):
                    assert time.monotonic() < deadline, "shutters never opened"
                    time.sleep(0.02)
                lit = spec.intensities()
                state = twin.control.state()
                assert state["plant"]["slot"] is None  # unhomed carriage between slots: the black slider body
                expected = twin.optics.panels.spectrum() * twin.optics.rho_black * 0.2
                band = expected > 1000
                np.testing.assert_allclose((lit - dark)[band] / expected[band], 1.0, atol=0.1)
                assert state["spectrometer"]["acquisitions"] == 2
                twin.control.set_fault(lamp_failure="panels")
                failed = spec.intensities()
                assert np.abs(failed - dark)[band].mean() < 10  # the lamp failure leaves only dark counts
        finally:
            rtu.close()


def test_reset_at_reboots_the_firmware_at_that_request(ideal_map):
    with Twin(time_scale=20, appearance_map=ideal_map, faults=FaultConfig(reset_at=4)) as twin:
        rtu = Rtu(twin.modbus_port)
        try:
            frames = [rtu.read_input(_find("modbus_frames_ok"), 1)[0] for _ in range(6)]
        finally:
            rtu.close()
        # frames_ok counts up, then restarts from zero: RAM state was lost at the 4th request
        assert frames[:3] == sorted(frames[:3]) and frames[3] < frames[2]
        assert twin.control.state()["counters"]["requests"] == 6


def test_corrupted_link_fails_some_transactions_and_counts_the_bytes(ideal_map):
    with Twin(time_scale=20, appearance_map=ideal_map, faults=FaultConfig(corrupt=0.05), seed=7) as twin:
        rtu = Rtu(twin.modbus_port, timeout=0.15)
        try:
            ok = sum(rtu.read_input(_find("vendor_id"), 1) == [registers.VENDOR_ID] for _ in range(40))
        finally:
            rtu.close()
        state = twin.control.state()
        counters = state["counters"]
        assert state["fault_seed"] == 7
        # 8-byte request + 7-byte reply at 5 % per byte: ~46 % of transactions survive
        assert 5 < ok < 35 and counters["bytes_corrupted"] > 0


def test_control_socket_mirrors_the_python_api(ideal_map):
    with Twin(sample="cyan-ink", time_scale=20, appearance_map=ideal_map) as twin:
        with TwinClient(twin.control_path) as client:
            assert client.ports()["modbus_port"] == twin.modbus_port
            truth = client.truth()
            np.testing.assert_allclose(truth["alpha"], twin.control.truth()["alpha"])
            assert truth["name"] == "cyan-ink" and len(truth["wavelengths_nm"]) == 1024
            client.insert_sample("milk", 0.4)
            assert twin.control.state()["sample"] == "milk"
            t0 = client.sim_time()
            time.sleep(0.1)
            assert client.sim_time() > t0 + 0.5  # 20x: 0.1 s wall is ~2 s simulated
            assert client.set_fault(drop=0.5)["drop"] == 0.5 and twin.faults.drop == 0.5
            with pytest.raises(DeviceError, match="drop must be a probability"):
                client.set_fault(drop=7)
            with pytest.raises(DeviceError, match="unknown fault"):
                client.set_fault(gremlins=True)
            assert twin.faults.drop == 0.5  # refused requests change nothing
            client.set_fault(stuck_slider=True)
            assert twin.control.state()["plant"]["stuck_slider"] is True  # passed on to the firmware's plant
            client.press_button()
            client.remove_sample()
            assert client.truth() is None
            raw = client._sock
            raw.sendall(b"{not json\n")
            assert json.loads(client._file.readline())["ok"] is False
            raw.sendall(b'{"cmd":"insert_sample","name":"milk","thickness_mm":0.4,"extra":1}\n')
            assert "extra" in json.loads(client._file.readline())["error"]
            raw.sendall(b"x" * 200_000 + b"\n")
            assert "longer than" in json.loads(client._file.readline())["error"]
            assert client.state()["sample"] is None


def test_trimeter_sim_prints_ports_and_stops_cleanly_on_sigint(ideal_map, tmp_path, capsys):
    proc = subprocess.Popen([sys.executable, "-m", "trimeter", "sim", "--json", "--time-scale", "20",
                             "--sample", "magenta-ink", "--map", str(ideal_map.path), "--state-dir", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ports = json.loads(proc.stdout.readline())
        with TwinClient(ports["control_path"]) as client:
            assert client.state()["sample"] == "magenta-ink"
        with open_spectrometer(ports["spectrometer_url"]) as spec:
            assert spec.description.pixels == 1024
        ctl = ["sim", "--state-dir", str(tmp_path), "--ctl"]  # in-process: finds the twin via ports.json
        assert main(ctl + ["insert_sample", "name=milk", "thickness_mm=0.4"]) == 0
        capsys.readouterr()
        assert main(ctl + ["truth"]) == 0
        assert json.loads(capsys.readouterr().out)["truth"]["name"] == "milk"
        assert main(ctl + ["insert_sample", "name=unobtainium"]) == 2
        assert "sample must be one of" in capsys.readouterr().err
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not os.path.exists(ports["control_path"]) and not (tmp_path / "ports.json").exists()
    fw_pids = [p for p in filter(str.isdigit, os.listdir("/proc"))
               if str(tmp_path) in open(f"/proc/{p}/cmdline", "rb").read().decode(errors="replace")]
    assert fw_pids == []  # the firmware went with it


def test_impossible_twin_settings_are_refused_up_front():
    for bad in (0, -1, float("nan"), "fast"):
        with pytest.raises(InputError, match="time_scale"):
            Twin(time_scale=bad)
    with pytest.raises(InputError, match="faults must be a FaultConfig"):
        Twin(faults={"drop": 0.1})
    for bad in (-1, 1.5, "7", True):
        with pytest.raises(InputError, match="seed must be a non-negative integer"):
            Twin(seed=bad)
    assert Twin(seed=5).fault_seed == 5 and Twin().fault_seed != Twin().fault_seed  # none given: a random one


def test_a_crashed_firmware_is_reported_and_cleaned_up(ideal_map, tmp_path):
    twin = Twin(time_scale=20, appearance_map=ideal_map, state_dir=tmp_path).start()
    try:
        with open_spectrometer(twin.spectrometer_url) as spec:
            twin._process.kill()  # a crash, not a clean exit
            twin._process.wait()
            assert not twin.running
            with pytest.raises(DeviceError, match="plant"):
                spec.intensities()  # the spectrometer says why instead of hanging
    finally:
        twin.close()
    assert _children() == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["firmware.log", "storage.bin"]
