"""`trimeter measure [--thickness MM [--thickness MM2]]`: capture the inserted sample (I_b, I_w, I_c),
fit α, σt, g and write a results directory (printed at the end). The fit uses the map table the
instrument carries (its active slot, cached by SHA-256: no map files needed here); `--map` fits with a
map instead. With two thicknesses you are asked to swap the samples in between; both are fitted and
combined (a second thickness the instrument's table is not for uses the shipped map of it)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from trimeter.cli._instrument import add_instrument_args, open_device, open_spectrometer, progress_bar, settings_from
from trimeter.domain.measurement import Estimate
from trimeter.errors import InputError
from trimeter.inversion.methods import METHODS
from trimeter.formats.device_table import DeviceTable
from trimeter.sequences.measure import resolve_samples
from trimeter.sequences.service import Service, calibration_is_stale

SHOW_NM = (450, 550, 650)


def summary(parameters: Estimate, wavelengths: Sequence[float] = SHOW_NM, truth: dict | None = None) -> str:
    lines = [f"{'λ [nm]':>8} {'α':>8} {'σt [1/mm]':>11} {'g':>7}" + ("   truth: α      σt      g" if truth else "")]
    for w in wavelengths:
        i = int(np.argmin(np.abs(parameters.wavelengths_nm - w)))
        row = (f"{parameters.wavelengths_nm[i]:8.1f} {parameters.alpha[i]:8.4f} {parameters.sigma_t[i]:11.4f} "
               f"{parameters.g[i]:7.3f}")
        if truth:
            j = int(np.argmin(np.abs(np.asarray(truth["wavelengths_nm"]) - w)))
            row += f"   {truth['alpha'][j]:9.4f} {truth['sigma_t'][j]:7.3f} {truth['g'][j]:6.3f}"
        lines.append(row)
    return "\n".join(lines)


def describe_fit_model(model: object, instrument: dict) -> str:
    """What a sample is fitted with, for the line that says so: a map, or the instrument's table."""
    if isinstance(model, DeviceTable):
        read = "the cache" if instrument.get("cached") else "the device"
        return (f"the instrument's map table {model.name} (ℓ = {model.thickness_mm:g} mm, slot "
                f"{instrument.get('slot', '?')}, sha256 {model.sha256[:12]}…, from {read} in "
                f"{instrument.get('seconds', 0):.2f} s)")
    name, thickness = getattr(model, "name", "?"), getattr(model, "thickness_mm", float("nan"))
    return f"map {name} (ℓ = {thickness:g} mm)"


def run(args: argparse.Namespace) -> None:
    settings = settings_from(args)
    if args.method:
        settings.set("method", args.method)
    thicknesses = args.thickness or [settings.thickness_mm]
    if len(thicknesses) > 2 or any(not t > 0 or t == float("inf") for t in thicknesses):
        raise InputError("thickness: give one or two positive thicknesses in mm")
    if args.map and len(args.map) != len(thicknesses):
        raise InputError("map: give one --map per --thickness")
    requests = list(zip(thicknesses, args.map or [None] * len(thicknesses), strict=True))
    if args.map:  # a map named on the command line: checked before anything moves
        resolve_samples(requests)
    if args.results:
        settings.set("results_dir", args.results)
    service = Service(lambda: open_device(settings), lambda: open_spectrometer(settings), settings,
                      on_event=lambda e: print(f"warning: {e.message}") if e.kind == "warning" else None)
    service.connect()
    try:
        # without --map the fit uses the table the instrument carries (read, or found in the cache)
        samples = service.resolve_samples(requests)
        source = "--thickness" if args.thickness else "host config thickness_mm"
        for sample in samples:  # never assumed silently
            where = describe_fit_model(sample.map, service.last_instrument_table)
            print(f"thickness: {sample.thickness_mm:g} mm ({source}), {where}")
        reason = calibration_is_stale(service.calibration, service.connected_device().read("uptime_s"),
                                      settings.calibration_max_age_s) or service.calibration_stale_reason
        if reason:
            raise InputError(f"calibration: {reason}; run `trimeter calibrate` with the holder empty")

        def swap(thickness: float) -> None:
            input(f"insert the {thickness:g} mm sample and press Enter ")

        with progress_bar("measurement") as update:
            service.on_progress = update
            path = service.measure(samples, between=swap, label=args.label)
    finally:
        service.close()
    p = service.last_parameters
    assert p is not None  # set by every measure that returns
    print(summary(p))
    for note in service.last_advice:
        print(f"note: {note}")
    print(f"results: {path}")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("measure", help="measure the inserted sample", description=__doc__)
    add_instrument_args(p)
    p.add_argument("--thickness", type=float, action="append", help="sample thickness in mm (twice for two samples)")
    p.add_argument("--map", action="append",
                   help="appearance map per thickness (default: the map table the instrument carries)")
    p.add_argument("--method", choices=METHODS, help="inversion method (default: host config)")
    p.add_argument("--label", help="a name for the results directory")
    p.add_argument("--results", help="results root directory (default: host config / data dir)")
    p.set_defaults(func=run)
