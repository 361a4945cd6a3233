"""The STM32F405 image boots in QEMU (netduinoplus2) and answers Modbus RTU on USART1.

QEMU emulates the CPU, SysTick, USART1 (RXNE interrupt only) and the NVIC, but not RCC, GPIO, flash
programming or the watchdog (docs/platform-notes.md), so this checks the port's boot path (vector table,
.data/.bss, FPU enable, clock fallback with timeouts), the USART driver and the core's register map
on the real instruction set — not motion or storage, which the host tests cover. Skipped when
qemu-system-arm or the image is missing.
"""

from __future__ import annotations

import shutil
import socket
import struct
import subprocess
import time
from pathlib import Path

import pytest

from trimeter import registers as R
from trimeter.crc import crc16_modbus as crc16

ROOT = Path(__file__).resolve().parents[2]
ELF = ROOT / "firmware" / "build" / "stm32" / "trimeter-fw.elf"
QEMU = shutil.which("qemu-system-arm")

pytestmark = [
    pytest.mark.skipif(QEMU is None, reason="qemu-system-arm not installed (Debian package qemu-system-arm)"),
    pytest.mark.skipif(not ELF.is_file(), reason=f"STM32 image not built ({ELF}): make -C firmware stm32"),
]


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    # USART1 on a Unix socket of this test's own: a TCP port picked free and handed to QEMU could be taken by
    # another process (a second pytest worker) before QEMU binds it, and the test would then talk to that
    path = tmp_path_factory.mktemp("qemu") / "usart1"
    proc = subprocess.Popen(
        [QEMU, "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-kernel", str(ELF),
         "-serial", f"unix:{path},server=on,wait=on"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 10
        while True:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                sock.connect(str(path))
                break
            except OSError:
                sock.close()
                assert proc.poll() is None and time.monotonic() < deadline, "QEMU did not open its serial port"
                time.sleep(0.05)
        sock.settimeout(0.5)
        yield sock
        sock.close()
    finally:
        proc.kill()
        proc.wait()


def _frame_length(reply: bytes) -> int:
    """The RTU reply's length as far as its first bytes tell: a CRC residue of 0 alone can end a frame early
    (some prefix of a longer reply may happen to check)."""
    if len(reply) >= 2 and reply[1] & 0x80:
        return 5
    if len(reply) >= 3 and reply[1] in (3, 4):
        return 3 + reply[2] + 2
    return 5


def transact(sock: socket.socket, pdu: bytes, tries: int = 10) -> bytes:
    """One RTU request; retried while the guest boots (bytes before USART init are lost)."""
    frame = bytes([1]) + pdu
    frame += struct.pack("<H", crc16(frame))
    for _ in range(tries):
        sock.sendall(frame)
        reply = b""
        try:
            while len(reply) < _frame_length(reply) or crc16(reply) != 0:
                chunk = sock.recv(300)
                if not chunk:
                    break
                reply += chunk
        except TimeoutError:
            continue
        if len(reply) >= 5 and crc16(reply) == 0 and reply[0] == 1:
            return reply[1:-2]
    pytest.fail(f"no valid reply to {pdu.hex()}")


def test_identity_and_register_map_hash(line):
    reply = transact(line, struct.pack(">BHH", 4, R.BY_NAME["vendor_id"].address, 8))
    words = struct.unpack(">8H", reply[2:])
    assert words[0] == R.VENDOR_ID
    h = R.BY_NAME["regmap_hash"].address
    assert (words[h] << 16 | words[h + 1]) == R.REGMAP_HASH


def test_config_defaults_and_a_refused_value(line):
    addr = R.BY_NAME["steps_per_mm"].address
    reply = transact(line, struct.pack(">BHH", 3, addr, 2))
    assert struct.unpack(">f", reply[2:6])[0] == pytest.approx(80.0)
    bad = struct.pack(">BHHB", 16, R.BY_NAME["slot_white_mm"].address, 2, 4) + struct.pack(">f", 1.0)
    assert transact(line, bad) == bytes([0x90, 3])  # inside the homing back-off: exception 03
    assert transact(line, struct.pack(">BHH", 6, R.BY_NAME["command"].address, R.Command.GOTO_WHITE)) == bytes(
        [0x86, 1])  # not homed: exception 01
