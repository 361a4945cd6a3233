"""`trimeter demo` (`make demo`): the whole instrument on the twin, end to end, in a couple of minutes.

Starts the twin (the real firmware core built for the `sim` port, plant, optics, spectrometer) with an
empty holder, runs the press-button service exactly as `trimeter serve` does, presses the button
(warm-up + calibration), inserts a virtual ink, presses again (capture + fit + results), then prints
α, σt, g at a few wavelengths beside the twin's truth, the timing split (physical vs. host overhead)
and the path of the figure. Its "independent physics:" line says where the twin's observables came from
(trimeter.twin.optics.physics_line): traced by the maps' own tracer and reduced to their I(ρ) model (the
errors include the map's interpolation and Monte Carlo error, not the tracer's or the model's), or, for a
set-up nobody traced, the very map the fit inverts (the errors are the chain's alone).

The host runs as a host with no map files would: the twin starts with the shipped table of that map in
its active slot and the service fits with the table it reads from the instrument (`--map` overrides)."""

from __future__ import annotations

import argparse
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trimeter.errors import DeviceError, InputError, OutputError
from trimeter.inversion.methods import METHODS
from trimeter.paths import data_dir, user_dirs_at

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.formats.device_table import DeviceTable
    from trimeter.sequences.service import Event

SHOW_NM = (450, 500, 550, 600, 650, 700)


def _wait_for(events: queue.Queue[Event], kind: str, timeout_s: float, log: Callable[[Event], None]) -> Event:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            event = events.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            raise DeviceError(f"demo: no '{kind}' from the service within {timeout_s:g} s") from None
        log(event)
        if event.kind == kind:
            return event
        if event.kind == "failed":
            raise DeviceError(f"demo: the service reported: {event.message}")


def demo_dir(out: str | None) -> Path:
    """Where the demo writes: --out, else the user's data directory (never the package or the repository,
    which for an installed package would be site-packages)."""
    return Path(out) if out else data_dir() / "demo"


def run(args: argparse.Namespace) -> None:
    from trimeter.domain import Sample
    from trimeter.formats.device_table import DeviceTable, table_path_for
    from trimeter.sequences.measure import map_for_thickness, prepare_fit

    wall_start = time.monotonic()
    amap = map_for_thickness(args.thickness, args.map)  # the twin's optics (the instrument side) render with it
    if amap.path is None:  # a map made in memory has no file, so no device table beside it
        raise InputError(f"demo: map {amap.name} has no file, so no device table for the twin to carry")
    table_path = table_path_for(amap.path)
    table = DeviceTable.load(table_path) if table_path.is_file() else None  # what the twin's slot holds
    if not args.map:
        if table is None:
            raise InputError(f"demo: map {amap.name} has no device table ({table_path.name}) for the twin to carry; "
                             f"build it with `trimeter map build --stages tlut`, or fit with --map")
        if args.method != "lut":
            raise InputError(f"demo: the instrument's table fits with method lut only; method {args.method} needs "
                             f"the appearance map: give --map {amap.name}")
    # a stale table or model fails now, not after the warm-up
    prepare_fit([Sample(args.thickness, table if table is not None and not args.map else amap)], args.method)
    out = demo_dir(args.out) / time.strftime("%Y%m%dT%H%M%S")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"demo: cannot create {out} ({exc.strerror or exc}); give --out DIR") from None
    print(f"demo: writing into {out}")
    with user_dirs_at(data=out):  # the demo's calibration never touches the user's
        _run_on_the_twin(args, out, amap, table, wall_start)


def _run_on_the_twin(args: argparse.Namespace, out: Path, amap: AppearanceMap, table: DeviceTable | None,
                     wall_start: float) -> None:
    from trimeter.device import Device
    from trimeter.results.figure import plot_parameters
    from trimeter.sequences.service import Service
    from trimeter.sequences.settings import HostSettings
    from trimeter.spectrometer import open_spectrometer
    from trimeter.twin import Twin
    from trimeter.twin.optics import physics_line

    settings = HostSettings()
    settings.set("results_dir", str(out / "results"))
    settings.set("thickness_mm", args.thickness)
    settings.set("method", args.method)
    settings.set("timeout_s", 0.3)
    if args.map:
        settings.set("map", str(amap.path))

    def log(event: Event) -> None:
        print(f"  [{event.kind}] {event.message}", flush=True)

    carried = "no map table" if table is None else f"map table {table.name} (sha256 {table.sha256[:12]}…)"
    fitted_with = f"the map {amap.name} (--map)" if args.map else "the table the instrument carries"
    print(f"demo: twin with '{args.sample}' ℓ = {args.thickness:g} mm and {carried} in its slot, read by its "
          f"{args.sensor}; the host fits with {fitted_with}; time scale {args.time_scale:g}×")
    with Twin(sample=None, thickness_mm=args.thickness, time_scale=args.time_scale, appearance_map=amap,
              state_dir=out / "twin", seed=args.seed,
              map_table=None if table is None else table.to_bytes(), sensor=args.sensor) as twin:
        settings.set("port", twin.modbus_port)
        settings.set("spectrometer", twin.spectrometer_url)
        events: queue.Queue[Event] = queue.Queue()
        service = Service(lambda: Device.open(settings.port, timeout_s=settings.timeout_s),
                          lambda: open_spectrometer(settings.spectrometer), settings, on_event=events.put,
                          device_clock=twin.sim_time, label=args.sample)
        stop = threading.Event()
        thread = threading.Thread(target=service.serve, kwargs={"stop": stop.is_set}, daemon=True)
        thread.start()
        try:
            _wait_for(events, "connected", 30, log)
            print("1. holder empty → press the button: warm-up + calibration")
            twin.control.press_button()
            _wait_for(events, "calibrated", 600, log)
            print(f"2. insert '{args.sample}' → press the button: measurement")
            twin.control.insert_sample(args.sample, args.thickness)
            sim0, wall0 = twin.sim_time(), time.monotonic()
            twin.control.press_button()
            measured = _wait_for(events, "measured", 600, log)
            cycle_wall, cycle_sim = time.monotonic() - wall0, twin.sim_time() - sim0
            truth = twin.control.truth()
            if truth is None:
                raise DeviceError("demo: the twin holds no sample to compare with")
        finally:
            stop.set()
            thread.join(timeout=10)

    params, timing = measured.data["parameters"], measured.data["timing"]
    if args.map:
        print(f"\nfitted with the map {amap.name} (--map)")
    else:
        read = service.last_instrument_table
        print(f"\nfitted with the instrument's map table {read['name']} (sha256 {read['sha256'][:12]}…, slot "
              f"{read['slot']}, {'from the host cache' if read['cached'] else 'read from the device'})")
    print(physics_line(truth.get("physics", "map"), args.sample, amap.name))
    print(f"  source: {truth.get('physics_source') or 'not recorded'}")
    print("α, σt [1/mm], g — measured (± 1σ) beside the twin's truth")
    print(f"{'λ nm':>6} {'α':>16} {'truth':>7} {'σt':>18} {'truth':>7} {'g':>15} {'truth':>6}")
    tw = np.asarray(truth["wavelengths_nm"])
    # a multichannel sensor has fewer bins than SHOW_NM: each bin is printed once
    shown = dict.fromkeys(int(np.argmin(np.abs(params.wavelengths_nm - w))) for w in SHOW_NM)
    for i in shown:
        t = {k: float(np.interp(params.wavelengths_nm[i], tw, np.asarray(truth[k]))) for k in ("alpha", "sigma_t", "g")}
        print(f"{params.wavelengths_nm[i]:6.1f} {params.alpha[i]:8.4f}±{params.alpha_std[i]:<7.4f} {t['alpha']:7.4f} "
              f"{params.sigma_t[i]:9.3f}±{params.sigma_t_std[i]:<8.3f} {t['sigma_t']:7.3f} "
              f"{params.g[i]:7.3f}±{params.g_std[i]:<7.3f} {t['g']:6.3f}")
    valid = np.isfinite(params.alpha)
    truth_on = {k: np.interp(params.wavelengths_nm, tw, np.asarray(truth[k])) for k in ("alpha", "sigma_t", "g")}
    band = valid & (params.wavelengths_nm >= 420) & (params.wavelengths_nm <= 720)
    if band.any():
        print(f"over 420-720 nm ({band.sum()} bins): |Δα| p95 "
              f"{np.nanpercentile(np.abs(params.alpha - truth_on['alpha'])[band], 95):.4f}, "
              f"|Δσt|/σt p95 {np.nanpercentile(np.abs(params.sigma_t / truth_on['sigma_t'] - 1)[band], 95):.2%}, "
              f"|Δg| p95 {np.nanpercentile(np.abs(params.g - truth_on['g'])[band], 95):.3f}")
    clean = band & (params.flags == 0)
    if clean.any():
        from trimeter.bench.uncertainty import coverage

        cover = {k: coverage(getattr(params, k), getattr(params, f"{k}_std"), truth_on[k], clean)
                 for k in ("alpha", "sigma_t", "g")}
        print(f"reported σ against the twin's truth over 420-720 nm ({int(clean.sum())} unflagged bins; a Gaussian "
              f"±1σ/±2σ covers 68 %/95 %): " + ", ".join(f"{label} {cover[k][0]:.0%}/{cover[k][1]:.0%}" for k, label
                                                        in (("alpha", "α"), ("sigma_t", "σt"), ("g", "g"))))
    figure = plot_parameters(out / "demo-vs-truth.png", params,
                             title=f"{args.sample}, ℓ = {args.thickness:g} mm (twin)",
                             truth={"wavelengths_nm": tw,
                                    **{k: np.asarray(truth[k]) for k in ("alpha", "sigma_t", "g")}})
    physical = timing["motion_device_s"] + timing["exposure_s"]
    overhead = timing["wall_s"] - physical / args.time_scale
    print(f"\nmeasurement cycle (press → results written): {cycle_wall:.2f} s wall, "
          f"{cycle_sim:.1f} s on the twin's clock")
    print(f"  sequence: {timing['wall_s']:.2f} s wall = physical {physical:.1f} s device time "
          f"(motion+settling {timing['motion_device_s']:.1f} s, exposures {timing['exposure_s']:.1f} s) / "
          f"{args.time_scale:g} "
          f"+ host & protocol overhead {overhead:.2f} s = {overhead / physical:.1%} of the physical time")
    print(f"  then fit {timing['fit_wall_s'] * 1e3:.0f} ms, results + figure + medium written in "
          f"{timing['write_wall_s']:.2f} s; "
          f"the rest is the button (debounce + polling)")
    print(f"  the sequence made {timing['requests']} Modbus requests ({timing['request_wall_s']:.2f} s inside them, "
          f"most overlapping motion); over a real 19200-baud link (~15 ms each) that is at most "
          f"{timing['requests'] * 0.015:.1f} s")
    print(f"results: {measured.data['path']}")
    print(f"figure:  {measured.data['path'] / 'figure.png'}")
    print(f"figure vs truth: {figure}")
    print(f"demo wall time: {time.monotonic() - wall_start:.1f} s")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="run the whole instrument on the twin, end to end", description=__doc__)
    p.add_argument("--sample", default="cyan-ink", help="virtual material (trimeter sim --list-materials)")
    p.add_argument("--thickness", type=float, default=0.4, help="sample thickness in mm (a map must exist for it)")
    p.add_argument("--map", help="fit with this appearance map (default: the table the twin carries, made from the "
                                 "shipped map of that thickness)")
    p.add_argument("--method", default="lut", choices=METHODS)
    p.add_argument("--time-scale", type=float, default=20.0, help="twin time runs this many times faster")
    p.add_argument("--sensor", default="spectrometer", choices=("spectrometer", "as7341", "c12880ma"),
                   help="the build the twin reads like: the spectrometer's pixels, the AS7341's nine channels "
                        "(fitted band-aware), or the C12880MA micro-spectrometer captured by the firmware (mcu:)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", help="output directory (default: the user data directory's demo/, printed; "
                                 "TRIMETER_DATA_DIR overrides it)")
    p.set_defaults(func=run)
