"""Twins on one simulated RS-485 bus (trimeter.twin.bus, `trimeter sim --instruments N`): each firmware answers at
its own address only, an address nobody has stays silent, a fault stays on its own twin's branch, and the CLI
prints the bus and the instruments."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from trimeter import registers as regs
from trimeter.device.bus import count_replies, probe_request
from trimeter.errors import InputError
from trimeter.twin import FaultConfig
from trimeter.twin._rtu import RtuMaster
from trimeter.twin.bus import TwinBus, check_addresses

UPTIME = regs.BY_NAME["uptime_s"]
VENDOR = regs.BY_NAME["vendor_id"]


def _read(port: str, address: int, register=VENDOR, attempts: int = 3) -> list[int] | None:
    master = RtuMaster(port, address=address, timeout_s=0.3)
    try:
        for _ in range(attempts):
            if (words := master.read_input(register.address, register.words)) is not None:
                return words
        return None
    finally:
        master.close()


def test_each_twin_answers_at_its_own_address_only_and_an_unused_address_is_silent(tmp_path):
    with TwinBus(3, time_scale=20.0, state_dir=tmp_path) as bus:
        assert bus.ports()["modbus_port"] == bus.modbus_port
        assert [i["address"] for i in bus.ports()["instruments"]] == [1, 2, 3]
        for address in (1, 2, 3):
            assert _read(bus.modbus_port, address) == [regs.VENDOR_ID]
        assert _read(bus.modbus_port, 4) is None
        for twin in bus.twins:  # the others heard every request and answered none of theirs
            assert twin.control.state()["counters"]["requests"] >= 4
        assert bus.twin(2).address == 2
        with pytest.raises(InputError, match="no instrument at address 9"):
            bus.twin(9)


def test_a_fault_on_one_twin_stays_on_its_branch(tmp_path):
    faults = [None, FaultConfig(drop=1.0), None]
    with TwinBus(3, time_scale=20.0, faults=faults, state_dir=tmp_path) as bus:
        for _ in range(5):
            assert _read(bus.modbus_port, 1) == [regs.VENDOR_ID]
            assert _read(bus.modbus_port, 3) == [regs.VENDOR_ID]
        assert _read(bus.modbus_port, 2) is None  # every reply of twin 2 dropped
        bus.twin(2).control.set_fault(drop=0.0)
        assert _read(bus.modbus_port, 2) == [regs.VENDOR_ID]


def test_two_twins_at_one_address_both_answer(tmp_path):
    with TwinBus(addresses=[1, 1, 2], time_scale=20.0, state_dir=tmp_path) as bus:
        assert _replies(bus.modbus_port, 1) == 2
        assert _replies(bus.modbus_port, 2) == 1
        assert _replies(bus.modbus_port, 3) == 0


def _replies(port: str, address: int, listen_s: float = 0.3) -> int:
    """Every reply to one request within listen_s (count_replies: -1 for collided bytes)."""
    master = RtuMaster(port, address=address)
    try:
        os.write(master.fd, probe_request(address))
        data, deadline = b"", time.monotonic() + listen_s
        while time.monotonic() < deadline:
            try:
                data += os.read(master.fd, 256)
            except BlockingIOError:
                time.sleep(0.002)
        return count_replies(data, address)
    finally:
        master.close()


@pytest.mark.parametrize("args,message", [((0,), "1..32 instruments"), ((33,), "1..32 instruments"),
                                          ((True,), "must be an integer")])
def test_bad_bus_sizes_are_refused(args, message):
    with pytest.raises(InputError, match=message):
        TwinBus(*args)


def test_bad_addresses_and_fault_lists_are_refused():
    with pytest.raises(InputError, match="within 1..247"):
        check_addresses([1, 248])
    with pytest.raises(InputError, match="2 given for 3 instruments"):
        TwinBus(3, faults=[None, None])


def test_sim_instruments_prints_the_bus_and_each_instrument_and_ctl_reaches_one(tmp_path):
    env = {**os.environ, "TRIMETER_KERNEL": "numpy"}
    process = subprocess.Popen([sys.executable, "-m", "trimeter", "sim", "--instruments", "3", "--json",
                                "--time-scale", "20", "--state-dir", str(tmp_path)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert process.stdout is not None
        ports = json.loads(process.stdout.readline())
        assert set(ports) == {"modbus_port", "instruments"}
        assert [i["address"] for i in ports["instruments"]] == [1, 2, 3]
        assert all(set(i) == {"address", "spectrometer_url", "control_path"} for i in ports["instruments"])
        assert _read(ports["modbus_port"], 3, attempts=3) == [regs.VENDOR_ID]
        ctl = [sys.executable, "-m", "trimeter", "sim", "--state-dir", str(tmp_path), "--ctl"]
        one = subprocess.run([*ctl, "set_fault", "drop=1.0", "--address", "2"], capture_output=True, text=True,
                             env=env)
        assert one.returncode == 0, one.stderr
        # the one that must answer gets more attempts than the silent one: a loaded machine answers late
        assert _read(ports["modbus_port"], 2) is None
        assert _read(ports["modbus_port"], 1, attempts=10) == [regs.VENDOR_ID]
        which = subprocess.run([*ctl, "state"], capture_output=True, text=True, env=env)
        assert which.returncode == 2 and "give --address (one of 1, 2, 3)" in which.stderr
    finally:
        process.send_signal(signal.SIGINT)
        process.wait(timeout=30)
    assert process.returncode == 0
    assert not (tmp_path / "ports.json").exists() and not (tmp_path / "instrument-1" / "ports.json").exists()


def test_the_firmware_address_is_configurable_and_saved_and_an_override_wins(tmp_path, monkeypatch):
    """`config set modbus_address` + `config save`: after a reset the firmware answers at the new address only;
    a twin started with an address (a bus position) answers there whatever is saved."""
    from trimeter.cli import main
    from trimeter.twin import Twin

    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    with Twin(time_scale=20.0, state_dir=tmp_path / "twin") as twin:
        port = str(twin.modbus_port)
        assert main(["config", "set", "modbus_address", "7", "--port", port]) == 0
        assert _read(port, 1) == [regs.VENDOR_ID]  # takes effect at the next boot
        assert main(["config", "save", "--port", port]) == 0
        twin.control.reset_firmware()
        time.sleep(0.3)
        assert _read(port, 7, attempts=3) == [regs.VENDOR_ID] and _read(port, 1) is None
    with Twin(time_scale=20.0, state_dir=tmp_path / "twin", address=3) as twin:
        assert _read(str(twin.modbus_port), 3, attempts=3) == [regs.VENDOR_ID]
        assert _read(str(twin.modbus_port), 7) is None
    with pytest.raises(InputError, match="within 1..247"):
        Twin(address=0)
