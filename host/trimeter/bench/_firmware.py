"""The firmware's fit measured off the device, from the repository's sources: the inversion kernel compiled
in the MCU's single precision for this host (its answers), and the fit's instructions on a Cortex-M4
counted under QEMU (its time, an estimate). Neither is a run on a real board."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from trimeter.errors import BuildError
from trimeter.paths import FIT_CORE_DIR, REPO_ROOT

FIRMWARE_DIR = REPO_ROOT / "firmware"
NATIVE_DIR = REPO_ROOT / "host" / "trimeter" / "inversion" / "native"
# firmware/qemu/count.c's label for a call as the device makes it (core/fit.c's fit_poll: FIT_BINS_PER_POLL bins)
COUNT_LABEL = "tr_fit_bins, one fit_poll's 4 bins"
COUNT_BINS_PER_CALL = 4


def single_precision_library(out_dir: Path) -> Path:
    """The kernel's C sources compiled with -DTR_SINGLE (float arithmetic, as the firmware links them) into a
    library `native.TableFitter(..., library=)` loads."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise BuildError("no C compiler (cc or gcc) to build the single-precision kernel")
    own, shared = sorted(NATIVE_DIR.glob("*.c")), sorted(FIT_CORE_DIR.glob("*.c"))
    if not own or not shared:
        raise BuildError(f"the kernel's sources ({NATIVE_DIR}) or the inverse core's ({FIT_CORE_DIR}) are "
                         f"missing: this needs the repository, not an installed package")
    sources = [str(p) for p in own + shared]
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / "libtrimeter_invert_single.so"
    done = subprocess.run([cc, "-O2", "-std=c11", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC", "-DTR_SINGLE",
                           f"-I{FIT_CORE_DIR}", "-o", str(out), *sources, "-lm"], capture_output=True, text=True)
    if done.returncode != 0:
        raise BuildError(f"compiling the single-precision kernel failed: {done.stderr.strip()[-500:]}")
    return out


def qemu_instruction_counts(table: Path, timeout_s: float = 300.0) -> dict[str, Any]:
    """`make -C firmware qemu-count` with this table: instructions per call on a Cortex-M4 under QEMU
    (firmware/qemu/count.py's JSON: per label mean, min, max, calls; the clock and cycles per instruction
    its time estimate assumes)."""
    if shutil.which("make") is None or not (FIRMWARE_DIR / "qemu" / "count.py").is_file():
        raise BuildError(f"counting needs make and the repository's firmware/ ({FIRMWARE_DIR})")
    # count.elf built in a directory of this run's own: firmware/build/qemu is shared by every count, and one
    # running beside this one (a `make qemu-count`, the test suite's other worker) would rebuild it under this one
    try:
        with tempfile.TemporaryDirectory(prefix="trimeter-qemu-count-") as build:
            done = subprocess.run(["make", "-s", "-C", str(FIRMWARE_DIR), "qemu-count",
                                   f"COUNT_TABLE={table.resolve()}", "COUNT_ARGS=--json", f"COUNT_BUILD={build}"],
                                  capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise BuildError(f"the QEMU count did not finish within {timeout_s:g} s") from None
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        said = (done.stderr or done.stdout).strip()[-500:]
        raise BuildError(f"the QEMU count failed (exit {done.returncode}): {said}")
    counts: dict[str, Any] = json.loads(lines[-1])
    if COUNT_LABEL not in counts["instructions"]:
        raise BuildError(f"the QEMU count has no '{COUNT_LABEL}' (was the firmware built without the fit core?)")
    return counts
