"""`trimeter bench link`: what a noisy Modbus link costs. On the twin, per fault level, a calibration
(holder check, warm-up, calibration) and a measurement of a virtual sample, each timed, with the
transport's and the runner's retries; ratios against the clean link measured in the same run.

    trimeter bench link [--levels 0,0.01,0.02,0.02+0.05] [--time-scale 50] [--seed 1] [--table] [--json PATH]

A level is `CORRUPT[+DROP]`: the probability that a byte has a bit flipped (both ways), and that a
reply is dropped. The host settings are the defaults (`timeout_s`, `attempts`), as `serve` uses them.
`--table` adds a cold read of the instrument's whole map table, as serve's first fit with no map named does
with nothing cached: within its time budget per try, and the service's tries (each going on from the last).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from trimeter.bench._rig import twin_and_service
from trimeter.device.client import MAP_READ_BUDGET_S
from trimeter.domain import Sample
from trimeter.errors import InputError, TrimeterError
from trimeter.paths import user_dirs_at
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.settings import HostSettings
from trimeter.sequences.steps import RetryPolicy
from trimeter.twin import FaultConfig

SAMPLE = "cyan-ink"
THICKNESS_MM = 0.4


def parse_levels(text: str) -> list[tuple[float, float]]:
    levels = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        corrupt, _, drop = item.partition("+")
        try:
            level = (float(corrupt), float(drop or 0.0))
        except ValueError:
            raise InputError(f"--levels: {item!r} is not CORRUPT[+DROP] (e.g. 0.02+0.05)") from None
        FaultConfig(corrupt=level[0], drop=level[1])  # refuses values outside 0..1
        levels.append(level)
    if not levels:
        raise InputError("--levels: no level given")
    return levels


def _link_counts(service) -> dict:
    stats = vars(service.device.transport.stats)
    return {k: stats[k] for k in ("requests", "retries", "garbled_replies", "timeouts", "reconnects", "failures")}


def measure_level(corrupt: float, drop: float, *, time_scale: float, seed: int, table: bool = False) -> dict:
    """One calibration and one measurement at this fault level on a fresh twin (then, with `table`, a cold read
    of the instrument's map table); failures are reported, not raised (they are what the benchmark is about)."""
    row: dict = {"corrupt": corrupt, "drop": drop}
    with twin_and_service(time_scale=time_scale, seed=seed, faults=FaultConfig(corrupt=corrupt, drop=drop)) as (
            twin, service, settings):
        amap = map_for_thickness(THICKNESS_MM, settings.map or None)
        for phase in ("calibrate", "measure", *(("table",) if table else ())):
            t0 = time.monotonic()
            try:
                if service.device is None:
                    service.connect()
                if phase == "calibrate":
                    service.calibrate()
                elif phase == "table":
                    row["table_resumes"] = _cold_table_read(service)
                    row["table_s"] = round(time.monotonic() - t0, 2)
                    continue
                else:
                    twin.control.insert_sample(SAMPLE, THICKNESS_MM)
                    service.measure([Sample(THICKNESS_MM, amap)])
                row[f"{phase}_s"] = round(time.monotonic() - t0, 2)
                timing = service.last_timing
                row[f"{phase}_step_retries"] = timing.get("step_retries", 0)
                row[f"{phase}_retry_wall_s"] = timing.get("retry_wall_s", 0.0)
            except TrimeterError as exc:
                row[f"{phase}_s"] = None
                row[f"{phase}_error"] = f"{exc} ({time.monotonic() - t0:.0f} s)"
                break
        if service.device is not None:
            row["link"] = _link_counts(service)
        row["proxy"] = {k: v for k, v in twin.control.state()["counters"].items()
                        if k in ("requests", "bytes_corrupted", "replies_dropped")}
    return row


def _cold_table_read(service) -> int:
    """Read the instrument's whole map table as serve's first fit does with an empty cache (its tries, each
    going on from the last); the resumes it took within them."""
    stats = service.device.transport.stats
    before = stats.resumed_reads
    with tempfile.TemporaryDirectory(prefix="trimeter-table-cache-") as cache, user_dirs_at(cache=Path(cache)):
        service.instrument_table()
    return stats.resumed_reads - before


def run(args) -> int:
    levels = parse_levels(args.levels)
    rows = []
    host = HostSettings()
    print(f"twin at time scale {args.time_scale:g}; host defaults (timeout {host.timeout_s:g} s + the frames' time on "
          f"the wire, {host.attempts} attempts per request, {RetryPolicy().attempts} tries per step); sample {SAMPLE} "
          f"{THICKNESS_MM:g} mm", flush=True)
    print(f"{'corrupt':>7} {'drop':>5} | {'calibrate s':>11} {'×clean':>6} {'steps↻':>6} | {'measure s':>9} "
          f"{'×clean':>6} {'steps↻':>6} | {'requests':>8} {'req↻':>5} {'garbled':>7} {'timeouts':>8}", flush=True)
    for i, (corrupt, drop) in enumerate(levels):
        row = measure_level(corrupt, drop, time_scale=args.time_scale, seed=args.seed + i, table=args.table)
        rows.append(row)
        base = rows[0]

        def ratio(key, row=row, base=base):
            if row.get(key) is None or not base.get(key):
                return "-"
            return f"{row[key] / base[key]:.1f}"

        link = row.get("link", {})
        print(f"{corrupt:>7.3f} {drop:>5.2f} | {row.get('calibrate_s') or 'FAILED':>11} {ratio('calibrate_s'):>6} "
              f"{row.get('calibrate_step_retries', '-'):>6} | {row.get('measure_s') or 'FAILED':>9} "
              f"{ratio('measure_s'):>6} {row.get('measure_step_retries', '-'):>6} | {link.get('requests', '-'):>8} "
              f"{link.get('retries', '-'):>5} {link.get('garbled_replies', '-'):>7} {link.get('timeouts', '-'):>8}",
              flush=True)
        if row.get("table_s") is not None:
            print(f"        cold table read {row['table_s']:g} s ({ratio('table_s')}× clean, {row['table_resumes']} "
                  f"resumes; budget {MAP_READ_BUDGET_S:g} s a try, {RetryPolicy().attempts} tries)", flush=True)
        for phase in ("calibrate", "measure", "table"):
            if f"{phase}_error" in row:
                print(f"        {phase} failed: {row[f'{phase}_error']}", flush=True)
    print("(×clean: wall time against the first level's; steps↻: steps the runner tried again; req↻: requests "
          "the transport repeated)")
    if args.json:
        Path(args.json).write_text(json.dumps({"time_scale": args.time_scale, "rows": rows}, indent=1) + "\n")
    return 0 if all(r.get("measure_s") is not None and (r.get("table_s") is not None or not args.table)
                    for r in rows) else 1


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("link", help="calibrate/measure wall time on a noisy link (twin)",
                                    description=__doc__)
    p.add_argument("--levels", default="0,0.01,0.02,0.02+0.05", help="CORRUPT[+DROP],… (default: %(default)s)")
    p.add_argument("--time-scale", type=float, default=50.0, help="twin time scale (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1,
                   help="the twin's seed (noise and link faults), +1 per level (default: %(default)s)")
    p.add_argument("--table", action="store_true",
                   help="also time a cold read of the instrument's whole map table per level")
    p.add_argument("--json", help="also write the rows as JSON here")
    p.set_defaults(func=run)
