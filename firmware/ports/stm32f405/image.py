"""Turn the linked ELF into flashable images that write only the program's own sectors.

usage: image.py FIRMWARE.elf OUTDIR

The program sits in two runs of flash around the storage sectors (stm32f405.ld); one .bin spanning
both would carry zeros over the saved config and maps. This writes one raw image per run,
OUTDIR/trimeter-fw-0x<ADDRESS>.bin (what st-flash and dfu-util take with an address), removes
images of an earlier layout, prints the layout, and fails if any loadable byte lies in a storage
sector (flash_layout.h).
"""

from __future__ import annotations

import re
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
PT_LOAD = 1
FLASH_BASE = 0x08000000
STEM = "trimeter-fw"


def sector_spans() -> list[tuple[int, int]]:
    """(start, end) of every F405 sector, RM0090 Table 5: 4 × 16 KiB, 64 KiB, 7 × 128 KiB."""
    sizes = [0x4000] * 4 + [0x10000] + [0x20000] * 7
    spans, start = [], FLASH_BASE
    for size in sizes:
        spans.append((start, start + size))
        start += size
    return spans


def storage_sectors(layout_h: Path = HERE / "flash_layout.h") -> dict[str, int]:
    found = re.findall(r"#define FLASH_STORAGE_SECTOR_(\w+) (\d+)u", layout_h.read_text())
    if not found:
        sys.exit(f"{layout_h}: no FLASH_STORAGE_SECTOR_* definitions")
    return {name.lower(): int(number) for name, number in found}


def load_segments(elf: bytes) -> list[tuple[int, bytes]]:
    """(load address, bytes) of every PT_LOAD segment with file contents, in address order."""
    if elf[:4] != b"\x7fELF" or elf[4] != 1 or elf[5] != 1:
        sys.exit("not a 32-bit little-endian ELF")
    phoff, = struct.unpack_from("<I", elf, 28)
    phentsize, phnum = struct.unpack_from("<HH", elf, 42)
    segments = []
    for i in range(phnum):
        p_type, offset, _vaddr, paddr, filesz, _memsz, _flags, _align = struct.unpack_from(
            "<8I", elf, phoff + i * phentsize)
        if p_type == PT_LOAD and filesz:
            segments.append((paddr, elf[offset:offset + filesz]))
    return sorted(segments)


def runs(segments: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
    """Segments that follow each other without a gap merged into one image each."""
    merged: list[tuple[int, bytearray]] = []
    for address, data in segments:
        if merged and merged[-1][0] + len(merged[-1][1]) == address:
            merged[-1][1].extend(data)
        else:
            merged.append((address, bytearray(data)))
    return [(address, bytes(data)) for address, data in merged]


def main(elf_path: str, out_dir: str) -> int:
    out = Path(out_dir)
    images = runs(load_segments(Path(elf_path).read_bytes()))
    spans = sector_spans()
    protected = {spans[number]: name for name, number in storage_sectors().items()}
    for address, data in images:
        end = address + len(data)
        for (start, stop), name in protected.items():
            if address < stop and start < end:
                sys.exit(f"{elf_path}: 0x{address:08X}-0x{end:08X} overlaps the {name} storage sector "
                         f"0x{start:08X}-0x{stop:08X}; fix stm32f405.ld")
    for stale in [*out.glob(f"{STEM}-0x*.bin"), out / f"{STEM}.bin"]:
        stale.unlink(missing_ok=True)
    for address, data in images:
        end = address + len(data)
        touched = [n for n, (start, stop) in enumerate(spans) if address < stop and start < end]
        name = f"{STEM}-0x{address:08X}.bin"
        (out / name).write_bytes(data)
        print(f"stm32f405 image: 0x{address:08X}-0x{end:08X} {len(data):6d} B  sectors "
              f"{touched[0]}-{touched[-1]}  {name}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1], sys.argv[2]))
