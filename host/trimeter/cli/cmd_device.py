"""The instrument on its own: `trimeter device standalone MODE` makes a press of its button measure with no
host attached (calibrate: the next press, holder empty, calibrates; then each press captures, fits on the
device with its map table and keeps the result); `trimeter device last-result` reads that result later
into a results directory, as `trimeter measure` writes one."""

from __future__ import annotations

import argparse

from trimeter import registers as regs
from trimeter.cli._instrument import add_instrument_args, open_device, settings_from
from trimeter.errors import InputError


def cmd_standalone(args: argparse.Namespace) -> int:
    from trimeter.sequences.standalone import calibration_refusal

    try:
        mode = regs.StandaloneMode[args.mode.upper()]
    except KeyError:
        raise InputError(f"standalone mode: one of {', '.join(m.name.lower() for m in regs.StandaloneMode)}, "
                         f"got {args.mode!r}") from None
    if args.force:
        if mode != regs.StandaloneMode.CALIBRATE:
            raise InputError("--force applies to `calibrate` only")
        mode = regs.StandaloneMode.CALIBRATE_FORCE
    with open_device(settings_from(args)) as device:
        device.write("standalone_mode", mode)
        values = device.read_many("standalone_status", "standalone_calibrated", "standalone_warmup_remaining_s",
                                  "standalone_check", "standalone_check_value")
    print(f"standalone mode {mode.name.lower()}; last press: {values['standalone_status'].name.lower()}; "
          f"{'calibrated' if values['standalone_calibrated'] else 'not calibrated'} since the device started")
    if values["standalone_status"] == regs.StandaloneStatus.CALIBRATION_REFUSED:
        print(f"the last calibration press was refused: "
              f"{calibration_refusal(values['standalone_check'], values['standalone_check_value'])}")
    if mode != regs.StandaloneMode.OFF and values["standalone_warmup_remaining_s"]:
        print(f"the lamps are on and warming up: a press waits {values['standalone_warmup_remaining_s']} s more "
              "(LED slow blink) before it captures")
    if mode in (regs.StandaloneMode.CALIBRATE, regs.StandaloneMode.CALIBRATE_FORCE):
        print("empty the holder and press the button: the device checks the holder is empty and calibrates (LED on "
              "when done; triple blink: refused, empty the holder and press again), then each press measures")
        if mode == regs.StandaloneMode.CALIBRATE_FORCE:
            print("--force: the device's calibration since it started is not compared (a lamp replaced since); the "
                  "empty-holder bounds still apply")
    return 0


def cmd_last_result(args: argparse.Namespace) -> int:
    from trimeter.results.writer import write_measurement
    from trimeter.sequences.standalone import read_standalone, recalibrate_advice

    settings = settings_from(args)
    with open_device(settings) as device:
        measurement, result = read_standalone(device)
    out = write_measurement(args.out or settings.results_path, measurement, label=args.label,
                            figure=not args.no_figure)
    table = measurement.samples[0].map
    print(f"standalone press #{result.sequence}: {result.status.name.lower()}, {len(result.bins)} bins, "
          f"{result.flagged_bins} lit bins flagged; fitted on the device with its table {table.name} "
          f"(ℓ = {result.thickness_mm:g} mm), no host attached")
    print(f"results: {out}")
    advice = recalibrate_advice(result)
    if advice:
        print(advice)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("device", help="the instrument on its own: standalone presses and their results",
                                   description=__doc__)
    sub = parser.add_subparsers(dest="device_command", metavar="SUBCOMMAND")
    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])
    p = sub.add_parser("standalone", help="what a press of the button does: off (the host's), calibrate, measure")
    p.add_argument("mode", help="off, calibrate or measure")
    p.add_argument("--force", action="store_true",
                   help="with calibrate: accept a lamp changed since the device's last calibration (not a sample in "
                        "the holder: the empty-holder bounds still apply)")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_standalone)
    p = sub.add_parser("last-result", help="read the last standalone measurement into a results directory")
    p.add_argument("--out", help="results root (default: host setting results_dir)")
    p.add_argument("--label", help="suffix of the results directory's name")
    p.add_argument("--no-figure", action="store_true", help="skip figure.png")
    add_instrument_args(p, spectrometer=False)
    p.set_defaults(func=cmd_last_result)
