"""`trimeter bench report`: the accuracy, speed and uncertainty benches at a size that fits in minutes, written
as docs/validation.md with its tables and plots (docs/img/validation/*.png), stamped with the commit, the date
and the machine. The page is generated: edit this module, not the page.

What it runs, each through the bench's own code (their figures are theirs; this module only arranges them):
- `bench fit` (trimeter.bench.fit.measure): every inversion method on each shipped map's held-out set,
  noise-free and with relative noise, time per 1024 bins and α / σt / g error;
- `bench table-fit` (trimeter.bench.table_fit.measure): the fit from the device table alone, in double
  precision (`trimeter fit --table`), refined at load (`--refine`), and in the firmware's single precision
  built for this host; the device's time from an instruction count under QEMU (trimeter.bench._firmware);
- `bench uncertainty` (trimeter.bench.uncertainty.measure): coverage of the reported ±1σ / ±2σ;
- `bench sensor` (trimeter.bench.sensor.measure): every build's accuracy (each spectrometer and sensor, each fit
  of its readings) on the twin's materials at the thinner sample, noise-free and with noise;
- `bench tracer-check` (trimeter.bench.tracer_check.check) at a small size (`--tracer-materials 0`: not run);
- `bench polarisation` (trimeter.bench.polarisation.measure): what unpolarised Fresnel leaves out
  (`--polarisation-spp 0`: not run).
The benches' own output goes to --work (logs and JSON), the page, its figures and every figure as JSON
(validation.json, with the page's stamp: what tools/gen_hardware.py quotes in the BOM) to --docs.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import time
from collections.abc import Iterator, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.atomic import atomic_output, atomic_write
from trimeter.errors import BuildError, InputError
from trimeter.paths import REPO_ROOT

PAGE = "validation.md"
FIGURES_JSON = "validation.json"  # beside the page: its figures and stamp, machine-readable
BUILDS_SECTION = "Each build"  # the page's heading that hardware/bom.md links to
BUILDS_THICKNESS_MM = 0.4  # the thinner sample, as the demo and the twin use
IMG_DIR = "img/validation"  # under --docs; the page links its figures relative to itself
HEADLINE_MAP = "device-n1.5-l0.4"  # the instrument's thinner sample: the map the demo and the twin use
DEVICE_LABEL = "on the device (firmware's C, single precision)"
# bench fit's variants shown in the headline, by the name a reader knows them by
FIT_METHODS = {"paper": "paper", "paper-median": "paper, ε-median", "lut p≤8": "lut", "mlp p0": "mlp network alone",
               "mlp p≤8": "mlp"}
TABLE_METHODS = {"table alone, C, double": "table alone (C, double)",
                 "table alone, refined at load (--refine)": "table alone, refined at load"}
WHAT = {
    "paper": "the paper's method: linear interpolation over the map's nodes (scipy Delaunay), per (ρ_b, ρ_w)",
    "paper, ε-median": "the paper's method with its ε-median over 250 perturbed inputs per bin",
    "lut": "the default: the inverse table's first guess, then up to 8 Newton steps on the refined map (C kernel)",
    "mlp network alone": "the `.onnx` network's guess, no polish",
    "mlp": "the network's guess, then up to 8 Newton steps (as lut)",
    "table alone (C, double)": "`trimeter fit --table`: the device table (.tlut) alone, the firmware's C fit in "
                               "double precision",
    "table alone, refined at load": "`trimeter fit --table --refine`: the table's model sampled onto the refined "
                                    "grid at load",
    DEVICE_LABEL: "the same table fit compiled in single precision, as the firmware links it; time: instructions "
                  "counted on a Cortex-M4 under QEMU at 168 MHz, 1.0–1.5 cycles each (an estimate)",
}


def register(bench_subparsers: argparse._SubParsersAction) -> None:
    p = bench_subparsers.add_parser("report", help="run the accuracy, speed and uncertainty benches and write "
                                                   "docs/validation.md with its figures",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--docs", type=Path, default=REPO_ROOT / "docs",
                   help=f"where {PAGE} and {IMG_DIR}/ are written (default: the repository's docs/)")
    p.add_argument("--work", type=Path, default=Path("out/bench-report"), help="the benches' own logs and JSON")
    p.add_argument("--map", dest="maps", action="append",
                   help="map(s) to score (default: every shipped map with a held-out set)")
    p.add_argument("--noise", default="0,0.005,0.01", help="bench fit's relative noise levels (must include 0)")
    p.add_argument("--repeats", type=int, default=5, help="timed rounds per variant, best kept (default 5)")
    p.add_argument("--median-bins", type=int, default=128, help="bins timed for the paper's ε-median (default 128)")
    p.add_argument("--draws", type=int, default=8, help="bench uncertainty's noise draws per material (default 8)")
    p.add_argument("--sensor-noise", default="0,0.005",
                   help="bench sensor's relative noise levels for the builds' table (must include 0)")
    p.add_argument("--sensor-draws", type=int, default=3, help="bench sensor's noise draws per material (default 3)")
    p.add_argument("--tracer-materials", type=int, default=8,
                   help="random materials per geometry for the tracer check (default 8; 0: not run)")
    p.add_argument("--tracer-paths", type=int, default=1 << 18, help="tracer paths per material (default 262144)")
    p.add_argument("--tracer-spp", type=int, default=1 << 16, help="volpath samples per render (default 65536)")
    p.add_argument("--polarisation-spp", type=int, default=1 << 18,
                   help="volpath samples per render of the polarisation bench (default 262144; 0: not run)")
    p.add_argument("--no-device", action="store_true",
                   help="skip the single-precision build and the QEMU count (no C compiler or QEMU here)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    noise = _noise_levels(args.noise, "--noise")
    sensor_noise = _noise_levels(args.sensor_noise, "--sensor-noise")
    if args.repeats < 1 or args.draws < 1 or args.median_bins < 1 or args.sensor_draws < 1:
        raise InputError("--repeats, --draws, --median-bins and --sensor-draws must be at least 1")
    if args.tracer_materials < 0:
        raise InputError(f"--tracer-materials must be ≥ 0, got {args.tracer_materials}")
    if args.polarisation_spp and args.polarisation_spp < 16:
        raise InputError(f"--polarisation-spp must be 0 (not run) or ≥ 16, got {args.polarisation_spp}")
    args.work.mkdir(parents=True, exist_ok=True)
    results = measure(args, noise, sensor_noise)
    results["seconds"] = round(time.perf_counter() - start, 1)
    text = json.dumps(results, indent=1, default=_jsonable) + "\n"
    atomic_write(args.work / "report.json", text)
    page = write_page(results, args.docs)
    atomic_write(args.docs / FIGURES_JSON, text)
    print(f"{page} written in {results['seconds']:.0f} s (the benches' logs and JSON: {args.work})")
    return 0


def _noise_levels(text: str, option: str) -> list[float]:
    try:
        levels = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"{option}: {text!r} is not a comma-separated list of numbers") from None
    if 0.0 not in levels or any(not (0 <= x < 0.5) for x in levels):
        raise InputError(f"{option}: levels in [0, 0.5), including 0 (the headline figures are noise-free)")
    return levels


def _jsonable(value: object) -> object:
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return float(value)  # type: ignore[arg-type]  # json's default: anything else numeric


@contextlib.contextmanager
def _step(title: str, log: Path) -> Iterator[None]:
    """A bench's own printed output into its log file; one line here per step with its time."""
    print(f"{title} … ", end="", flush=True)
    t0 = time.perf_counter()
    with log.open("w") as f, contextlib.redirect_stdout(f):
        yield
    print(f"{time.perf_counter() - t0:.0f} s (log: {log})", flush=True)


def measure(args: argparse.Namespace, noise: list[float], sensor_noise: list[float]) -> dict[str, Any]:
    """Run the benches; every figure the page shows, as one JSON-able dict."""
    from trimeter.bench import fit, polarisation, sensor, tracer_check, uncertainty

    work: Path = args.work
    results: dict[str, Any] = {"stamp": machine_stamp(), "settings": {
        k: getattr(args, k) for k in ("maps", "noise", "repeats", "median_bins", "draws", "tracer_materials",
                                      "tracer_paths", "tracer_spp", "no_device", "sensor_noise", "sensor_draws",
                                      "polarisation_spp")}}
    with _step("accuracy and speed (bench fit)", work / "fit.log"):
        results["fit"] = fit.measure(argparse.Namespace(
            maps=args.maps, noise=",".join(map(str, noise)), median_bins=args.median_bins, repeats=args.repeats,
            per_wavelength_backgrounds=False, out=work / "fit", seed=0))
    with _step("the device table alone (bench table-fit)", work / "table-fit.log"):
        results["tables"] = {m["map"]: _tables(m, args) for m in results["fit"]["maps"]}
    device_maps = [m["map"] for m in results["fit"]["maps"] if m["geometry"] == "device"]
    results["uncertainty"] = None
    if device_maps:
        with _step("coverage of the reported σ (bench uncertainty)", work / "uncertainty.log"):
            results["uncertainty"] = uncertainty.measure(argparse.Namespace(
                maps=device_maps, noise="0.002,0.005,0.01", draws=args.draws, thickness_rel_std=0.02,
                modes="given,fixed", out=work / "uncertainty", seed=0))
    with _step("every build's accuracy (bench sensor)", work / "sensor.log"):
        results["builds"] = {"thickness_mm": BUILDS_THICKNESS_MM, "runs": [sensor.measure(argparse.Namespace(
            thickness=BUILDS_THICKNESS_MM, noise=level, draws=args.sensor_draws, band_nm="400:950", seed=0))
            for level in sensor_noise]}
    results["tracer"] = None
    if args.tracer_materials:
        with _step("the map tracer against Mitsuba (bench tracer-check)", work / "tracer-check.log"):
            results["tracer"] = tracer_check.check(argparse.Namespace(
                materials=args.tracer_materials, paths=args.tracer_paths, spp=args.tracer_spp, geometry="both",
                seed=2027, backend="auto", series_orders=None))
            results["tracer"]["mitsuba"] = _mitsuba_version()
    results["polarisation"] = None
    if args.polarisation_spp:
        with _step("polarised against unpolarised renders (bench polarisation)", work / "polarisation.log"):
            t0 = time.perf_counter()
            results["polarisation"] = polarisation.measure(argparse.Namespace(
                geometry="both", spp=args.polarisation_spp, slab_spp=polarisation.DEFAULT_SLAB_SPP,
                materials=len(polarisation.MATERIALS), seed=polarisation.DEFAULT_SEED))
            results["polarisation"].update(seconds=round(time.perf_counter() - t0, 1), mitsuba=_mitsuba_version())
    return results


def _tables(fit_map: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """The map's device table fitted alone (double; single precision as the firmware) and counted under QEMU."""
    from trimeter.bench import table_fit
    from trimeter.bench._firmware import (COUNT_BINS_PER_CALL, COUNT_LABEL, qemu_instruction_counts,
                                          single_precision_library)
    from trimeter.formats.appearance import find_map
    from trimeter.formats.device_table import table_path_for

    path = table_path_for(find_map(fit_map["map"]))
    if not path.is_file():
        return {"skipped": f"no device table {path.name} beside the map"}
    out: dict[str, Any] = {"table": str(path.relative_to(REPO_ROOT)) if path.is_relative_to(REPO_ROOT) else str(path)}
    out["double"] = table_fit.measure(path, fit_map["map"], args.repeats)
    if fit_map["geometry"] != "device":
        return out  # the instrument carries device tables only
    if args.no_device:
        out["device_skipped"] = "--no-device"
        return out
    try:
        library = single_precision_library(args.work / "single")
        out["single"] = table_fit.measure(path, fit_map["map"], args.repeats, library)
        counts = qemu_instruction_counts(path)
    except BuildError as exc:
        out["device_skipped"] = str(exc)
        return out
    call = counts["instructions"][COUNT_LABEL]
    per_bin = {"mean": call["mean"] / COUNT_BINS_PER_CALL, "min": round(call["min"] / COUNT_BINS_PER_CALL),
               "max": round(call["max"] / COUNT_BINS_PER_CALL), "calls": call["calls"],
               "bins_per_call": COUNT_BINS_PER_CALL}
    cpi = counts["cycles_per_instruction"]
    out["device"] = {"instructions_per_bin": per_bin, "mhz": counts["mhz"], "cycles_per_instruction": cpi,
                     "ms_per_1024": [per_bin["mean"] * c * 1024 / (counts["mhz"] * 1e3) for c in cpi]}
    return out


def _mitsuba_version() -> str:
    try:
        import mitsuba

        return str(mitsuba.__version__)
    except ImportError:
        return "?"


def machine_stamp() -> dict[str, Any]:
    """Commit, date and machine the figures were made on."""
    from trimeter.inversion import native

    def git(*argv: str) -> str:
        try:
            done = subprocess.run(["git", "-C", str(REPO_ROOT), *argv], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return ""
        return done.stdout.strip() if done.returncode == 0 else ""

    # the page and its figures are this command's output: rewriting them does not make the code dirty
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", f":!docs/{PAGE}", f":!docs/{IMG_DIR}",
                  f":!docs/{FIGURES_JSON}")
    cpu = platform.processor() or "?"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {"commit": git("rev-parse", "HEAD") or "unknown (not a git checkout)",
            "commit_date": git("show", "-s", "--format=%cI", "HEAD"), "uncommitted_changes": bool(changed),
            "date_utc": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "cpu": cpu,
            "cores": os.cpu_count(), "cores_usable": native.usable_cpus(), "load_average": list(load),
            "python": platform.python_version(), "numpy": np.__version__, "os": platform.platform(terse=True),
            "kernel": native.status()}


# ---- the page ------------------------------------------------------------------------------------------


def write_page(results: dict[str, Any], docs: Path) -> Path:
    """docs/validation.md and its figures from `measure`'s results; returns the page's path."""
    img = docs / IMG_DIR
    img.mkdir(parents=True, exist_ok=True)
    fit_maps = results["fit"]["maps"]
    figures = {m["map"]: _plot_time_error(m, results["tables"].get(m["map"], {}), img) for m in fit_maps}
    coverage_png = _plot_coverage(results["uncertainty"], img) if results["uncertainty"] else None
    tracer_png = _plot_tracer(results["tracer"], img) if results["tracer"] else None
    page = docs / PAGE
    lines = _header(results)
    lines += _accuracy_section(results, figures, page)
    lines += _builds_section(results["builds"])
    lines += _uncertainty_section(results["uncertainty"], coverage_png, page)
    lines += _tracer_section(results["tracer"], tracer_png, page)
    lines += polarisation_section(results.get("polarisation"))
    lines += _reproduce_section(results)
    atomic_write(page, "\n".join(lines) + "\n")
    return page


def _rel(path: Path, page: Path) -> str:
    return os.path.relpath(path, page.parent).replace(os.sep, "/")


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *("| " + " | ".join(r) + " |" for r in rows), ""]


def _f(x: float | None, digits: int = 4) -> str:
    if x is None or not np.isfinite(x):
        return "–"
    return f"{x:.{digits}f}"


def _g(x: float | None, digits: int = 3) -> str:
    if x is None or not np.isfinite(x):
        return "–"
    return f"{x:.{digits}g}"


def _pct(x: float | None, digits: int = 1) -> str:
    if x is None or not np.isfinite(x):
        return "–"
    return f"{100 * x:.{digits}f} %"


def _header(results: dict[str, Any]) -> list[str]:
    s = results["stamp"]
    commit = s["commit"][:12] + (" with uncommitted changes" if s["uncommitted_changes"] else "")
    load = ", ".join(f"{x:.2f}" for x in s["load_average"])
    return [
        "# Validation",
        "",
        "<!-- Generated by `trimeter bench report` (host/trimeter/bench/report.py): do not edit by hand. -->",
        "",
        f"Generated by `trimeter bench report` from commit `{commit}` on {s['date_utc']}, in "
        f"{results['seconds']:.0f} s, on {s['cpu']} ({s['cores']} cores, {s['cores_usable']} usable; load average "
        f"{load} when it started), {s['os']}, Python {s['python']}, numpy {s['numpy']}; inversion kernel: "
        f"{s['kernel']}. Every figure below comes from that run; re-run the command to refresh them.",
        "",
        "**What these figures are, and are not.**",
        "",
        "- Nothing on this page has touched real hardware. No trimeter has been built; every input here is "
        "simulated.",
        "- The held-out sets (`maps/heldout/`, made by `tools/make_heldout.py`) are random materials off the maps' "
        "grids, rendered directly, never interpolated from a map: for the device geometry by Monte Carlo with this "
        "project's own tracer (`trimeter.forward.transport.trace_column`, with far more paths than the maps), for the "
        "ideal geometry by adding-doubling (`iadpython`). Because the device references come from the same tracer "
        "as the device maps, an error of the tracer itself does not show in the accuracy section: the tracer "
        "is compared with Mitsuba 3 further down. Nor do the models the device references share with the "
        "maps: Fresnel per polarisation at every face with every scattering depolarising (the tracer's "
        "polarisation option, on in the device recipes) and one return coefficient C for the background's "
        "bounces. What the single C costs the fits on these held-out sets, and what unpolarised Fresnel cost them "
        "before the device maps tracked polarisation, is measured by `tools/model_effect_check.py` (figures: "
        "maps/README.md, \"Polarisation\" and \"Known open points\").",
        "- Noise, where there is any, is synthetic: relative Gaussian noise on I_b, I_w and I_c.",
        "- Times are the best of several rounds, all methods of a table timed round-robin in one process on a "
        "shared machine: compare them within a table. On a loaded machine a call longer than the scheduler's time "
        "slice (the paper rows: tens of milliseconds) is slowed more than a sub-millisecond one (lut), so ratios to "
        "paper overstate the speed-up; the load average above says how loaded it was. \"On the device\" is an "
        "estimate from an instruction count under QEMU, not a run on a board.",
        "",
    ]


def _method_rows(fit_map: dict[str, Any], tables: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per method, noise-free rendered references: name, time (ms per 1024 bins, or a range),
    α / σt / g error figures and NaN / flag rates."""
    rows = []
    clean = {r["variant"]: r for r in fit_map["rows"] if r["noise"] == 0}
    for variant, name in FIT_METHODS.items():
        if variant in clean:
            rows.append({"method": name, "source": "fit", **clean[variant],
                         "time": _g(clean[variant]["ms_per_1024"])})
    double = tables.get("double")
    if double:
        for r in double["rows"]:
            if r["variant"] in TABLE_METHODS:
                rows.append({"method": TABLE_METHODS[r["variant"]], "source": "table-fit", **r,
                             "time": _g(r["ms_per_1024"]) + "*", "nan_rate_measurable": r["nan_rate_measurable"]})
    single, device = tables.get("single"), tables.get("device")
    if single and device:
        r = next(r for r in single["rows"] if r["variant"].startswith("table alone, C"))
        lo, hi = device["ms_per_1024"]
        rows.append({"method": DEVICE_LABEL, "source": "device", **r, "ms_per_1024": float(np.sqrt(lo * hi)),
                     "ms_range": (lo, hi), "time": f"{lo:.0f}–{hi:.0f} (est.)"})
    return rows


def _accuracy_section(results: dict[str, Any], figures: dict[str, Path], page: Path) -> list[str]:
    fit = results["fit"]
    maps = fit["maps"]
    headline = next((m for m in maps if m["map"] == HEADLINE_MAP), maps[0])
    lines = ["## Accuracy and speed: every method on the held-out sets", "",
             "Per method: time per 1024 wavelength bins of the whole fit (input checks, flags and per-bin σ "
             "included; one core), and over the held-out materials the 95th percentile of |α error|, of the "
             "relative σt error and of |g error| (g over α ≥ 0.5; all over the measurable gamut, I_c ≥ 1e-3), "
             "noise-free. Targets for lut and mlp: α p95 ≤ 0.01, σt relative p95 ≤ 1 %, g p95 ≤ 0.015.", ""]
    for m in [headline] + [m for m in maps if m is not headline]:
        tables = results["tables"].get(m["map"], {})
        rows = _method_rows(m, tables)
        lines += [f"### {m['map']}" + (" (headline)" if m is headline else ""), "",
                  f"{m['materials']} held-out materials ({m['measurable']} in the measurable gamut), "
                  f"ℓ = {m['thickness_mm']:g} mm, {m['geometry']} geometry; references: {m['heldout_source']}.", ""]
        lines += _table(["method", "ms per 1024 bins", "α p95", "σt rel. p95", "g p95", "α / g p95 well-cond.",
                         "NaN in gamut", "flagged (all materials)"],
                        [[r["method"], r["time"], _f(r["alpha_p95"]), _pct(r["sigma_rel_p95"], 3), _f(r["g_p95"]),
                          f"{_f(r['alpha_p95_well'])} / {_f(r['g_p95_well'])}", _pct(r.get("nan_rate_measurable")),
                          _pct(r.get("flag_rate"))] for r in rows])
        notes = []
        if any(r["source"] == "table-fit" for r in rows):
            base = next(r for r in tables["double"]["rows"] if r["variant"].startswith("map lut"))
            lut = next((r for r in rows if r["method"] == "lut"), None)
            notes.append(f"\\* timed in `bench table-fit`'s own round-robin, where lut took "
                         f"{_g(base['ms_per_1024'])} ms" + (f" (here {lut['time']})" if lut else "") + ".")
        if tables.get("device"):
            d = tables["device"]
            per_bin = d["instructions_per_bin"]
            notes.append(f"On the device: {per_bin['mean']:,.0f} instructions per bin, fitted "
                         f"{per_bin.get('bins_per_call', 1)} per call as its fit loop does (the table check shared; "
                         f"{per_bin['calls']} calls in `firmware/qemu/count.c`, {per_bin['min']:,}–{per_bin['max']:,} "
                         f"per bin) at "
                         f"{d['mhz']:g} MHz and {d['cycles_per_instruction'][0]:g}–{d['cycles_per_instruction'][1]:g} "
                         "cycles per instruction; its errors are the single-precision build's on this host.")
        elif tables.get("device_skipped"):
            notes.append(f"On the device: not measured ({tables['device_skipped']}).")
        lines += [" ".join(notes), ""] if notes else []
        if m["map"] in figures:
            lines += [f"![time against error, {m['map']}]({_rel(figures[m['map']], page)})", ""]
        lines += _noise_table(m)
        lines += _budget_lines(m)
        lines += _targets_lines(m)
    if fit.get("speed"):
        lines += _speed_lines(fit["speed"])
    if fit.get("two_thicknesses"):
        two = fit["two_thicknesses"]
        lines += ["### Both thicknesses fitted together", "",
                  f"{' + '.join(two['maps'])}: the same materials at both thicknesses, fitted together (the paper's "
                  f"procedure); {two['measurable']} materials measurable at either thickness.", ""]
        lines += _table(["method", "ms per 1024 bins", "α p95", "g p95"],
                        [[r["variant"], _g(r["ms_per_1024"]), _f(r["alpha_p95"]), _f(r["g_p95"])]
                         for r in two["rows"]])
    return lines


def _speed_lines(speed: dict[str, Any]) -> list[str]:
    """bench fit's speed section: the whole lut fit (flags and stds included) against a bare scipy lookup."""
    times = speed["ms_per_1024"]
    lookup = times["bare lookup"]
    lines = ["### Speed with uncertainty", "",
             f"{speed['map']}: 1024 bins (its held-out materials inside the hull of the map's nodes, noise-free), "
             "the whole lut fit, with per-bin σ and flags, against a bare scipy `LinearNDInterpolator` lookup of "
             "the same bins on the map's nodes (the paper's interpolant, built beforehand: the call alone), timed "
             "round-robin in the same run; the paper's ε-median on fewer bins, scaled."
             + (" Each round times, in this order: " + " → ".join(f"“{name}”" for name in speed["round"]) + "."
                if "round" in speed else "")
             + (f" The lut fits run in {speed['fit_threads']} threads, which share the bins out, unless the row "
                "says one thread; the lookup and the paper's method in one."
                if speed.get("fit_threads", 1) > 1 else ""),
             ""]
    lines += _table(["", "ms per 1024 bins", "× bare lookup"],
                    [[name, _g(ms), _g(ms / lookup)] for name, ms in times.items()])
    for key, t in speed["targets"].items():
        label = {"lut_over_lookup": "whole lut fit over a bare lookup",
                 "two_thicknesses_ms": "two thicknesses fitted together, ms per 1024 bins",
                 "two_thicknesses_one_thread_ms": "the same in one thread, ms per 1024 bins"}.get(key, key)
        lines.append(f"- {label}: {_g(t['value'])} (target ≤ {t['max']:g}): {'met' if t['met'] else 'missed'}")
    return lines + [""]


def _noise_table(m: dict[str, Any]) -> list[str]:
    levels = sorted({r["noise"] for r in m["rows"]})
    if len(levels) < 2:
        return []
    by = {(r["variant"], r["noise"]): r for r in m["rows"]}
    variants = [v for v in FIT_METHODS if (v, levels[0]) in by]
    header = ["method"] + [f"α / σt / g p95 at {100 * lv:g} % noise" for lv in levels]
    rows = [[FIT_METHODS[v]] + [f"{_f(by[v, lv]['alpha_p95'])} / {_pct(by[v, lv]['sigma_rel_p95'], 2)} / "
                                f"{_f(by[v, lv]['g_p95'])}" for lv in levels] for v in variants]
    return ["With relative noise on I_b, I_w, I_c (the same draws for every method):", "", *_table(header, rows)]


def _budget_lines(m: dict[str, Any]) -> list[str]:
    b = m["budget"]
    ref, err, wc = b["reference_noise_floor"], b["map_error_floor"], b["well_conditioned"]
    return [f"What limits these figures (first order through the map's Jacobian): the references' own Monte Carlo "
            f"noise amounts to α p95 {_f(ref['alpha_p95'])}, g p95 {_f(ref['g_p95'])}; the map's error against the "
            f"references (what an exact inversion of the map would miss) to α p95 {_f(err['alpha_p95'])}, g p95 "
            f"{_f(err['g_p95'])}. \"Well-conditioned\": the materials whose references are precise enough to judge "
            f"the targets (their own α std < {wc['alpha_floor_std_below']:g}: {wc['alpha_count']} of "
            f"{wc['alpha_of']}; g std < {wc['g_floor_std_below']:g}: {wc['g_count']} of {wc['g_of']}).", ""]


def _targets_lines(m: dict[str, Any]) -> list[str]:
    lines = []
    for variant, checks in m.get("targets", {}).items():
        missed = [k for k, c in checks.items() if c["issue_target"] and not c["met"]]
        shown = "; ".join(f"{k} {_g(c['value'])} (≤ {c['limit']:g})" if "paper" not in k else
                          f"{k} {_g(c['value'])} (≥ {c['limit']:g})"
                          for k, c in checks.items() if c["issue_target"])
        lines.append(f"- {variant}: " + ("all targets met" if not missed else "missed " + ", ".join(missed))
                     + f" — {shown}")
    return (["Targets, judged in this run:", "", *lines, ""]) if lines else []


def _builds_section(builds: dict[str, Any]) -> list[str]:
    """bench sensor's table: one row per build (and the inks alone), per noise level."""
    runs = builds["runs"]
    first = runs[0]
    lines = [f"## {BUILDS_SECTION}", "",
             f"What each build of the instrument would measure, from `trimeter bench sensor`: the twin's "
             f"{first['material_count']} catalogue materials at {builds['thickness_mm']:g} mm, their I_b, I_w, I_c "
             f"traced directly (independently of the map {first['map']} that the fits invert), read as each build "
             f"reads them: the ideal spectrometer every pixel as it is; the USB spectrometer (seabreeze) through its "
             f"slit under the build's LEDs; the AS7341 its {first['channels']} channels' band readings, fitted per "
             f"channel as if monochromatic (reported at the datasheet's centres, or scored at each band's centroid) "
             f"or band-aware (`trimeter fit --bands`). The spectrometers are scored at {first['scored_pixels']} "
             f"pixels {first['band_nm'][0]:g}–{first['band_nm'][1]:g} nm. p95 over the reported values of |Δα|, "
             f"|Δσt|/σt and |Δg| against the material's own spectra at the reported wavelengths, and how many "
             f"reported values carry any flag. \"inks\": the four smooth ink-like materials alone. Noise: relative "
             f"Gaussian on each reading plus 2e-4 absolute. The hardware's bill of materials quotes its builds' rows "
             f"from this section's JSON (`docs/{FIGURES_JSON}`).", ""]
    for run in runs:
        lines += [("Noise-free:" if run["noise"] == 0 else
                   f"With {100 * run['noise']:g} % noise ({run['draws']} draws per material):"), ""]
        lines += _table(["build", "materials", "α p95", "σt rel. p95", "g p95", "flagged"],
                        [[r["build"], r["materials"], _f(r["alpha_p95"]), _pct(r["sigma_t_rel_p95"], 2),
                          _f(r["g_p95"]), f"{r['flagged']} of {r['values']} ({_pct(r['flagged'] / r['values'], 0)})"]
                         for r in run["builds"]])
    return lines


def _uncertainty_section(unc: dict[str, Any] | None, png: Path | None, page: Path) -> list[str]:
    lines = ["## Uncertainty: do the reported σ cover the truth?", ""]
    if unc is None:
        return lines + ["Not run: no device map among the maps scored.", ""]
    counts = ", ".join(f"{name} {n}" for name, n in unc.get("heldout_materials", {}).items())
    lines += [f"The {unc.get('heldout_part', 'whole')} part of the device maps' held-out sets ({counts} materials; "
              "the calibration part, on which the map's error scale in the σ is chosen, is never scored here). "
              "Each material drawn "
              f"{unc['draws']} times with relative Gaussian noise of known size on I_b, I_w, I_c and fitted by lut. "
              "**given**: the noise's std handed to the fit (with the references' own Monte Carlo error); "
              "**fixed**: the fit's fixed noise model alone. Share of unflagged bins whose truth lies within ±1σ / "
              "±2σ of the estimate (goal 68 % ± 5 / 95 % ± 3; ✓ = met), and the mean signed error over σ (an "
              "offset all estimates share, which no ±σ covers). \"ℓ ±2 %\": each sample's real thickness drawn "
              "2 % off the map's and that std given to the fit.", ""]
    if png is not None:
        lines += [f"![coverage of the reported σ]({_rel(png, page)})", ""]
    rows = []
    for r in unc["rows"]:
        cells = [r["case"], f"{100 * r['noise']:g} %", r["mode"], f"{r['unflagged']}/{r['bins']}"]
        for p in ("alpha", "sigma_t", "g"):
            c = r[p]
            cells.append(f"{_pct(c['within_1sigma'], 0)} / {_pct(c['within_2sigma'], 0)}"
                         + (" ✓" if c["goal_met"] else ""))
        cells.append(" / ".join(f"{r[p]['mean_z']:+.2f}" for p in ("alpha", "sigma_t", "g")))
        rows.append(cells)
    lines += _table(["case", "noise", "σ", "unflagged", "α ±1σ / ±2σ", "σt ±1σ / ±2σ", "g ±1σ / ±2σ",
                     "mean z α / σt / g"], rows)
    lines += ["The map's own error against the σ the fit reports at the lowest noise level (median of "
              "|noise-free error| / σ, and the share above 1: where that share is large, the map's error, not "
              "the noise, sets the coverage):", ""]
    lines += _table(["case", "σ", "α", "σt", "g"],
                    [[b["case"], b["mode"]] + [f"{_g(b[p]['median'], 2)} ({_pct(b[p]['share_above_1'], 0)})"
                                               for p in ("alpha", "sigma_t", "g")] for b in unc["map_error"]])
    return lines


def _tracer_section(tracer: dict[str, Any] | None, png: Path | None, page: Path) -> list[str]:
    from trimeter.forward.transport.agreement import Z_MEAN_MAX, Z_P95_MAX

    lines = ["## The map tracer against Mitsuba 3", ""]
    full = "trimeter bench tracer-check --paths 4194304 --spp 4194304"
    if tracer is None:
        return lines + ["Not run by this command (`--tracer-materials 0`), and no stored result is shown in its "
                        f"place. The check: `{full}` (40 random materials per geometry on both backgrounds; it "
                        "renders every material with Mitsuba's `volpath` and takes tens of minutes on two cores).",
                        ""]
    st = tracer["settings"]
    lines += [f"The tracer that builds the maps against Mitsuba {tracer.get('mitsuba', '?')}'s `volpath`, at a size "
              f"that fits in this command: {st['materials']} seeded random materials per geometry, each on both "
              f"reference backgrounds (ρ = 0.02, 0.9), {st['paths']:,} tracer paths and {st['spp']:,} samples per "
              f"render (volpath extrapolated to no ray offset), {tracer['seconds']:.0f} s. z = (tracer − volpath) / "
              f"combined standard error; the check's goal over its full size is p95 |z| ≤ {Z_P95_MAX} and "
              f"|mean z| ≤ {Z_MEAN_MAX} per geometry. At this size the renders' own noise is large, so the check "
              f"resolves only differences of that order (the median combined standard error is "
              f"{_pct(_median_rel_stderr(tracer['rows']), 2)} of the value), and p95 of few values is nearly their "
              f"largest. \"Ideal vs adding-doubling\": the ideal geometry's tracer against Prahl's "
              f"adding-doubling (exact there), over the tracer's standard error alone. The full check: `{full}` "
              "(tens of minutes on two cores).", ""]
    if png is not None:
        lines += [f"![tracer against volpath: z-scores]({_rel(png, page)})", ""]
    lines += _table(["group", "n", "mean z", "std", "p95 \\|z\\|", "max \\|z\\|", "goal"],
                    [[k, str(s["count"]), f"{s['mean']:+.2f} ± {_g(s['mean_stderr'], 2)}", _g(s["std"], 2),
                      f"{s['p95_abs']:.2f}", f"{s['max_abs']:.2f}", ("" if "ρ=" in k else "met" if s["ok"] else
                                                                     "missed")] for k, s in tracer["summary"].items()])
    return lines


POLARISATION_HEADING = "Polarisation: what unpolarised Fresnel leaves out"


def polarisation_section(pol: dict[str, Any] | None) -> list[str]:
    """The page's section from trimeter.bench.polarisation.measure's report (None: not run)."""
    lines = [f"## {POLARISATION_HEADING}", ""]
    command = "trimeter bench polarisation"
    if pol is None:
        return lines + [f"Not run by this command (`--polarisation-spp 0`). The bench: `{command}` (a few minutes).",
                        ""]
    unpolarised, polarised = pol["variants"]
    lines += ["The device maps are traced with Fresnel per polarisation at every face and every scattering "
              "depolarising (the tracer's option, checked by `trimeter bench polarisation-tracer`); the ideal map, "
              "the tracer check's renders and adding-doubling use unpolarised Fresnel. What that leaves out: "
              f"Mitsuba {pol.get('mitsuba', '?')}'s `volpath` renders each material in `{unpolarised}` (u) and "
              f"in `{polarised}`, the faces' Fresnel as Mueller matrices, twice: with Mitsuba's `hg`, whose "
              "scattering keeps the light's polarisation (p), and with `hg_depolarising`, whose scattering "
              "depolarises it (d); a real medium lies between. "
              f"{pol['spp']:,} samples per render, all renders of a material from the same seeds (so each shift "
              f"has its own standard error and z = shift / that error), {pol.get('seconds', float('nan')):.0f} s. "
              "The intensities of all three are fitted with the geometry's shipped map (I_c, at normal incidence, "
              "is the same for all); a fitted shift counts (!) when it is beyond the map's own error σ_map (the σ "
              "fit() reports for noise-free intensities: the map's Monte Carlo and interpolation error) and beyond "
              "twice its render noise.", ""]
    slab = pol.get("slab")
    if slab:
        d = slab["delta"]
        lines += [f"The set-up, on a clear lossless slab (n = {slab['n']}) over ρ = {slab['rho']}: the diffuse "
                  f"reflectance R_d its rendered I implies is {slab['unpolarised']['R_d']:.4f} ± "
                  f"{slab['unpolarised']['stderr']:.4f} unpolarised (closed form "
                  f"{slab['unpolarised']['closed_form']:.4f}) and {slab['polarised']['R_d']:.4f} ± "
                  f"{slab['polarised']['stderr']:.4f} polarised (closed form {slab['polarised']['closed_form']:.4f}); "
                  f"the difference {d['R_d']:+.4f} ± {d['stderr']:.4f} (closed form {d['closed_form']:+.4f}), "
                  f"{slab['spp']:,} samples per render.", ""]
    names = {"alpha": "α", "sigma_t": "σt", "g": "g"}
    for geo in pol["geometries"]:
        rows = []
        for k, f in enumerate(geo["fits"]):
            black, white = geo["rows"][2 * k], geo["rows"][2 * k + 1]
            cells = [f"{f['material']} ({f['alpha']['truth']:g}, {f['sigma_t']['truth']:g}/mm, {f['g']['truth']:g})"]
            for r in (black, white):
                cells.append(f"{r['delta']:+.5f} ({r['z']:+.1f}) / {r['delta_depolarising']:+.5f} "
                             f"({r['z_depolarising']:+.1f})")
            for p in ("alpha", "sigma_t", "g"):
                c = f[p]
                cells.append(f"{c['shift']:+.4f}{'!' if c['beyond_map_error'] else ''} / "
                             f"{c['shift_depolarising']:+.4f}{'!' if c['beyond_map_error_depolarising'] else ''} "
                             f"({c['sigma_map']:.4f})")
            rows.append(cells)
        moved = [sum(f[p][f"beyond_map_error{s}"] for f in geo["fits"] for p in names) for s in ("", "_depolarising")]
        lines += [f"### {geo['geometry']} (fitted with {geo['map']})", ""]
        lines += _table(["material (α, σt, g)", "ΔI_b p / d (z)", "ΔI_w p / d (z)",
                         *(f"Δ{n} p / d (σ_map)" for n in names.values())], rows)
        lines += [f"Beyond the map's error: {moved[0]} of {len(geo['fits']) * len(names)} fitted values (p), "
                  f"{moved[1]} (d).", ""]
    return lines + [f"More materials, more samples, the JSON: `{command}`.", ""]


def _median_rel_stderr(rows: list[dict[str, Any]]) -> float:
    rel = [np.hypot(r["tracer_stderr"], r["volpath_stderr"]) / abs(r["volpath"]) for r in rows if r["volpath"]]
    return float(np.median(rel)) if rel else float("nan")


def _reproduce_section(results: dict[str, Any]) -> list[str]:
    s = results["settings"]
    argv = ["trimeter bench report"]
    for key, flag in (("noise", "--noise"), ("repeats", "--repeats"), ("median_bins", "--median-bins"),
                      ("draws", "--draws"), ("tracer_materials", "--tracer-materials"),
                      ("tracer_paths", "--tracer-paths"), ("tracer_spp", "--tracer-spp"),
                      ("polarisation_spp", "--polarisation-spp"),
                      ("sensor_noise", "--sensor-noise"), ("sensor_draws", "--sensor-draws")):
        argv.append(f"{flag} {s[key]}")
    argv += [f"--map {m}" for m in s["maps"] or ()] + (["--no-device"] if s["no_device"] else [])
    return ["## Reproduce", "",
            f"This page, its figures, its figures as JSON (`{FIGURES_JSON}`) and the benches' logs and JSON (under "
            "`out/bench-report/`):", "",
            "```", " ".join(argv), "```", "",
            "Each part on its own, with more options: `trimeter bench fit`, `trimeter bench table-fit --table "
            "maps/device-n1.5-l0.4.tlut`, `trimeter bench uncertainty`, `trimeter bench sensor`, "
            "`trimeter bench tracer-check`, `trimeter bench polarisation`, and the "
            "device's instruction count `make -C firmware qemu-count COUNT_TABLE=maps/device-n1.5-l0.4.tlut`."]


# ---- figures ------------------------------------------------------------------------------------------


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    with atomic_output(path) as f:
        fig.savefig(f, dpi=100, format="png", metadata={"Software": None})  # no version string: stable bytes
    _pyplot().close(fig)
    return path


def _plot_time_error(fit_map: dict[str, Any], tables: dict[str, Any], img: Path) -> Path:
    """Time per 1024 bins against α / σt / g p95 (noise-free), one point per method."""
    plt = _pyplot()
    rows = _method_rows(fit_map, tables)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for ax, key, label in ((axes[0], "alpha_p95", "α abs error p95"), (axes[1], "sigma_rel_p95", "σt rel. error p95"),
                           (axes[2], "g_p95", "g abs error p95 (α ≥ 0.5)")):
        for i, r in enumerate(rows):
            y = r[key]
            if not (np.isfinite(y) and y > 0):
                continue
            colour = f"C{i % 10}"
            if "ms_range" in r:
                lo, hi = r["ms_range"]
                ax.errorbar([r["ms_per_1024"]], [y], xerr=[[r["ms_per_1024"] - lo], [hi - r["ms_per_1024"]]],
                            fmt="s", color=colour, capsize=3, label=r["method"])
            else:
                ax.scatter(r["ms_per_1024"], y, s=30, color=colour, label=r["method"])
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("ms per 1024 bins (whole fit)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"{fit_map['map']}: time against error, noise-free held-out set")
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return _save(fig, img / f"time-vs-error-{fit_map['map']}.png")


def _plot_coverage(unc: dict[str, Any], img: Path) -> Path:
    """Share within ±1σ and ±2σ per case and noise level (σ given to the fit), against the goal bands."""
    from trimeter.bench.uncertainty import GOAL_1, GOAL_2

    plt = _pyplot()
    rows = [r for r in unc["rows"] if r["mode"] == "given"]
    labels = [f"{r['case']}\n{100 * r['noise']:g} %" for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(2, 1, figsize=(max(8, 0.9 * len(rows) + 2), 6.5), sharex=True)
    for ax, key, (goal, tol), floor in ((axes[0], "within_1sigma", GOAL_1, 30), (axes[1], "within_2sigma", GOAL_2, 60)):
        ax.axhspan(100 * (goal - tol), 100 * (goal + tol), color="grey", alpha=0.25, label="goal")
        for j, (p, name) in enumerate((("alpha", "α"), ("sigma_t", "σt"), ("g", "g"))):
            shares = np.array([100 * r[p][key] for r in rows])
            ax.scatter(x + (j - 1) * 0.2, np.maximum(shares, floor), s=28, label=name, color=f"C{j}",
                       marker="o")
        ax.set_ylabel(f"% within ±{key[7]}σ")
        ax.set_ylim(floor, 100.5)  # a share below the floor is drawn on it
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, ncol=4, loc="lower left")
    axes[1].set_xticks(x, labels, rotation=35, ha="right", fontsize=7)
    fig.suptitle("coverage of the reported σ (lut, σ of the noise given to the fit, unflagged bins)")
    fig.tight_layout()
    return _save(fig, img / "coverage.png")


def _plot_tracer(tracer: dict[str, Any], img: Path) -> Path:
    """z per material and background, per geometry, and the ideal geometry against adding-doubling."""
    from trimeter.forward.transport.agreement import Z_P95_MAX

    plt = _pyplot()
    groups: list[tuple[str, list[float]]] = []
    for geometry in ("ideal", "device"):
        for rho in (0.02, 0.9):
            z = [r["z"] for r in tracer["rows"] if r["geometry"] == geometry and r["rho"] == rho]
            if z:
                groups.append((f"{geometry}\nρ = {rho:g}", z))
    iad = [r["z_iad"] for r in tracer["rows"] if "z_iad" in r]
    if iad:
        groups.append(("ideal against\nadding-doubling", iad))
    fig, ax = plt.subplots(figsize=(7, 4))
    rng = np.random.default_rng(0)  # horizontal jitter only, so equal z's stay visible
    for i, (_, z) in enumerate(groups):
        ax.scatter(i + rng.uniform(-0.15, 0.15, len(z)), z, s=18, color=f"C{i}")
    for level in (-Z_P95_MAX, Z_P95_MAX):
        ax.axhline(level, color="grey", ls="--", lw=1)
    ax.axhline(0, color="black", lw=0.5)
    ax.set_xticks(range(len(groups)), [g for g, _ in groups], fontsize=8)
    ax.set_ylabel("z = (tracer − reference) / std-error")
    ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle(f"map tracer against Mitsuba volpath ({tracer['settings']['materials']} materials per geometry)")
    fig.tight_layout()
    return _save(fig, img / "tracer-z.png")

