"""A real Modbus master (mbpoll, libmodbus) against the firmware sim over its pty.

Proves the wire format end to end, independently of our own pymodbus client: identity and map hash,
writes read back (u16, f32 in big-endian word order, coils), and the exception codes the register
map promises — 02 bad address (also for half of a wide value), 01 bad function, 03 bad value.
Addresses come from the generated trimeter.registers, never restated here.
"""

from __future__ import annotations

import os
import re
import select
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from trimeter import registers as R

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "firmware" / "build" / "sim" / "trimeter-fw-sim"
READY_TIMEOUT_S = 10.0

pytestmark = [
    pytest.mark.skipif(not SIM.is_file(), reason=f"firmware sim not built ({SIM}): run `make -C firmware sim`"),
    pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll not installed (Debian package mbpoll)"),
]


@pytest.fixture(scope="module")
def link(tmp_path_factory):
    """Start the sim, yield its Modbus pty link; SIGTERM it afterwards and expect a clean exit."""
    tmp = tmp_path_factory.mktemp("sim")
    modbus_link, plant_link = tmp / "modbus", tmp / "plant"
    proc = subprocess.Popen(
        [str(SIM), "--storage", str(tmp / "storage.bin"), "--modbus-link", str(modbus_link),
         "--plant-link", str(plant_link), "--address", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        seen = b""
        while b"ready\n" not in seen:
            left = deadline - time.monotonic()
            if proc.poll() is not None or left <= 0:
                pytest.fail(f"sim did not print ready within {READY_TIMEOUT_S} s (exit {proc.poll()})")
            if select.select([proc.stdout], [], [], min(left, 0.1))[0]:
                seen += os.read(proc.stdout.fileno(), 256)
        yield str(modbus_link)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = proc.wait()
    assert rc == 0, f"sim exited {rc} on SIGTERM"
    assert not modbus_link.exists(), "sim left its pty link behind"


MBPOLL = ["mbpoll", "-m", "rtu", "-a", "1", "-b", "19200", "-P", "none", "-1", "-o", "1"]


def mbpoll(link: str, *options: str, values: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """One mbpoll transaction; `values` makes it a write."""
    cmd = [*MBPOLL, *options, link]
    if values:
        cmd += ["--", *values]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=15)


def run(link: str, table: str, name: str, count: int = 1, values: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """Read (or write) the named item: PDU addresses (-0), big-endian word order (-B)."""
    options = ["-0", "-B", "-t", table, "-r", str(R.BY_NAME[name].address)]
    if not values:  # mbpoll refuses -c on writes: the count is the number of values
        options += ["-c", str(count)]
    return mbpoll(link, *options, values=values)


def values_of(result: subprocess.CompletedProcess) -> dict[int, str]:
    assert result.returncode == 0, result.stdout + result.stderr
    return {int(a): v for a, v in re.findall(r"^\[(\d+)\]:\s+(\S+)", result.stdout, flags=re.M)}


def test_identity_and_map_hash(link):
    vals = values_of(run(link, "3:hex", "vendor_id", count=8))
    base = R.BY_NAME["vendor_id"].address
    words = [int(vals[base + i], 16) for i in range(8)]
    assert words[R.BY_NAME["vendor_id"].address - base] == R.VENDOR_ID
    assert words[R.BY_NAME["model_id"].address - base] == R.MODEL_ID
    major, minor, patch = (words[R.BY_NAME[f"firmware_version_{p}"].address - base]
                           for p in ("major", "minor", "patch"))
    assert (major, minor, patch) == R.FIRMWARE_VERSION
    h = R.BY_NAME["regmap_hash"].address - base
    assert (words[h] << 16 | words[h + 1]) == R.REGMAP_HASH


def test_write_then_read_u16_f32_and_coil(link):
    assert run(link, "4", "led_panels_level", values=("500",)).returncode == 0
    assert values_of(run(link, "4", "led_panels_level")) == {R.BY_NAME["led_panels_level"].address: "500"}

    slot = R.BY_NAME["slot_white_mm"]
    assert run(link, "4:float", "slot_white_mm", values=("61.5",)).returncode == 0
    assert float(values_of(run(link, "4:float", "slot_white_mm"))[slot.address]) == 61.5
    # Big-endian word order on the wire: the high word of 61.5f (0x4276_0000) comes first.
    raw = values_of(run(link, "4:hex", "slot_white_mm", count=2))
    assert (raw[slot.address], raw[slot.address + 1]) == ("0x4276", "0x0000")

    coil = R.BY_NAME["led_collimated_on"]
    assert run(link, "0", "led_collimated_on", values=("1",)).returncode == 0
    assert values_of(run(link, "0", "led_collimated_on")) == {coil.address: "1"}
    assert run(link, "0", "led_collimated_on", values=("0",)).returncode == 0


def test_exception_02_bad_address(link):
    result = mbpoll(link, "-0", "-t", "3", "-r", str(R.SPANS["input_register"]))
    assert result.returncode != 0
    assert "Illegal data address" in result.stderr


def test_exception_02_half_of_a_wide_value(link):
    before = values_of(run(link, "4:hex", "steps_per_mm", count=2))
    low_word = R.BY_NAME["steps_per_mm"].address + 1
    result = mbpoll(link, "-0", "-t", "4", "-r", str(low_word), values=("0",))
    assert "Illegal data address" in result.stderr
    assert values_of(run(link, "4:hex", "steps_per_mm", count=2)) == before


def test_exception_01_bad_function(link):
    # -u sends FC 0x11 (report server id), which the firmware does not implement. mbpoll exits 0 here,
    # so the exception text is what tells.
    result = mbpoll(link, "-u")
    assert "Illegal function" in result.stderr


def test_exception_03_bad_value_changes_nothing(link):
    reg = R.BY_NAME["led_collimated_level"]
    before = values_of(run(link, "4", "led_collimated_level"))
    result = run(link, "4", "led_collimated_level", values=(str(reg.max + 1),))
    assert result.returncode != 0
    assert "Illegal data value" in result.stderr
    assert values_of(run(link, "4", "led_collimated_level")) == before
