"""The firmware sim as a process: its CLI, the plant-control protocol (firmware/ports/sim/README.md),
scaled simulated time, and the core's behaviour seen from both sides — Modbus on the pty (raw RTU
frames, independent of the host client) and the plant's physical state on the socket.

Runs the sim at --time-scale 50, so a homing of a few simulated seconds costs ~0.1 s here.
Addresses come from the generated trimeter.registers.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import struct
import subprocess
import time
from pathlib import Path

import pytest
import serial

from trimeter import registers as R
from trimeter.crc import crc16_modbus as crc16

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "firmware" / "build" / "sim" / "trimeter-fw-sim"
TIME_SCALE = 50.0

pytestmark = pytest.mark.skipif(not SIM.is_file(), reason=f"firmware sim not built ({SIM}): make -C firmware sim")


class Sim:
    """One sim process with a raw Modbus line and a plant socket."""

    def __init__(self, tmp: Path, storage: Path | None = None, extra: tuple[str, ...] = ()):
        self.tmp = tmp
        self.storage = storage or tmp / "storage.bin"
        self.modbus_link, self.plant_link = tmp / "modbus", tmp / "plant"
        self.proc = subprocess.Popen(
            [str(SIM), "--storage", str(self.storage), "--modbus-link", str(self.modbus_link),
             "--plant-link", str(self.plant_link), "--time-scale", str(TIME_SCALE), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        seen, deadline = b"", time.monotonic() + 10
        while b"ready\n" not in seen:
            assert self.proc.poll() is None and time.monotonic() < deadline, "sim did not print ready"
            if select.select([self.proc.stdout], [], [], 0.1)[0]:
                seen += os.read(self.proc.stdout.fileno(), 64)
        self.line = serial.Serial(str(self.modbus_link), 19200, timeout=2)
        self.sock = socket.socket(socket.AF_UNIX)
        self.sock.settimeout(5)
        self.sock.connect(str(self.plant_link))
        self.sock_file = self.sock.makefile("rwb")

    # -- plant socket
    def raw(self, line: bytes) -> dict:
        self.sock_file.write(line + b"\n")
        self.sock_file.flush()
        return json.loads(self.sock_file.readline())

    def plant(self, **message) -> dict:
        return self.raw(json.dumps(message).encode())

    def state(self) -> dict:
        reply = self.plant(cmd="state")
        assert reply["ok"], reply
        return reply

    # -- Modbus RTU
    def transact(self, pdu: bytes) -> bytes:
        frame = bytes([1]) + pdu
        self.line.reset_input_buffer()
        self.line.write(frame + struct.pack("<H", crc16(frame)))
        head = self.line.read(2)
        assert len(head) == 2, "no reply"
        fc = head[1]
        if fc & 0x80:
            rest = self.line.read(3)
        elif fc in (1, 2, 3, 4):
            count = self.line.read(1)
            rest = count + self.line.read(count[0] + 2)
        else:
            rest = self.line.read(6)
        reply = head + rest
        assert crc16(reply) == 0, f"bad CRC in reply {reply.hex()}"
        return reply[1:-2]

    def write_regs(self, name: str, words: list[int]) -> int:
        """FC16; returns 0 or the exception code."""
        addr = R.BY_NAME[name].address
        pdu = struct.pack(">BHHB", 16, addr, len(words), 2 * len(words)) + struct.pack(f">{len(words)}H", *words)
        reply = self.transact(pdu)
        return reply[1] if reply[0] & 0x80 else 0

    def command(self, name: str) -> int:
        return self.write_regs("command", [R.Command[name.upper()]])

    def read_input(self, name: str, count: int = 1) -> list[int]:
        reply = self.transact(struct.pack(">BHH", 4, R.BY_NAME[name].address, count))
        assert reply[0] == 4, reply.hex()
        return list(struct.unpack(f">{count}H", reply[2:]))

    def read_holding(self, name: str, count: int = 1) -> list[int]:
        reply = self.transact(struct.pack(">BHH", 3, R.BY_NAME[name].address, count))
        assert reply[0] == 3, reply.hex()
        return list(struct.unpack(f">{count}H", reply[2:]))

    def wait(self, predicate, sim_seconds: float) -> dict:
        """Poll the plant until predicate(state) or sim_seconds of *simulated* time passed."""
        start = self.state()["time_s"]
        while True:
            s = self.state()
            if predicate(s):
                return s
            assert s["time_s"] - start < sim_seconds, f"timed out after {sim_seconds} s simulated: {s}"
            time.sleep(0.005)

    def stop(self) -> int:
        self.line.close()
        self.sock.close()
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=5)


@pytest.fixture
def sim(tmp_path):
    s = Sim(tmp_path)
    yield s
    assert s.stop() == 0
    assert not s.modbus_link.exists() and not s.plant_link.exists()


def f32_words(x: float) -> list[int]:
    return list(struct.unpack(">2H", struct.pack(">f", x)))


def test_state_reply_and_scaled_time(sim):
    s = sim.state()
    assert s["position_mm"] == pytest.approx(50.0) and s["homed"] is False and s["fault"] is None
    assert set(s["shutters"]) == {"panel_left", "panel_right", "collimated"}
    assert all(not sh["open"] for sh in s["shutters"].values())
    assert s["leds"]["panels"] == 0 and s["slot"] is None and s["state"] in ("idle", "settling")
    # Simulated time runs at the scale, and lets time slip rather than chase a backlog when the machine is
    # starved: never faster than the scale, and at it in at least one of a few windows (a loaded CI machine
    # may starve one).
    rates = []
    for _ in range(5):
        t0, wall0 = sim.state()["time_s"], time.monotonic()
        time.sleep(0.2)
        rates.append((sim.state()["time_s"] - t0) / (time.monotonic() - wall0))
        if rates[-1] > 0.7 * TIME_SCALE:
            break
    assert max(rates) < 1.1 * TIME_SCALE and rates[-1] > 0.7 * TIME_SCALE, rates


def test_bad_requests_change_nothing(sim):
    before = sim.state()
    for line in (b"not json", b'{"cmd":"fly"}', b'{"cmd":"set","stuck_slider":1}',
                 b'{"cmd":"set","stuck_slider":true,"colour":"red"}', b'{"cmd":"state","x":{"y":1}}',
                 b'{"cmd":"press_button","hold_ms":-5}', b"x" * 5000):
        reply = sim.raw(line)
        assert reply["ok"] is False and reply["error"], line[:40]
    after = sim.state()
    assert after["stuck_slider"] is False and after["button"] is False
    assert after["position_steps"] == before["position_steps"]


def test_home_and_goto_move_the_plant(sim):
    assert sim.command("goto_white") == 1  # not homed: wrong state
    assert sim.command("home") == 0
    s = sim.wait(lambda s: s["homed"] and s["state"] == "idle", 20)
    assert s["position_mm"] == pytest.approx(2.0)  # zero at the switch, then the back-off
    assert sim.command("goto_white") == 0
    s = sim.wait(lambda s: s["state"] == "idle", 20)
    assert s["slot"] == "white" and s["position_mm"] == pytest.approx(60.0)
    assert sim.read_input("position_slot") == [R.Slot.WHITE]


def test_shutters_and_leds_follow_coils(sim):
    reply = sim.transact(struct.pack(">BHHB", 15, 0, 6, 1) + bytes([0b011011]))  # panels' shutters + LEDs
    assert reply[0] == 15
    s = sim.wait(lambda s: s["state"] == "idle", 5)
    assert s["shutters"]["panel_left"]["open"] and s["shutters"]["panel_right"]["open"]
    assert not s["shutters"]["collimated"]["open"]
    assert s["leds"]["panels"] == pytest.approx(1.0) and s["leds"]["collimated"] == 0


def test_stuck_slider_faults_and_reset_keeps_the_plant(sim):
    assert sim.command("home") == 0
    sim.wait(lambda s: s["homed"] and s["state"] == "idle", 20)
    assert sim.plant(cmd="set", stuck_slider=True)["ok"]
    assert sim.command("goto_open") == 0
    s = sim.wait(lambda s: s["fault"] is not None, 20)
    assert s["fault"] == "stall" and s["fault_code"] == R.Fault.STALL
    assert s["status_pattern"] == "fast_blink"
    assert sim.command("home") == 1  # latched
    assert sim.plant(cmd="reset")["ok"]
    s = sim.state()
    assert s["fault"] is None and s["homed"] is False and s["stuck_slider"] is True
    assert s["position_mm"] == pytest.approx(2.0)


def test_broken_endstop_times_out(sim):
    assert sim.plant(cmd="set", endstop_broken=True)["ok"]
    assert sim.command("home") == 0
    s = sim.wait(lambda s: s["fault"] is not None, 30)
    assert s["fault"] == "homing_timeout" and s["endstop"] is False


def test_press_button_counts_one_event(sim):
    assert sim.read_input("button_events") == [0]
    assert sim.plant(cmd="press_button")["ok"]
    sim.wait(lambda s: not s["button"], 2)
    time.sleep(0.01)
    assert sim.read_input("button_events") == [1]


def test_saved_config_survives_a_restart_and_bad_values_are_refused(tmp_path):
    first = Sim(tmp_path)
    try:
        assert first.write_regs("slot_white_mm", f32_words(70.0)) == 0
        assert first.write_regs("slot_white_mm", f32_words(1.0)) == 3  # inside the homing back-off
        assert first.command("save_config") == 1  # destructive: refused without an unlock first
        assert first.write_regs("unlock", [R.Unlock.KEY]) == 0
        assert first.command("save_config") == 0
    finally:
        assert first.stop() == 0
    second = Sim(tmp_path)
    try:
        assert second.read_holding("slot_white_mm", 2) == f32_words(70.0)
    finally:
        assert second.stop() == 0


def test_foreign_storage_file_is_refused_untouched(tmp_path):
    storage = tmp_path / "notes.txt"
    storage.write_bytes(b"my precious notes")
    proc = subprocess.run([str(SIM), "--storage", str(storage), "--modbus-link", str(tmp_path / "m"),
                           "--plant-link", str(tmp_path / "p")], capture_output=True, text=True, timeout=10)
    assert proc.returncode == 2 and "not a sim storage image" in proc.stderr
    assert storage.read_bytes() == b"my precious notes"
