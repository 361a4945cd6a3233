"""The STM32F405 build's flashable artifacts, and what of the program runs from RAM.

Flashing must never erase the saved configuration or the maps: every artifact the build leaves in
firmware/build/stm32 (the ELF's load segments, the .hex, the per-run .bin images) is read here on its
own terms and must hold no byte in a storage sector (ports/stm32f405/flash_layout.h), and together
the images must carry exactly the ELF's bytes. The flash commands are checked as printed (RUN=echo):
no board is attached to the build machine.

The F405 stalls every flash fetch while it programs, so the step timer's ISR, the ISRs that could
hold it up, everything they call and the hooks they call through must be in RAM and load nothing
from flash; the disassembly shows it.
"""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "firmware"
PORT = FIRMWARE / "ports" / "stm32f405"
BUILD = FIRMWARE / "build" / "stm32"
ELF = BUILD / "trimeter-fw.elf"
OBJDUMP = shutil.which("arm-none-eabi-objdump")

FLASH = range(0x08000000, 0x08100000)
RAM = range(0x20000000, 0x20020000)
SECTOR_SIZES = [0x4000] * 4 + [0x10000] + [0x20000] * 7
# The ISRs (the step timer's, and those that could stall ahead of it) and the flash driver's entries.
RAM_ROOTS = ["TIM5_IRQHandler", "SysTick_Handler", "USART1_IRQHandler", "flash_region_write", "flash_region_erase"]
# Hooks motion_isr calls through the hal_t (hal.h's [ISR] ones, and stepper_enable when it faults).
ISR_HOOKS = ["stepper_enable", "stepper_dir", "stepper_step", "endstop_active", "stepper_stalled"]

built = pytest.mark.skipif(not ELF.is_file(), reason=f"STM32 image not built ({ELF}): make -C firmware stm32")


def sector_ranges() -> list[range]:
    out, start = [], FLASH.start
    for size in SECTOR_SIZES:
        out.append(range(start, start + size))
        start += size
    return out


def storage_ranges() -> dict[str, range]:
    text = (PORT / "flash_layout.h").read_text()
    found = dict(re.findall(r"#define FLASH_STORAGE_SECTOR_(\w+) (\d+)u", text))
    assert set(found) == {"CONFIG_A", "CONFIG_B", "MAP_A", "MAP_B"}
    return {name: sector_ranges()[int(n)] for name, n in found.items()}


def elf_load_segments(data: bytes) -> list[tuple[int, int, bytes]]:
    """(run address, load address, bytes) of every PT_LOAD segment with contents."""
    phoff, = struct.unpack_from("<I", data, 28)
    phentsize, phnum = struct.unpack_from("<HH", data, 42)
    out = []
    for i in range(phnum):
        p_type, offset, vaddr, paddr, filesz, *_ = struct.unpack_from("<8I", data, phoff + i * phentsize)
        if p_type == 1 and filesz:
            out.append((vaddr, paddr, data[offset:offset + filesz]))
    return out


def elf_flash_bytes() -> dict[int, int]:
    return spread({paddr: data for _vaddr, paddr, data in elf_load_segments(ELF.read_bytes())})


def initial_value(address: int, size: int) -> bytes:
    """What the reset handler copies to a RAM address: its bytes in the segment loaded there."""
    for vaddr, _paddr, data in elf_load_segments(ELF.read_bytes()):
        if vaddr <= address and address + size <= vaddr + len(data):
            return data[address - vaddr:address - vaddr + size]
    raise AssertionError(f"0x{address:08x} has no initial value in a load segment")


def hex_bytes(text: str) -> dict[int, int]:
    """Address → byte of an Intel HEX file (checksums checked)."""
    out: dict[int, int] = {}
    base = 0
    for line in text.split():
        assert line.startswith(":")
        rec = bytes.fromhex(line[1:])
        assert sum(rec) & 0xFF == 0, f"bad checksum: {line}"
        count, address, kind, payload = rec[0], rec[1] << 8 | rec[2], rec[3], rec[4:-1]
        assert len(payload) == count
        if kind == 0:
            for i, b in enumerate(payload):
                assert base + address + i not in out
                out[base + address + i] = b
        elif kind == 2:
            base = int.from_bytes(payload, "big") << 4
        elif kind == 4:
            base = int.from_bytes(payload, "big") << 16
        elif kind == 1:
            break
    return out


def spread(segments: dict[int, bytes]) -> dict[int, int]:
    return {address + i: b for address, data in segments.items() for i, b in enumerate(data)}


def overlaps(addresses: set[int] | dict[int, int], ranges: dict[str, range]) -> list[str]:
    lo, hi = min(addresses), max(addresses)
    return [name for name, r in ranges.items() if r.start <= hi and lo < r.stop
            and any(a in r for a in addresses)]


@built
def test_every_flashable_artifact_avoids_the_storage_sectors():
    storage = storage_ranges()
    elf = elf_flash_bytes()
    assert elf and set(elf) <= set(FLASH), "a load segment outside flash"
    artifacts = sorted(p for p in BUILD.iterdir() if p.suffix in {".bin", ".hex", ".dfu", ".srec", ".elf"})
    images = [p for p in artifacts if p.suffix == ".bin"]
    assert images and (BUILD / "trimeter-fw.hex") in artifacts
    assert {p.suffix for p in artifacts} <= {".bin", ".hex", ".elf"}, "an artifact this test does not read"

    for name in ("CONFIG_A", "CONFIG_B", "MAP_A", "MAP_B"):
        assert not any(a in storage[name] for a in elf), f"the ELF loads bytes into {name}"

    hexed = hex_bytes((BUILD / "trimeter-fw.hex").read_text())
    assert not overlaps(hexed, storage)
    assert all(elf.get(a) == b for a, b in hexed.items())
    # objcopy leaves out the alignment padding between sections that the ELF's segments carry
    assert all(elf[a] == 0 for a in set(elf) - set(hexed))

    from_bins: dict[int, int] = {}
    for path in images:
        match = re.fullmatch(r"trimeter-fw-0x([0-9A-F]{8})\.bin", path.name)
        assert match, f"{path.name}: a .bin must name the address it is written to"
        address = int(match.group(1), 16)
        data = path.read_bytes()
        assert not overlaps(spread({address: data}), storage), path.name
        for i, b in enumerate(data):
            assert address + i not in from_bins
            from_bins[address + i] = b
    assert from_bins == elf


def test_the_layout_is_the_one_boards_in_the_field_have():
    """Moving a storage sector would lose every saved config or map on the next flash."""
    storage = storage_ranges()
    assert (storage["CONFIG_A"].start, storage["CONFIG_B"].start) == (0x08008000, 0x0800C000)
    assert (storage["MAP_A"].start, storage["MAP_B"].start) == (0x08020000, 0x08040000)


def test_image_tool_refuses_an_elf_that_writes_a_storage_sector(tmp_path):
    """A program that grew into sector 2 (a hand-made ELF with one load segment there)."""
    header = bytearray(52)
    header[:6] = b"\x7fELF\x01\x01"
    struct.pack_into("<IHH", header, 28, 52, 32, 1)  # e_phoff … (e_flags, e_ehsize left 0)
    struct.pack_into("<HH", header, 42, 32, 1)
    segment = struct.pack("<8I", 1, 84, 0x08007F00, 0x08007F00, 0x200, 0x200, 5, 4)
    elf = tmp_path / "grown.elf"
    elf.write_bytes(bytes(header) + segment + b"\0" * 0x200)
    result = subprocess.run([sys.executable, PORT / "image.py", elf, tmp_path], capture_output=True, text=True)
    assert result.returncode != 0
    assert "config_a storage sector" in result.stderr
    assert not list(tmp_path.glob("*.bin"))


@built
def test_flash_commands_write_the_elf_or_each_image_at_its_address():
    out = subprocess.run(
        ["make", "-s", "-C", FIRMWARE, "-o", "build/stm32/trimeter-fw.elf", "flash", "flash-dfu", "flash-stlink",
         "RUN=echo"], capture_output=True, text=True, check=True).stdout.splitlines()
    images = sorted(BUILD.glob("trimeter-fw-0x*.bin"))
    addresses = [p.name[len("trimeter-fw-"):-len(".bin")] for p in images]
    openocd = [line.split() for line in out if line.startswith("openocd ")]
    assert openocd == [["openocd", "-f", "interface/stlink.cfg", "-f", "target/stm32f4x.cfg", "-c", "program",
                        "build/stm32/trimeter-fw.elf", "verify", "reset", "exit"]]
    dfu = [line.split() for line in out if line.startswith("dfu-util ")]
    assert [d[:4] for d in dfu] == [["dfu-util", "-a", "0", "-s"]] * len(images)
    assert [d[4] for d in dfu] == addresses[:-1] + [addresses[-1] + ":leave"]
    assert [d[6] for d in dfu] == [f"build/stm32/{p.name}" for p in images]
    stlink = [line.split() for line in out if line.startswith("st-flash ")]
    assert [s[-2:] for s in stlink] == [[f"build/stm32/{p.name}", a] for p, a in zip(images, addresses, strict=True)]
    assert ["--reset" in s for s in stlink] == [False] * (len(images) - 1) + [True]


# ---------------------------------------------------------------- what runs from RAM

def disassembly() -> dict[str, dict]:
    """name → {address, branches (target names), words (literal-pool values), movt (immediates)}."""
    text = subprocess.run([OBJDUMP, "-d", "--no-show-raw-insn", ELF], capture_output=True, text=True,
                          check=True).stdout
    functions: dict[str, dict] = {}
    current = None
    for line in text.splitlines():
        head = re.match(r"^([0-9a-f]{8}) <([^>]+)>:$", line)
        if head:
            current = functions.setdefault(head.group(2), {"address": int(head.group(1), 16), "branches": set(),
                                                           "words": [], "movt": []})
            continue
        if current is None:
            continue
        branch = re.match(r"^\s*[0-9a-f]+:\s+(?:b|bl|blx|b\.w|b\.n|b[a-z]{2}(?:\.[nw])?|cbn?z)\s+(?:\w+,\s*)?"
                          r"[0-9a-f]+ <([^>+]+)(?:\+0x[0-9a-f]+)?>", line)
        if branch:
            current["branches"].add(branch.group(1))
        word = re.match(r"^\s*[0-9a-f]+:\s+\.word\s+0x([0-9a-f]+)", line)
        if word:
            current["words"].append(int(word.group(1), 16))
        movt = re.match(r"^\s*[0-9a-f]+:\s+movt\s+\w+,\s*#(\d+)", line)
        if movt:
            current["movt"].append(int(movt.group(1)))
    # A linker veneer (a call too far for bl, e.g. RAM → flash) jumps to the address in its literal.
    by_address = {f["address"]: name for name, f in functions.items()}
    for name, f in functions.items():
        if name.endswith("_veneer"):
            f["branches"].update(by_address[w & ~1] for w in f["words"] if w & ~1 in by_address)
    return functions


def reachable(functions: dict[str, dict], roots: list[str]) -> set[str]:
    seen, todo = set(), list(roots)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        todo.extend(functions[name]["branches"])
    return seen


def symbols() -> dict[str, int]:
    nm = shutil.which("arm-none-eabi-nm")
    out = subprocess.run([nm, ELF], capture_output=True, text=True, check=True).stdout
    return {parts[2]: int(parts[0], 16) for parts in (line.split() for line in out.splitlines()) if len(parts) == 3}


needs_objdump = pytest.mark.skipif(OBJDUMP is None, reason="arm-none-eabi-objdump not installed")


@built
@needs_objdump
def test_the_isrs_and_the_flash_driver_run_from_ram_without_touching_flash():
    functions = disassembly()
    called = reachable(functions, RAM_ROOTS)
    assert {"app_step_isr", "motion_isr", "wait_idle"} <= called  # the walk does follow the calls
    in_flash = sorted(n for n in called if functions[n]["address"] not in RAM)
    assert not in_flash, f"reached from {RAM_ROOTS} but in flash: {in_flash}"
    # The flash driver handles flash addresses by design; the ISRs' code must not load from flash.
    for name in reachable(functions, RAM_ROOTS[:3]):
        loads = [hex(w) for w in functions[name]["words"] if w in FLASH]
        assert not loads and 0x0800 not in functions[name]["movt"], f"{name} refers to flash: {loads}"


@built
@needs_objdump
def test_the_vector_table_and_the_step_hooks_are_read_from_ram():
    syms = symbols()
    table = syms["ram_vector_table"]
    assert table in RAM and table % 512 == 0
    assert table in disassembly()["reset_handler"]["words"]  # filled at reset (QEMU boots through it)

    fields = re.findall(r"\(\*(\w+)\)\(", (FIRMWARE / "core" / "hal.h").read_text())
    assert fields[:3] == ["uart_read", "uart_write", "now_us"]
    hal = syms["board_hal"]
    assert hal in RAM
    pointers = struct.unpack("<" + "I" * (1 + len(fields)), initial_value(hal, 4 * (1 + len(fields))))
    for hook in ISR_HOOKS:
        pointer = pointers[1 + fields.index(hook)]  # after void *ctx
        assert pointer & ~1 in RAM, f"board_hal.{hook} → 0x{pointer:08x} is in flash"


def test_gen_pinout_refuses_a_backup_domain_pin(tmp_path):
    pinout = (ROOT / "hardware" / "pinout.toml").read_text()
    ok = subprocess.run([sys.executable, PORT / "gen_pinout.py", ROOT / "hardware" / "pinout.toml",
                         tmp_path / "ok.h"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    bad = tmp_path / "pinout.toml"
    bad.write_text(re.sub(r'(\[status_led\][^\[]*?port = )"\w"\s+pin = \d+', r'\1"C"\npin = 13', pinout))
    assert '"C"\npin = 13' in bad.read_text()
    result = subprocess.run([sys.executable, PORT / "gen_pinout.py", bad, tmp_path / "bad.h"],
                            capture_output=True, text=True)
    assert result.returncode != 0 and "[status_led] PC13 is a backup-domain pin" in result.stderr
