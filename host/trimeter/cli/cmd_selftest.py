"""`trimeter selftest`: check a (freshly built) instrument part by part — homing, each slot, each
shutter and LED (the spectrometer sees it switch), the spectrometer's dark level and exposure range —
and print pass/fail with what to fix. Exit 0 when every check passes, 1 when any fails.
Run it with the holder EMPTY: the optical checks expect the bare backgrounds and beam."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from trimeter.cli._instrument import add_instrument_args, open_device, open_spectrometer, settings_from
from trimeter.sequences.calibrate import previous_calibration
from trimeter.sequences.selftest import FAIL, PASS, SKIP, CheckResult, SelfTestReport, run_selftest

if TYPE_CHECKING:
    from trimeter.device import Device
    from trimeter.domain import Calibration
    from trimeter.spectrometer import Spectrometer

_STYLE = {PASS: ("PASS", "green"), FAIL: ("FAIL", "bold red"), SKIP: ("not judged", "yellow")}


def run(args: argparse.Namespace) -> int:
    settings = settings_from(args)
    device = open_device(settings)
    try:
        spectrometer = open_spectrometer(settings)
        try:
            calibration = previous_calibration(settings)
            report = (run_selftest(device, spectrometer, calibration=calibration) if args.json
                      else _run_with_progress(device, spectrometer, calibration))
        finally:
            spectrometer.close()
    finally:
        device.close()
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        _print_table(report)
    return 0 if report.passed else 1


def _run_with_progress(device: Device, spectrometer: Spectrometer, calibration: Calibration | None
                       ) -> SelfTestReport:
    from rich.console import Console

    console = Console()
    with console.status("selftest: starting") as status:
        def on_result(result: CheckResult, index: int, total: int) -> None:
            label, style = _STYLE[result.status]
            console.print(f"[{style}]{label:>10}[/] {result.name}")
            if index + 1 < total:
                status.update(f"selftest: check {index + 2} of {total}")

        return run_selftest(device, spectrometer, calibration=calibration, on_result=on_result)


def _print_table(report: SelfTestReport) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"trimeter selftest (firmware {report.device['firmware']}, spectrometer "
                        f"{report.spectrometer['model']} {report.spectrometer['serial']})")
    table.add_column("check", no_wrap=True)
    table.add_column("result", no_wrap=True)
    table.add_column("what was seen / what to fix")
    for check in report.checks:
        label, style = _STYLE[check.status]
        message = check.message.removeprefix("not judged: ") if check.status == SKIP else check.message
        table.add_row(check.name, f"[{style}]{label}[/]", message)
    console = Console()
    console.print(table)
    failed = [c.name for c in report.checks if c.status == FAIL]
    skipped = [c.name for c in report.checks if c.status == SKIP]
    if failed:
        console.print(f"[bold red]{len(failed)} of {len(report.checks)} checks failed[/]: {', '.join(failed)}"
                      + (f"; not judged because of them: {', '.join(skipped)}" if skipped else ""))
    else:
        console.print(f"[green]all {len(report.checks)} checks passed[/]"
                      + (f" ([yellow]not judged[/]: {', '.join(skipped)})" if skipped else ""))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("selftest", help="check homing, slots, shutters, LEDs and the spectrometer",
                              description=__doc__)
    add_instrument_args(p)
    p.add_argument("--json", action="store_true", help="print the report as JSON (no progress output)")
    p.set_defaults(func=run)
