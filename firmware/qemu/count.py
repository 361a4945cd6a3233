#!/usr/bin/env python3
"""Instructions per call on a Cortex-M4, counted under QEMU (see count.c).

    python3 count.py build/qemu/count.elf [--qemu qemu-system-arm] [--nm arm-none-eabi-nm] [--mhz 168] [--json]

QEMU runs the driver one guest instruction per translation block (-singlestep) with every executed
block logged (-d exec,nochain), so the log lines between count_begin's and count_end's first instruction
are the instructions executed in between; the driver's first measurement (nothing between the markers)
is subtracted from the others. The time at the given clock is an estimate: a Cortex-M4 retires about one
instruction per cycle, more with flash wait states and FPU divides; the range printed assumes 1.0-1.5
cycles per instruction.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

TRACE = re.compile(rb"^Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/")


def symbol_addresses(elf: Path, nm: str, names: tuple[str, ...]) -> dict[str, int]:
    out = subprocess.run([nm, str(elf)], check=True, capture_output=True, text=True).stdout
    found = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] in names:
            found[parts[2]] = int(parts[0], 16) & ~1  # Thumb: the symbol's bit 0 is not part of the address
    missing = [n for n in names if n not in found]
    if missing:
        raise SystemExit(f"count.py: {elf} has no symbol {', '.join(missing)}")
    return found


def spans(log: Path, begin: int, end: int) -> list[int]:
    """Instructions executed between each count_begin entry and the next count_end entry."""
    counts, inside, n = [], False, 0
    with log.open("rb") as f:
        for line in f:
            m = TRACE.match(line)
            if not m:
                continue
            pc = int(m.group(1), 16)
            if pc == begin:
                inside, n = True, 0
            elif pc == end and inside:
                counts.append(n)
                inside = False
            elif inside:
                n += 1
    return counts


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("elf", type=Path)
    ap.add_argument("--qemu", default="qemu-system-arm")
    ap.add_argument("--nm", default="arm-none-eabi-nm")
    ap.add_argument("--mhz", type=float, default=168.0)
    ap.add_argument("--timeout-s", type=float, default=300.0)
    ap.add_argument("--json", action="store_true", help="print the counts as one JSON object instead of a table")
    args = ap.parse_args()
    marks = symbol_addresses(args.elf, args.nm, ("count_begin", "count_end"))
    with tempfile.TemporaryDirectory(prefix="qemu-count-") as tmp:
        log, said = Path(tmp) / "exec.log", Path(tmp) / "labels.txt"
        try:
            run = subprocess.run(
                [args.qemu, "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-serial", "null",
                 "-chardev", f"file,id=labels,path={said}", "-semihosting-config",
                 "enable=on,target=native,chardev=labels", "-singlestep", "-d", "exec,nochain",
                 "-D", str(log), "-kernel", str(args.elf)],
                capture_output=True, text=True, timeout=args.timeout_s)
        except subprocess.TimeoutExpired:
            print(f"count.py: QEMU did not finish within {args.timeout_s:g} s", file=sys.stderr)
            return 1
        labels = [line for line in said.read_text().splitlines() if line.strip()] if said.exists() else []
        if run.returncode != 0 or not labels:
            print(f"count.py: QEMU exited {run.returncode}: {run.stderr.strip()[-500:]}", file=sys.stderr)
            return 1
        counts = spans(log, marks["count_begin"], marks["count_end"])
    if len(counts) != len(labels) or labels[0] != "baseline":
        print(f"count.py: {len(labels)} labels but {len(counts)} measured spans", file=sys.stderr)
        return 1
    base = counts[0]
    seen: dict[str, list[int]] = {}
    for label, n in zip(labels[1:], counts[1:], strict=True):
        seen.setdefault(label, []).append(n - base)
    if args.json:
        print(json.dumps({"machine": "netduinoplus2", "mhz": args.mhz, "cycles_per_instruction": [1.0, 1.5],
                          "markers_subtracted": base,
                          "instructions": {label: {"mean": sum(v) / len(v), "min": min(v), "max": max(v),
                                                   "calls": len(v)} for label, v in seen.items()}}))
        return 0
    print(f"instructions per call, Cortex-M4 under QEMU netduinoplus2 (markers' {base} subtracted); "
          f"time at {args.mhz:g} MHz for 1.0-1.5 cycles per instruction")
    for label, values in seen.items():
        lo, hi, mean = min(values), max(values), sum(values) / len(values)
        us = (mean / args.mhz, 1.5 * mean / args.mhz)
        spread = f" (min {lo}, max {hi}, {len(values)} calls)" if len(values) > 1 else ""
        print(f"  {label:<44} {mean:>9.0f}{spread}   {us[0]:.1f}-{us[1]:.1f} us")
    for label, values in seen.items():  # a call fitting several bins: what one bin costs in it
        several = re.search(r"(\d+) bins", label)
        if several:
            n = int(several.group(1))
            print(f"  per bin in '{label}': {sum(values) / len(values) / n:,.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
