#!/usr/bin/env python3
"""The self-sufficient device table (`.tlut` v2, trimeter.formats.device_table): build it from a map and
its in-scattering table, fit from it alone, and score that fit on the map's held-out set with
`trimeter bench fit`'s scoring.

    .venv/bin/python tools/device_table_study.py build MAP [-o FILE] [--n-inverse N]
    .venv/bin/python tools/device_table_study.py measure MAP [MAP…] [--noise 0,0.005]
    .venv/bin/python tools/device_table_study.py budget MAP [MAP…]

`build` prints the bytes per part. `measure` prints, per map and noise level, α abs / σt relative /
g abs (α ≥ 0.5) p50 and p95 over the measurable gamut for: the map's own lut fit (`trimeter.fit`,
the map file with its .tlut and .tins), the v2 table alone with its forward model sampled onto the
refined grid at load (the host path), the same with the polish evaluating the compact model on the
fly (the device path: numpy, and C from the file's bytes where the kernel is built), and the
polish-free table guess. `budget` prints what the bytes buy:
the same fit with the forward coefficients at float64/32/16, L unquantized and smaller inverse grids.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from trimeter.model.compact import CompactForward
from trimeter.model.grid import ForwardGrid, SigmaCell

if TYPE_CHECKING:
    from trimeter.domain.parameters import FitResult
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.formats.device_table import DeviceTable
    from trimeter.inversion.table_model import DeviceTableModel

    # one way of fitting (I_b, I_w, I_c) bins, as measure() and budget() score them
    Fitter = Callable[[np.ndarray, np.ndarray, np.ndarray], FitResult | SimpleNamespace]
    Say = Callable[[str], object]


# ------------------------------------------------------------------------------------------- build
def build(amap: AppearanceMap, n_inverse: int | None = None) -> DeviceTable:
    """The v2 table of an AppearanceMap (the pipeline's tlut stage: trimeter.inversion.table_builder.build_from_map)."""
    from trimeter.inversion.table_builder import build_from_map

    return build_from_map(amap, n_inverse)


# --------------------------------------------------------------------------------------------- fit
def table_model(table: DeviceTable, forward: CompactForward | None = None,
                inscatter_L: np.ndarray | None = None) -> DeviceTableModel:
    """The fit's view of the table alone (DeviceTableModel); forward, inscatter_L: other coefficients or
    L than the table's (for the precision study)."""
    from trimeter.inversion.lut import TableInverter
    from trimeter.inversion.table_model import DeviceTableModel

    if forward is None and inscatter_L is None:
        return DeviceTableModel(table)
    source = table
    if forward is not None:  # the same table with another forward model: its node values overridden
        source = copy.copy(table)
        vars(source)["coefficients_grid"] = forward.nodes()
    axes = tuple(np.asarray(a, dtype=np.float64) for a in (table.alpha, table.log_sigma_t, table.g))
    return DeviceTableModel(table, TableInverter(source, inscatter=table.inscatter_table(inscatter_L),
                                                 model_variance=(table.model_variance(), axes)))


class OnTheFlyGrid(ForwardGrid):
    """A ForwardGrid whose A, B, C come from the compact model at each point (the device's polish), not
    from its refined cells; `grid`'s nodes, in-scattering and model-error tables only serve the clamps
    and the cell lookups of those tables."""

    def __init__(self, grid: ForwardGrid, compact: CompactForward) -> None:
        super().__init__(grid.alpha, grid.log_sigma_t, grid.g, grid.coefficients_grid, setup=grid.setup,
                         mc_stderr=grid.mc_stderr)
        self.compact = compact
        self.inscatter_grid, self.model_var = grid.inscatter_grid, grid.model_var

    def coefficients(self, alpha: np.ndarray, cell: SigmaCell, g: np.ndarray,
                     with_sigma_derivative: bool = False) -> tuple[np.ndarray, ...]:
        value, d_a, d_ls, d_g = self.compact.evaluate(alpha, cell.log_sigma_t, g)
        return (value, d_a, d_g, d_ls) if with_sigma_derivative else (value, d_a, d_g)

    def alpha_g_cells(self, alpha: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # the compact model is smooth across cells: a step never needs evaluating again for that
        return np.zeros(len(alpha), dtype=np.intp), np.zeros(len(g), dtype=np.intp)


def on_the_fly_inverter(table: DeviceTable) -> DeviceTableModel:
    """The table's fit model with the polish on the compact model itself (fit_table runs it on the
    numpy kernel: the compiled one reads the refined cells)."""
    return on_the_fly_model(table)


def fit_table(table: DeviceTable, model: DeviceTableModel, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray,
              rho_b: np.ndarray | None = None, rho_w: np.ndarray | None = None, **options: Any) -> FitResult:
    """trimeter.inversion.api.fit's lut path on a fit model of `table` (DeviceTableModel(table), table_model
    or on_the_fly_inverter), on the numpy kernel where the polish evaluates the compact model."""
    from trimeter.inversion.api import fit
    from trimeter.inversion.kernel import NumpyKernel

    if isinstance(model.grid, OnTheFlyGrid):
        options.setdefault("kernel", NumpyKernel())
    return fit(model, I_b, I_w, I_c, rho_b, rho_w, method="lut", **options)


def on_the_fly_model(table: DeviceTable) -> DeviceTableModel:
    """The table's fit model with the polish on the compact model itself (run it on the numpy kernel:
    the compiled one reads the refined cells)."""
    from trimeter.inversion.table_model import DeviceTableModel

    model = DeviceTableModel(table)
    model.inverter.grid = OnTheFlyGrid(model.inverter.grid, table.forward())
    return model


# ----------------------------------------------------------------------------------------- measure
# bench fit's figures (trimeter.bench.fit_scoring.error_figures); "well": the well-conditioned subset, "det": the bins
# the fit does not flag UNDERDETERMINED
_COLUMNS = (("α p50", "alpha_p50"), ("α p95", "alpha_p95"), ("σt rel p50", "sigma_rel_p50"),
            ("σt rel p95", "sigma_rel_p95"), ("g p50", "g_p50"), ("g p95", "g_p95"), ("α p95 well", "alpha_p95_well"),
            ("g p95 well", "g_p95_well"), ("α p95 det", "alpha_p95_determined"), ("g p95 det", "g_p95_determined"))
def measure(amap: AppearanceMap, noise_levels: Sequence[float], seed: int = 0,
            say: Say = print) -> list[dict[str, Any]]:
    from trimeter.bench.fit_scoring import error_budget, error_figures
    from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities
    from trimeter.inversion import native
    from trimeter.inversion.table_model import DeviceTableModel
    from trimeter.inversion.artifacts import fit as fit_maps

    t0 = time.perf_counter()
    table = build(amap)
    built = time.perf_counter() - t0
    say(f"\n== {amap.name}: v2 table {table.size_bytes} bytes (built in {built:.1f} s)")
    for part, nbytes in table.sizes().items():
        say(f"   {part:12s} {nbytes:7d}")
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    truth = (h["alpha"], h["sigma_t"], h["g"])
    budget = error_budget(amap, h, rb, rw)
    I_b0, I_w0 = heldout_intensities(h, rb, rw)
    I_c0 = heldout_collimated(amap, h)
    t0 = time.perf_counter()
    host = DeviceTableModel(table)
    say(f"   fit model from the table alone: {time.perf_counter() - t0:.2f} s")
    fly = on_the_fly_model(table)
    variants: dict[str, Fitter] = {
        "map lut p≤8": lambda ib, iw, ic: fit_maps(amap, ib, iw, ic, method="lut"),
        "table (refined at load) p≤8": lambda ib, iw, ic: fit_table(table, host, ib, iw, ic),
        "table (on the fly) p≤8": lambda ib, iw, ic: fit_table(table, fly, ib, iw, ic),
        "table guess p0": lambda ib, iw, ic: fit_table(table, host, ib, iw, ic, polish=0, polish_tol=0.0),
    }
    if native.available():  # the C fit from the table's bytes, as the firmware runs it (here in double)
        fitter = native.TableFitter(table.to_bytes())
        variants["table in C (on the fly) p≤8"] = lambda ib, iw, ic: _c_result(fitter.fit(ib, iw, ic))
    rng = np.random.default_rng(seed)
    cases = []
    for level in noise_levels:
        noisy = tuple(x * (1 + level * rng.standard_normal(x.shape)) if level else x for x in (I_b0, I_w0, I_c0))
        cases.append((f"rendered, noise {level * 100:g} %", noisy))
    cases.append(("map-exact", budget["map_exact"]))
    rows = []
    for label, (ib, iw, ic) in cases:
        say(f"   {label}\n   {'':30s}" + "".join(f"{title:>11s}" for title, _ in _COLUMNS) + f"{'ms/1024':>11s}")
        tile = np.resize(np.arange(len(ib)), 1024)
        tiled = (ib[tile], iw[tile], ic[tile])
        for name, run in variants.items():
            res = run(ib, iw, ic)
            ms = _warm_ms(partial(run, *tiled))
            st = error_figures(res, truth, budget)
            rows.append({"map": amap.name, "case": label, "variant": name, "ms_per_1024": ms, **st})
            say(f"   {name:30s}" + "".join(f"{st[key]:11.2e}" if "sigma" in key else f"{st[key]:11.4f}"
                                                for _, key in _COLUMNS) + f"{ms:11.2f}")
    return rows


def _c_result(columns: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> SimpleNamespace:
    """native.TableFitter's (α, σt, g, flags) as the scoring reads a FitResult (it returns no stds)."""
    alpha, sigma_t, g, flags = columns
    return SimpleNamespace(alpha=alpha, sigma_t=sigma_t, g=g, flags=flags, alpha_std=np.full(len(alpha), np.nan))


def budget(amap: AppearanceMap, say: Say = print) -> list[dict[str, Any]]:
    """What the slot's bytes buy: fits from the table (host path, noise-free rendered held-out) with the
    forward coefficients at other precisions, with L unquantized, and with smaller inverse grids."""
    from trimeter.bench.fit_scoring import error_budget, error_figures
    from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities
    from trimeter.inversion.api import fit
    from trimeter.formats.device_table import MAX_BYTES, table_size

    table = build(amap)
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    truth = (h["alpha"], h["sigma_t"], h["g"])
    scoring = error_budget(amap, h, rb, rw)
    I_b, I_w = heldout_intensities(h, rb, rw)
    I_c = heldout_collimated(amap, h)
    exact = compact_from_map(amap)
    na, ns, ng = amap.A.shape
    coef_bytes = 3 * na * ns * ng
    rounded = {name: exact.coefficients.astype(dtype).astype(np.float64) for name, dtype in
               (("float16", np.float16), ("float32", np.float32))}
    # (variant, table, forward coefficients, L, their bytes; None: the table's own)
    cases: list[tuple[str, DeviceTable, CompactForward | None, np.ndarray | None, int | None]] = [
             ("as stored: coefficients u16, L u16", table, None, None, 2 * coef_bytes),
             ("coefficients float64 (unquantized)", table, exact, None, 8 * coef_bytes),
             ("coefficients float32", table, _with_coefficients(exact, rounded["float32"]), None, 4 * coef_bytes),
             ("coefficients float16", table, _with_coefficients(exact, rounded["float16"]), None, 2 * coef_bytes),
             ("L float64 (unquantized)", table, None, amap.inscatter.L, None)]
    for n_inv in (24, 16, 8):
        cases.append((f"inverse grid {n_inv}×{n_inv}", build(amap, n_inv), None, None, None))
    say(f"\n== {amap.name}: noise-free rendered held-out, table refined at load, lut p≤8 (* over the slot)")
    say(f"   {'variant':38s}{'coef bytes':>11s}{'file bytes':>11s} " + "".join(f"{t:>11s}" for t, _ in _COLUMNS[:6])
        + f"{'ms/1024':>10s}")
    rows = []
    tile = np.resize(np.arange(len(I_b)), 1024)
    for name, tab, forward, L, nbytes in cases:
        model = table_model(tab, forward, L)
        res = fit(model, I_b, I_w, I_c, method="lut")
        ms = _warm_ms(partial(fit, model, I_b[tile], I_w[tile], I_c[tile], method="lut"))
        st = error_figures(res, truth, scoring)
        # the file these coefficients would make with this inverse grid (over the slot: would not fit)
        nu, nt, nv = tab.inscatter.shape
        size = (table_size(na, ns, ng, tab.inv_alpha_q.shape[1], nu, nt, nv, len(tab._geometry_bytes()))
                + (nbytes or 2 * coef_bytes) - 2 * coef_bytes)
        rows.append({"map": amap.name, "variant": name, "file_bytes": size, "ms_per_1024": ms, **st})
        say(f"   {name:38s}{nbytes or 2 * coef_bytes:11d}{size:11d}{'*' if size > MAX_BYTES else ' '}"
            + "".join(f"{st[key]:11.2e}" if "sigma" in key else f"{st[key]:11.4f}" for _, key in _COLUMNS[:6])
            + f"{ms:9.2f}")
    return rows


def compact_from_map(amap: AppearanceMap) -> CompactForward:
    values = np.stack([amap.A, amap.B, amap.C], axis=-1).astype(np.float64)
    return CompactForward.from_nodes(np.array(amap.alpha, np.float64), np.log(np.array(amap.sigma_t, np.float64)),
                                     np.array(amap.g, np.float64), values)


def _with_coefficients(model: CompactForward, coefficients: np.ndarray) -> CompactForward:
    return CompactForward(model.alpha, model.log_sigma_t, model.g, coefficients)


def _warm_ms(fn: Callable[[], object], repeats: int = 5) -> float:
    """Best of `repeats` calls in ms, after an untimed one (as for a batch of spectra)."""
    fn()
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main(argv: Sequence[str] | None = None) -> int:
    from trimeter.errors import TrimeterError
    from trimeter.formats.appearance import AppearanceMap, find_map

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="write the v2 table of a map")
    b.add_argument("map", help="map file or shipped map name")
    b.add_argument("-o", "--output", type=Path, help="output file (default: <map>.v2.tlut in the current directory)")
    b.add_argument("--n-inverse", type=int, help="inverse grid side (default: the largest that fits the slot)")
    bud = sub.add_parser("budget", help="accuracy against the precision and inverse-grid size the bytes buy")
    bud.add_argument("maps", nargs="+", help="map files or shipped map names")
    m = sub.add_parser("measure", help="held-out accuracy of fits from the v2 table alone")
    m.add_argument("maps", nargs="+", help="map files or shipped map names")
    m.add_argument("--noise", default="0", help="comma-separated relative noise levels (default 0)")
    m.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        if args.command == "build":
            amap = AppearanceMap.load(find_map(args.map))
            table = build(amap, args.n_inverse)
            out = table.save(args.output or Path(f"{amap.name}.v2.tlut"))
            print(f"{out}: {table.size_bytes} bytes")
            for part, nbytes in table.sizes().items():
                print(f"   {part:12s} {nbytes:7d}")
        elif args.command == "budget":
            for spec in args.maps:
                budget(AppearanceMap.load(find_map(spec)))
        else:
            try:
                levels = [float(x) for x in args.noise.split(",")]
            except ValueError:
                ap.error(f"--noise: not a comma-separated list of numbers: {args.noise!r}")
            for spec in args.maps:
                measure(AppearanceMap.load(find_map(spec)), levels, args.seed)
    except TrimeterError as exc:
        print(f"device_table_study: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
