"""`trimeter bench soak`: the press-button service (`serve`, in-process) on the twin for many cycles,
with stale calibrations, device resets, sample swaps and link faults; every written result is checked
against the twin's truth.

    trimeter bench soak --cycles N [--seed S] [--time-scale 300] [--calibration-max-age 14400] [--json PATH]

A cycle is one press of the twin's button by the simulated operator, who does what the status LED
asks: triple blink → empty the holder and press; after a calibration → insert a sample and press;
after a result → swap in another material and press; fast blink (a failure) → press again. Before
each press the link gets a fault level drawn at random (clean, 1 % or 2 % byte corruption, 2 % with 5 %
dropped replies and a few replies late), and now and then the firmware is reset; calibrations also go
stale by age (`calibration_max_age_s`, device seconds). The twin runs 300× faster than real time by
default: a cycle's device time (moves, settling, exposures, warm-ups) is then a small part of its wall
time, which goes to the host's own work (writing the result, fitting) and to the link's recoveries; the
calibration age limit is in device seconds, so it scales along (14400 s: stale about every 48 s of wall time).

Printed: cycles, results written, calibrations, **garbage** (a written result that is wrong for the
sample that was in: goal 0), failures and refusals with their reasons, RSS of this process over time
(the service and the twin's threads; goal flat).

A result is wrong when, over 420-720 nm, the 95th percentile of |Δα| exceeds ALPHA_TOL, of |Δσt|/σt
SIGMA_T_REL_TOL or of |Δg| G_TOL, or fewer than MIN_FINITE of its bins are finite. The tolerances are
several times the errors of good results on this twin (printed as the worst good errors seen), yet far
below what a wrong calibration, a stale reply taken for a spectrum or the previous sample give: those
miss α or σt by tenths.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trimeter.bench._rig import twin_and_service
from trimeter.errors import InputError

BAND_NM = (420.0, 720.0)
ALPHA_TOL = 0.05
SIGMA_T_REL_TOL = 0.10
G_TOL = 0.15
MIN_FINITE = 0.9
THICKNESS_MM = 0.4
MATERIALS = ("cyan-ink", "magenta-ink", "yellow-ink", "milk")
# (weight, faults) drawn before each press
LINK_LEVELS = ((0.55, dict(corrupt=0.0, drop=0.0, late=0.0)),
               (0.2, dict(corrupt=0.01, drop=0.0, late=0.0)),
               (0.15, dict(corrupt=0.02, drop=0.0, late=0.0)),
               (0.1, dict(corrupt=0.02, drop=0.05, late=0.01, late_delay_s=0.2)))
RESET_PROBABILITY = 0.03
REACTION_TIMEOUT_S = 300.0  # no answer to a press within this (wall): counted as a failure, pressed again


@dataclass
class SoakReport:
    cycles: int = 0
    results: int = 0
    calibrations: int = 0
    garbage: list = field(default_factory=list)       # (cycle, sample, errors)
    checked: list = field(default_factory=list)       # every written result: (cycle, sample, path, errors)
    failures: dict = field(default_factory=dict)      # reason → count
    refusals: dict = field(default_factory=dict)
    resets: int = 0
    worst_good: dict = field(default_factory=lambda: {"alpha": 0.0, "sigma_t_rel": 0.0, "g": 0.0})
    rss_mb: list = field(default_factory=list)        # (cycle, wall_s, MB)
    wall_s: float = 0.0

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items()}


def rss_mb() -> float:
    try:
        import psutil
    except ImportError:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")
    return psutil.Process().memory_info().rss / 2**20


def result_errors(result_dir: Path, truth: dict) -> dict:
    """p95 errors of a written result (its parameters.json) against the twin's truth, over BAND_NM."""
    combined = json.loads((Path(result_dir) / "parameters.json").read_text())["combined"]
    wl = np.asarray(combined["wavelength_nm"], float)
    band = (wl >= BAND_NM[0]) & (wl <= BAND_NM[1])
    got = {k: np.asarray([np.nan if v is None else v for v in combined[k]], float)[band] for k in ("alpha", "sigma_t",
                                                                                                   "g")}
    want = {k: np.interp(wl[band], truth["wavelengths_nm"], truth[k]) for k in ("alpha", "sigma_t", "g")}
    finite = np.isfinite(got["alpha"]) & np.isfinite(got["sigma_t"]) & np.isfinite(got["g"])
    if not finite.any():
        return {"finite": 0.0, "alpha": np.inf, "sigma_t_rel": np.inf, "g": np.inf}
    return {"finite": float(finite.mean()),
            "alpha": float(np.percentile(np.abs(got["alpha"] - want["alpha"])[finite], 95)),
            "sigma_t_rel": float(np.percentile((np.abs(got["sigma_t"] - want["sigma_t"]) / want["sigma_t"])[finite],
                                               95)),
            "g": float(np.percentile(np.abs(got["g"] - want["g"])[finite], 95))}


def is_garbage(errors: dict) -> bool:
    return (errors["finite"] < MIN_FINITE or errors["alpha"] > ALPHA_TOL or errors["sigma_t_rel"] > SIGMA_T_REL_TOL
            or errors["g"] > G_TOL)


class Operator:
    """What a person at the instrument does; the only part that touches the sample and the button."""

    def __init__(self, twin, rng: np.random.Generator):
        self.twin, self.rng = twin, rng
        self.sample: str | None = None

    def empty_holder_and_press(self) -> None:
        self.twin.control.remove_sample()
        self.sample = None
        self.twin.control.press_button()

    def insert_sample_and_press(self) -> dict:
        """Swaps in a random material; returns the truth of what is now in the holder."""
        self.sample = str(self.rng.choice(MATERIALS))
        self.twin.control.insert_sample(self.sample, THICKNESS_MM)
        truth = self.twin.control.truth()
        self.twin.control.press_button()
        return truth

    def press_again(self) -> None:
        self.twin.control.press_button()


def _reason(message: str) -> str:
    """A failure message without its numbers and paths, so equal causes are counted together."""
    import re

    text = re.sub(r"/\S+", "PATH", message)
    text = re.sub(r"\b[0-9a-f]{2}( [0-9a-f]{2})+\b", "BYTES", text)
    text = re.sub(r"-?\d+(\.\d+)?", "N", text)
    return text[:160]


def run_soak(cycles: int, *, seed: int = 0, time_scale: float = 300.0, calibration_max_age_s: float = 14400.0,
             progress=lambda line: print(line, flush=True), root: Path | None = None,
             device_table: bool = False, link_levels=LINK_LEVELS) -> SoakReport:
    """`root`: where the twin's state, the calibration and the results go (default: a temporary directory).
    `device_table`: the host names no map, so every fit uses the table read from the instrument (serve's
    default configuration) over the same faulty link. `link_levels`: (weight, faults) pairs drawn before
    each press (a clean link only checks the harness itself, whatever the machine's load)."""
    if cycles < 1:
        raise InputError(f"--cycles must be ≥ 1, got {cycles}")
    rng = np.random.default_rng(seed)
    events: queue.Queue = queue.Queue()
    report = SoakReport()
    started = time.monotonic()
    settings: dict[str, object] = {"calibration_max_age_s": calibration_max_age_s}
    if device_table:
        settings["map"] = ""
    with twin_and_service(time_scale=time_scale, seed=seed, settings=settings, on_event=events.put, root=root) as (
            twin, service, _):
        operator = Operator(twin, rng)
        stop = threading.Event()
        server = threading.Thread(target=service.serve, kwargs=dict(stop=stop.is_set, poll_s=0.02, reconnect_s=0.2),
                                  name="soak-serve", daemon=True)
        server.start()
        try:
            _operate(cycles, twin, operator, events, report, rng, link_levels, progress, started)
        finally:
            stop.set()
            server.join(timeout=30)
    report.wall_s = round(time.monotonic() - started, 1)
    return report


def _operate(cycles, twin, operator, events, report, rng, link_levels, progress, started) -> None:
    weights = np.array([w for w, _ in link_levels], float)
    truth = None
    next_action = "wait"  # the service asks first (no calibration yet → triple blink)
    checkpoint = max(1, min(10, cycles // 10))  # RSS every 10 cycles at most: a jump is placed to within 10
    while report.cycles < cycles:
        if next_action != "wait":
            level = link_levels[rng.choice(len(link_levels), p=weights / weights.sum())][1]
            twin.control.set_fault(**level)
            if rng.random() < RESET_PROBABILITY:
                twin.control.reset_firmware()
                report.resets += 1
                next_action = "wait"  # the service will see the reset and ask for an empty holder
            else:
                report.cycles += 1
                if next_action == "empty":
                    operator.empty_holder_and_press()
                elif next_action == "sample":
                    truth = operator.insert_sample_and_press()
                else:
                    operator.press_again()
                if report.cycles % checkpoint == 0 or report.cycles == cycles:
                    wall, mb = round(time.monotonic() - started, 1), round(rss_mb(), 1)
                    report.rss_mb.append((report.cycles, wall, mb))
                    progress(f"cycle {report.cycles:>5}  {wall:>7.0f} s  RSS {mb:7.1f} MB  results {report.results:>4} "
                             f"garbage {len(report.garbage)}  "
                             f"failures {sum(report.failures.values())}  refusals {sum(report.refusals.values())}")
        try:
            event = events.get(timeout=REACTION_TIMEOUT_S)
        except queue.Empty:
            report.failures["no reaction to a press"] = report.failures.get("no reaction to a press", 0) + 1
            next_action = "again"
            continue
        next_action = _react(event, report, truth, operator)


def _react(event, report: SoakReport, truth, operator) -> str:
    """What the operator does next after this event ('wait': nothing, a later event decides)."""
    kind = event.kind
    if kind == "empty_holder":
        return "empty"
    if kind == "calibrated":
        report.calibrations += 1
        return "sample"
    if kind == "measured":
        report.results += 1
        errors = result_errors(event.data["path"], truth)
        report.checked.append((report.cycles, operator.sample, str(event.data["path"]), errors))
        if is_garbage(errors):
            report.garbage.append((report.cycles, operator.sample, errors))
        else:
            for key in report.worst_good:
                report.worst_good[key] = max(report.worst_good[key], round(errors[key], 4))
        return "sample"
    if kind == "refused":
        reason = _reason(event.message)
        report.refusals[reason] = report.refusals.get(reason, 0) + 1
        return "wait"  # the service asks again (triple blink) or is ready: its next event says
    if kind == "failed":
        reason = _reason(event.message)
        report.failures[reason] = report.failures.get(reason, 0) + 1
        time.sleep(0.5)  # let a reconnect settle, so the press is not lost in it
        return "again" if operator.sample is not None else "empty"
    return "wait"  # connected, press, calibrating, warmed_up, reset, reconnecting, advice, warning …


def print_report(report: SoakReport) -> None:
    print(f"cycles {report.cycles}   results {report.results}   calibrations {report.calibrations}   "
          f"firmware resets {report.resets}   wall {report.wall_s:.0f} s")
    print(f"garbage results: {len(report.garbage)}   (goal 0; wrong = p95 |Δα| > {ALPHA_TOL}, |Δσt|/σt > "
          f"{SIGMA_T_REL_TOL}, |Δg| > {G_TOL} over {BAND_NM[0]:.0f}-{BAND_NM[1]:.0f} nm, or < {MIN_FINITE:.0%} "
          "finite bins)")
    for cycle, sample, errors in report.garbage:
        print(f"  cycle {cycle}: {sample}: " + ", ".join(f"{k} {v:.3g}" for k, v in errors.items()))
    print("worst good result: " + ", ".join(f"{k} {v:.3g}" for k, v in report.worst_good.items()))
    for title, counts in (("failures", report.failures), ("refusals", report.refusals)):
        print(f"{title}: {sum(counts.values())}")
        for reason, count in sorted(counts.items(), key=lambda item: -item[1]):
            print(f"  {count:>4} × {reason}")
    print("RSS over time (cycle, wall s, MB): " + "  ".join(f"{c}:{t:.0f}s:{m:.1f}" for c, t, m in report.rss_mb))
    if len(report.rss_mb) >= 3:  # the first checkpoint comes before the first fit has loaded the maps
        (c0, _, first), (c1, _, last) = report.rss_mb[1], report.rss_mb[-1]
        print(f"RSS growth from cycle {c0} to cycle {c1}: {last - first:+.1f} MB")


def run(args) -> int:
    report = run_soak(args.cycles, seed=args.seed, time_scale=args.time_scale,
                      calibration_max_age_s=args.calibration_max_age, device_table=args.device_table)
    print_report(report)
    if args.json:
        Path(args.json).write_text(json.dumps(report.to_dict(), indent=1, default=str) + "\n")
    return 0 if not report.garbage else 1


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("soak", help="serve on the twin for many cycles, results checked against truth",
                                    description=__doc__)
    p.add_argument("--cycles", type=int, default=50, help="operator presses (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time-scale", type=float, default=300.0, help="twin time scale (default: %(default)s)")
    p.add_argument("--calibration-max-age", type=float, default=14400.0,
                   help="calibration_max_age_s for the service, device seconds (default: %(default)s)")
    p.add_argument("--device-table", action="store_true",
                   help="fit with the table read from the instrument (serve's default, no map named)")
    p.add_argument("--json", help="also write the report as JSON here")
    p.set_defaults(func=run)
