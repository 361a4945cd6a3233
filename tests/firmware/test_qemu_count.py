"""`make -C firmware qemu-count`: instructions per call on a Cortex-M4 under QEMU (firmware/qemu/).

The span counter is checked on a hand-made exec log, and the whole harness on the real driver: every
measurement is reported, and the counts are what the code must take (a table-driven CRC-32 costs a
handful of instructions per byte; a counter that saw translation blocks instead of instructions, or
missed the markers, lands far outside). Skipped without QEMU or the ARM toolchain."""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# stdout holds the recipe's output alone, also where pytest runs under make (a sub-make names its directories)
COUNT = ["make", "-s", "--no-print-directory", "-C", str(ROOT / "firmware"), "qemu-count"]
COUNT_PY = ROOT / "firmware" / "qemu" / "count.py"


def _own_build(tmp_path) -> list[str]:
    """count.elf built in the test's own directory: firmware/build/qemu is one path for every caller, and another
    count running beside this one (a second pytest worker, `trimeter bench report`) would rebuild it under us."""
    return [f"COUNT_BUILD={tmp_path / 'qemu'}"]


def _count_module():
    spec = importlib.util.spec_from_file_location("qemu_count", COUNT_PY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_spans_count_the_instructions_between_each_pair_of_markers(tmp_path):
    begin, end = 0x08000100, 0x08000104
    pcs = [0x0800_0200, begin, 0x0800_0300, 0x0800_0302, end, 0x0800_0400, begin, end, begin, 0x0800_0500]
    lines = [f"Trace 0: 0x7f00 [00000000/{pc:08x}/00000000/ff200000] \n" for pc in pcs]
    lines.insert(3, "Stopped execution of TB chain before 0x7f00 [08000300]\n")  # not an instruction
    log = tmp_path / "exec.log"
    log.write_text("".join(lines))
    # the last begin has no end (the program stopped): not a measurement
    assert _count_module().spans(log, begin, end) == [2, 0]


@pytest.mark.skipif(shutil.which("qemu-system-arm") is None or shutil.which("arm-none-eabi-gcc") is None,
                    reason="needs qemu-system-arm and gcc-arm-none-eabi")
def test_qemu_count_reports_every_measurement_with_plausible_counts(tmp_path):
    run = subprocess.run([*COUNT, *_own_build(tmp_path)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    counts = {m.group(1).strip(): int(m.group(2))
              for m in re.finditer(r"^  (.+?)\s{2,}(\d+)", run.stdout, re.MULTILINE)}
    assert set(counts) >= {"crc16_modbus, 256 B", "crc32_update, 1024 B", "mb_handle_adu, FC03 read of 10 registers",
                           "map_table_check, header"}, run.stdout
    assert 4 * 1024 <= counts["crc32_update, 1024 B"] <= 16 * 1024
    assert 4 * 256 <= counts["crc16_modbus, 256 B"] <= 16 * 256
    assert 100 < counts["mb_handle_adu, FC03 read of 10 registers"] < counts["crc32_update, 1024 B"]


@pytest.mark.skipif(shutil.which("qemu-system-arm") is None or shutil.which("arm-none-eabi-gcc") is None,
                    reason="needs qemu-system-arm and gcc-arm-none-eabi")
def test_qemu_count_counts_the_inverse_core_per_bin_with_a_device_table(tmp_path):
    """With COUNT_TABLE (the l0.4 map's format-2 table), tr_fit_bins too: the table check per call and
    a spread of single bins, each a Newton polish on the compact model (tens of thousands of instructions:
    a few model evaluations of a few thousand each; far fewer would mean the fit did not run)."""
    from trimeter.formats.appearance import AppearanceMap, find_map

    spec = importlib.util.spec_from_file_location("device_table_tool", ROOT / "tools" / "device_table_study.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    table = tool.build(AppearanceMap.load(find_map("device-n1.5-l0.4"))).save(tmp_path / "l04.tlut")
    run = subprocess.run([*COUNT, f"COUNT_TABLE={table}",
                          *_own_build(tmp_path)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    check = re.search(r"^  tr_fit_bins, table check \(n = 0\)\s+(\d+)", run.stdout, re.MULTILINE)
    per_bin = re.search(r"^  tr_fit_bins, 1 bin\s+(\d+) \(min (\d+), max (\d+), (\d+) calls\)", run.stdout,
                        re.MULTILINE)
    assert check and per_bin, run.stdout
    assert 500 < int(check.group(1)) < 20_000
    mean, low, high, calls = (int(x) for x in per_bin.groups())
    assert calls == 8 and 5_000 < low <= mean <= high < 200_000, run.stdout
    # the same 8 bins in one call: the table checked once, the fits as one per call
    together = re.search(r"^  tr_fit_bins, the 8 bins in one call\s+(\d+)", run.stdout, re.MULTILINE)
    assert together, run.stdout
    separately = 8 * (mean - int(check.group(1))) + int(check.group(1))
    assert abs(int(together.group(1)) - separately) < 0.02 * separately, run.stdout


@pytest.mark.skipif(shutil.which("qemu-system-arm") is None or shutil.which("arm-none-eabi-gcc") is None,
                    reason="needs qemu-system-arm and gcc-arm-none-eabi")
def test_qemu_count_as_json_holds_the_table_s_counts(tmp_path):
    """COUNT_ARGS=--json (what `trimeter bench report` reads): the same counts as the table, one object."""
    import json

    def count(*extra):
        run = subprocess.run([*COUNT, *extra, *_own_build(tmp_path)],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        return run.stdout

    text = count()
    counts = json.loads(count("COUNT_ARGS=--json").splitlines()[-1])
    shown = {m.group(1).strip(): int(m.group(2)) for m in re.finditer(r"^  (.+?)\s{2,}(\d+)", text, re.MULTILINE)}
    assert shown and {k: round(v["mean"]) for k, v in counts["instructions"].items()} == shown
    assert counts["mhz"] == 168 and counts["cycles_per_instruction"] == [1.0, 1.5]
