"""`trimeter calibrate`: warm the lamps up and measure the three references with the holder EMPTY
(paper Sec. 4.2). The calibration is stored in the host's data directory and used by `measure`.

A quick look first refuses a sample in the holder or swapped slots (before the warm-up); the result is
checked against physical bounds and against the previous good calibration of this instrument and
spectrometer (lamp spectra, ρ_black). After replacing a lamp, `--force` accepts a calibration that
disagrees with the previous one (the physical bounds still apply)."""

from __future__ import annotations

import argparse
import numpy as np

from trimeter.cli._instrument import add_instrument_args, open_device, open_spectrometer, progress_bar, settings_from
from trimeter.sequences.service import Service


def run(args: argparse.Namespace) -> None:
    settings = settings_from(args)
    service = Service(lambda: open_device(settings), lambda: open_spectrometer(settings), settings,
                      on_event=lambda e: print(e.message) if e.kind not in ("connected",) else None)
    service.connect()
    try:
        with progress_bar("calibration") as update:
            service.on_progress = update
            cal = service.calibrate(warm=not args.no_warm_up, force=args.force)
    finally:
        service.close()
    ok = cal.flags == 0
    print(f"calibration: {ok.sum()}/{len(ok)} usable bins, "
          f"{cal.wavelengths_nm[0]:.0f}-{cal.wavelengths_nm[-1]:.0f} nm, "
          f"ρ_black median {np.nanmedian(cal.rho_black):.3f}; saved in {settings.calibration_path}")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("calibrate", help="warm up and calibrate (holder empty)", description=__doc__)
    add_instrument_args(p)
    p.add_argument("--no-warm-up", action="store_true", help="skip the warm-up (lamps already stable)")
    p.add_argument("--force", action="store_true",
                   help="accept a calibration that disagrees with the previous good one (e.g. after replacing a lamp)")
    p.set_defaults(func=run)
