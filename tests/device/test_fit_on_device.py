"""Fitting on the device (Device.fit) against the firmware sim over its pty: the plumbing end to end.

Two builds of the real firmware besides the shipped one: one without the inverse core (FIT_CORE_SRC empty:
every run is refused as unavailable, and the client says so) and one linked with the stand-in core of
firmware/tests/standin/fit_core_standin.c, a transparent function whose outputs are known exactly in
float32 — so the bins' layout, the runs of at most fit_capacity bins, the flags, and every refusal
(no table, a thickness the table is not for) are checked on the wire, without the real core. The shipped
build, with the real core, is tests/device/test_table_fit_on_device.py's."""

from __future__ import annotations

import os
import select
import signal
import struct
import subprocess
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from trimeter import registers as regs
from trimeter.device.client import Device
from trimeter.errors import DeviceError, InputError

ROOT = Path(__file__).resolve().parents[2]
READY_TIMEOUT_S = 10.0


def _tiny_table(thickness_mm: float = 0.4) -> bytes:
    """The smallest map table (format 1, every grid count 2) the firmware accepts into a slot: its header
    (host/trimeter/inversion/table.py's layout) over a zero payload; the stand-in core reads no payload."""
    sizes = 4 * (2 + 2 + 2 + 6) + 6 * 8 + 24 * 2 + 4 * 8
    total = 128 + sizes + 4
    header = struct.pack("<8sHHI32s6f5HH24s20s", b"\x89TRLUT\r\n", 1, 128, total, bytes(32), 1.5, thickness_mm,
                         0.0, 0.02, 0.95, 1e-3, 2, 2, 2, 2, 2, 0, b"tiny", bytes(20))
    body = header + bytes(sizes)
    return body + struct.pack("<I", zlib.crc32(body))


def _start_sim(binary: Path, tmp: Path):
    proc = subprocess.Popen([str(binary), "--storage", str(tmp / "storage.bin"), "--modbus-link",
                             str(tmp / "modbus"), "--plant-link", str(tmp / "plant"), "--address", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    deadline, seen = time.monotonic() + READY_TIMEOUT_S, b""
    while b"ready\n" not in seen:
        left = deadline - time.monotonic()
        if proc.poll() is not None or left <= 0:
            _stop(proc)
            pytest.fail(f"{binary.name} did not print ready within {READY_TIMEOUT_S} s")
        if select.select([proc.stdout], [], [], min(left, 0.1))[0]:
            seen += os.read(proc.stdout.fileno(), 256)
    return proc


def _stop(proc) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _sim_with_core(tmp_path_factory, name: str, core_sources: str):
    """The sim built with FIT_CORE_SRC=core_sources (empty: no core), started; yields its Device."""
    tmp = tmp_path_factory.mktemp(name)
    binary = tmp / f"trimeter-fw-sim-{name}"
    build = subprocess.run(["make", "-s", "-C", str(ROOT / "firmware"), "sim", "SIM_CFLAGS=-std=c11 -O0 -D_GNU_SOURCE",
                            f"FIT_CORE_SRC={core_sources}", f"SIM_BIN={binary}"],
                           capture_output=True, text=True, timeout=120)
    assert build.returncode == 0, build.stderr
    proc = _start_sim(binary, tmp)
    dev = Device.open(str(tmp / "modbus"))
    yield dev
    dev.close()
    _stop(proc)


@pytest.fixture(scope="module")
def coreless(tmp_path_factory):
    yield from _sim_with_core(tmp_path_factory, "coreless", "")


@pytest.fixture(scope="module")
def standin(tmp_path_factory):
    yield from _sim_with_core(tmp_path_factory, "standin", "tests/standin/fit_core_standin.c")


def _bins(n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    i_b = rng.uniform(0.01, 0.5, n)
    return i_b, i_b + rng.uniform(0.01, 0.4, n), rng.uniform(0.0, 0.9, n), np.full(n, 0.02), np.full(n, 0.95)


def test_firmware_built_without_the_inverse_core_refuses_to_fit_saying_so(coreless):
    assert coreless.read("fit_available") == 0
    with pytest.raises(DeviceError, match="built without the inverse core"):
        coreless.fit(*_bins(3), thickness_mm=0.4)
    assert coreless.read("fit_status") == regs.FitStatus.ERROR_UNAVAILABLE
    assert coreless.read("fit_bins_done") == 0


def test_unusable_arguments_are_refused_before_anything_is_sent(coreless):
    i_b, i_w, i_c, rho_b, rho_w = _bins(4)
    with pytest.raises(InputError, match="1-D arrays of one length"):
        coreless.fit(i_b, i_w[:3], i_c, rho_b, rho_w, thickness_mm=0.4)
    with pytest.raises(InputError, match="1-D arrays of one length"):
        coreless.fit([], [], [], [], [], thickness_mm=0.4)
    with pytest.raises(InputError, match="arrays of numbers"):
        coreless.fit(["a"] * 4, i_w, i_c, rho_b, rho_w, thickness_mm=0.4)
    with pytest.raises(InputError, match="fit_thickness_mm"):
        coreless.fit(i_b, i_w, i_c, rho_b, rho_w, thickness_mm=float("nan"))
    with pytest.raises(InputError, match="fit_thickness_mm: 101 is outside"):
        coreless.fit(i_b, i_w, i_c, rho_b, rho_w, thickness_mm=101)
    assert coreless.read("fit_status") == regs.FitStatus.ERROR_UNAVAILABLE  # nothing reached the device


def test_with_a_core_linked_bins_go_out_and_results_come_back_exactly(standin):
    assert standin.read("fit_available") == 1
    with pytest.raises(DeviceError, match="no valid active map table"):
        standin.fit(*_bins(2), thickness_mm=0.4)
    table = _tiny_table(thickness_mm=0.4)
    standin.flash_map(table, version=1)
    with pytest.raises(InputError, match="not for a 0.8 mm sample"):
        standin.fit(*_bins(2), thickness_mm=0.8)
    assert standin.read("fit_status") == regs.FitStatus.ERROR_GEOMETRY
    with pytest.raises(DeviceError, match="another map table"):
        standin.fit(*_bins(2), thickness_mm=0.4, table=_tiny_table(thickness_mm=0.8))
    with pytest.raises(InputError, match="not a map table"):
        standin.fit(*_bins(2), thickness_mm=0.4, table=b"\x89TRLUT\r\n0000")

    n = standin.fit_capacity + 45  # two runs, the second partial
    i_b, i_w, i_c, rho_b, rho_w = _bins(n)
    i_c[7], rho_w[300] = np.nan, np.inf  # the device flags these, it does not refuse them
    got = standin.fit(i_b, i_w, i_c, rho_b, rho_w, thickness_mm=0.4, table=table)
    f32 = [np.asarray(v, dtype=np.float32) for v in (i_b, i_w, i_c, rho_b, rho_w)]
    bad = np.zeros(n, dtype=bool)
    bad[[7, 300]] = True
    assert got.table_crc32 == zlib.crc32(table[:-4]) != zlib.crc32(_tiny_table(thickness_mm=0.8)[:-4])
    np.testing.assert_array_equal(got.flags, np.where(bad, 1, 0))
    assert np.isnan(got.alpha[bad]).all() and np.isnan(got.g[bad]).all()
    np.testing.assert_array_equal(got.alpha[~bad], f32[0][~bad])
    np.testing.assert_array_equal(got.sigma_t[~bad], (np.float32(10) * f32[1])[~bad])
    np.testing.assert_array_equal(got.g[~bad], (f32[2] - f32[3] - f32[4])[~bad])
    assert standin.read("fit_status") == regs.FitStatus.DONE
    assert standin.read("fit_bins_done") == n - standin.fit_capacity
