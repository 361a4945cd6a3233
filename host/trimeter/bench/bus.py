"""`trimeter bench bus`: what sharing one RS-485 bus costs several instruments. On the twin, N instruments
measure at once (one Service each, on its own thread, as `serve` with [[instruments]] runs them) — once on one
shared bus (one port, addresses 1..N) and once each on its own port — against one instrument measuring alone on
the bus, all in the same run. The ratio bus/ports is the bus's own cost; both against the one alone also carry
what N instruments cost the host's CPU (N firmware sims and twins run here too).

    trimeter bench bus [--instruments 3] [--rounds 3] [--time-scale 50] [--json PATH]

A cycle is one measurement (capture + fit + write) of a virtual sample; the median over the rounds is shown.
No button polling runs here (serve's loops poll each instrument's button between jobs, a few requests a second).
"""

from __future__ import annotations

import contextlib
import json
import statistics
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from trimeter.bench._rig import host_dirs
from trimeter.domain import Sample
from trimeter.errors import InputError
from trimeter.sequences.instruments import Lab
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings
from trimeter.twin import Twin
from trimeter.twin.bus import MAX_INSTRUMENTS, TwinBus
from trimeter.twin.storage import table_bytes

SAMPLE = "cyan-ink"
THICKNESS_MM = 0.4


@contextlib.contextmanager
def _lab(root: Path, count: int, *, shared: bool, time_scale: float, seed: int
         ) -> Iterator[tuple[list[Twin], list[Service]]]:
    """N calibrated instruments with the sample in: on one bus (shared) or each on its own port."""
    host = HostSettings()
    table = table_bytes(map_for_thickness(host.thickness_mm).name)
    with contextlib.ExitStack() as stack:
        options: dict[str, Any] = {"time_scale": time_scale, "map_table": table, "sample": None}
        if shared:
            bus = stack.enter_context(TwinBus(count, state_dir=root / "bus", seed=seed, **options))
            twins, ports = bus.twins, [str(bus.modbus_port)] * count
        else:
            twins = [stack.enter_context(Twin(state_dir=root / f"port-{i + 1}", seed=seed + i, **options))
                     for i in range(count)]
            ports = [str(t.modbus_port) for t in twins]
        host.update({"map": map_for_thickness(host.thickness_mm).name, "results_dir": str(root / "results"),
                     "instruments": [{"name": f"i{i + 1}", "port": port, "address": twin.address or 1,
                                      "spectrometer": twin.spectrometer_url}
                                     for i, (port, twin) in enumerate(zip(ports, twins, strict=True))]},
                    source="benchmark")
        lab = Lab(host)
        stack.callback(lab.close)
        lab.check_buses()
        services = [lab.service(instrument, device_clock=twin.sim_time, label="bench")
                    for instrument, twin in zip(lab.instruments, twins, strict=True)]
        for service in services:
            stack.callback(service.close)
        _together([lambda s=s: (s.connect(), s.calibrate()) for s in services])
        for twin in twins:
            twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        yield twins, services


def _together(actions: list) -> list[float]:
    """Run the actions on one thread each, all at once; each one's wall time (the first error raised after all)."""
    times: list[float] = [0.0] * len(actions)
    errors: list[BaseException] = []

    def run(i: int) -> None:
        t0 = time.monotonic()
        try:
            actions[i]()
        except BaseException as exc:  # noqa: BLE001 - re-raised below, after the others finished
            errors.append(exc)
        times[i] = time.monotonic() - t0

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(actions))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    return times


def _measure(service: Service) -> None:
    service.measure([Sample(THICKNESS_MM, map_for_thickness(THICKNESS_MM, service.settings.map or None))])


def _link_counters(service: Service) -> dict:
    stats = getattr(service.device.transport, "stats", None) if service.device is not None else None
    return dict(vars(stats)) if stats is not None else {"bus_wait_s": 0.0, "requests": 0}


def run(args) -> int:
    if not 2 <= args.instruments <= MAX_INSTRUMENTS:
        raise InputError(f"--instruments must be within 2..{MAX_INSTRUMENTS}, got {args.instruments}")
    if not 1 <= args.rounds <= 20:
        raise InputError(f"--rounds must be within 1..20, got {args.rounds}")
    n = args.instruments
    print(f"{n} instruments on the twin (time scale {args.time_scale:g}), {args.rounds} rounds; sample {SAMPLE} "
          f"{THICKNESS_MM:g} mm; wall seconds per measurement (median)", flush=True)
    rows: dict = {}
    with tempfile.TemporaryDirectory(prefix="trimeter-bench-bus-") as tmp:
        root = Path(tmp)
        with host_dirs(root / "shared"), _lab(root / "shared", n, shared=True, time_scale=args.time_scale,
                                              seed=args.seed) as (_, services):
            alone = [_together([lambda: _measure(services[0])])[0] for _ in range(args.rounds)]
            bus = [_together([lambda s=s: _measure(s) for s in services]) for _ in range(args.rounds)]
            links = [_link_counters(s) for s in services]
        with host_dirs(root / "ports"), _lab(root / "ports", n, shared=False, time_scale=args.time_scale,
                                             seed=args.seed) as (_, services):
            ports = [_together([lambda s=s: _measure(s) for s in services]) for _ in range(args.rounds)]
    one = statistics.median(alone)
    for name, rounds in (("on one bus", bus), ("each on its own port", ports)):
        each = statistics.median(t for r in rounds for t in r)
        slowest = statistics.median(max(r) for r in rounds)
        rows[name] = {"cycle_s": round(each, 2), "slowest_s": round(slowest, 2), "x_alone": round(each / one, 2)}
    rows["alone"] = {"cycle_s": round(one, 2)}
    rows["bus_cost"] = round(rows["on one bus"]["cycle_s"] / rows["each on its own port"]["cycle_s"], 2)
    print(f"  one instrument alone on the bus:   {one:6.2f} s")
    for name in ("on one bus", "each on its own port"):
        r = rows[name]
        print(f"  {n} at once, {name + ':':<22} {r['cycle_s']:6.2f} s each (slowest {r['slowest_s']:.2f} s), "
              f"{r['x_alone']:.2f}x alone")
    print(f"  the bus's own cost (one bus / own ports): {rows['bus_cost']:.2f}x")
    print(f"  bus wait per instrument over the run: {[round(link['bus_wait_s'], 2) for link in links]} s; "
          f"requests {[link['requests'] for link in links]}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"instruments": n, "time_scale": args.time_scale, "rows": rows,
                                               "links": links}, indent=1) + "\n")
    return 0


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("bus", help="measurement cycle of N instruments on one bus against one alone "
                                               "(twin)", description=__doc__)
    p.add_argument("--instruments", type=int, default=3, help="how many (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="measurements per setting (default: %(default)s)")
    p.add_argument("--time-scale", type=float, default=50.0, help="twin time scale (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", help="also write the figures as JSON here")
    p.set_defaults(func=run)
