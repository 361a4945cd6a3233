"""`trimeter bench uncertainty`: does the reported ±1σ cover the truth 68 % of the time (±2σ: 95 %)?

Held-out materials (maps/heldout, as `bench fit` loads them: rendered off-grid, never map nodes) — by
default only their scored part (trimeter.bench.heldout.heldout_part): the calibration part is where the
map-error scale in the reported σ (LEAVE_ONE_OUT_SCALE) is chosen, with `--part calibration
--leave-one-out-scale a,b,…` (per scale, the given-stds rows' mean distance from the goal, goal_distance;
the nearest is marked) — each drawn several times with relative Gaussian noise of known size on I_b,
I_w, I_c, fitted by `lut` (fit()'s defaults) per device map and on both thicknesses together, and (`--sources`
table) by the instrument's fit from each map's device table (`trimeter fit --table`: native.TableFitter, its stds
from the table, trimeter.inversion.table_std; the map's error it carries is the one its table was built with,
whatever --leave-one-out-scale says). Two ways to fit each draw:
- given: the noise the draw got is handed to fit() as I_b_std, I_w_std, I_c_std (with the
  held-out renders' own MC std-error in quadrature on I_b, I_w: it is noise of known size too);
- fixed: fit()'s fixed noise model alone (σ_I = 0.005·I + 2e-4), whatever the noise was.
Per row: over the bins that carry no flag, the fraction whose truth lies within ±1σ and ±2σ of the
estimate, for α, σt and g (goal: 68 % ± 5 and 95 % ± 3), and the mean signed error over σ there (an
offset all the estimates share, which a first-order ±σ never covers); flagged bins counted by flag. A thickness
case draws each sample's real thickness off the map's by --thickness-rel-std and gives that std to
fit(): each sample (each thickness its own) is read as the same material at σt·ℓ'/ℓ on the map's
thickness ℓ (a slab's intensities depend on σt·ℓ, α and g only), the render's intensities moved by
the map's forward model between σt and σt·ℓ'/ℓ; the truth stays the material's. And the
map's own error: the noise-free fit's |error| over the σ fit() reports at the lowest noise level
(median and share above 1) — where that is ≳ 1, the map's error, not the noise, sets the coverage.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.bench import write_figures
from trimeter.bench.heldout import HELDOUT_PARTS
from trimeter.errors import InputError
from trimeter.inversion.flags import FitFlag

PARAMS = ("alpha", "sigma_t", "g")
GOAL_1, GOAL_2 = (0.68, 0.05), (0.95, 0.03)  # coverage goal ± tolerance at 1σ and 2σ


def register(bench_subparsers) -> None:
    p = bench_subparsers.add_parser("uncertainty", help="coverage of the reported ±1σ/±2σ on held-out materials",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--map", dest="maps", action="append",
                   help="map(s) (default: the shipped device maps with a held-out set)")
    p.add_argument("--noise", default="0.002,0.005,0.01", help="relative noise levels, comma-separated")
    p.add_argument("--draws", type=int, default=8, help="noise draws per held-out material (default 8)")
    p.add_argument("--thickness-rel-std", type=float, default=0.02,
                   help="relative std of the sample's thickness in the thickness case (default 0.02; 0: no case)")
    p.add_argument("--modes", default="given,fixed", help="given (stds handed to fit), fixed (fit's noise model)")
    p.add_argument("--sources", default="map,table",
                   help="what fits: map (the lut fit on the map), table (the instrument's fit from the map's device "
                        "table, stds from the table); default both")
    p.add_argument("--part", choices=HELDOUT_PARTS, default="scored",
                   help="which part of the held-out sets: scored (default; the map-error scale never saw it) or "
                        "calibration (where that scale is chosen)")
    p.add_argument("--leave-one-out-scale", default=None, metavar="S[,S…]",
                   help="map-error scale(s) to score instead of the shipped LEAVE_ONE_OUT_SCALE (several: a sweep, "
                        "for choosing it on --part calibration)")
    p.add_argument("--out", type=Path, default=Path("out/bench-uncertainty"))
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def coverage(estimate, std, truth, mask) -> tuple[float, float, int]:
    """(share within ±1σ, share within ±2σ, bins scored) over `mask` where the truth is finite. A bin
    with a NaN estimate or std counts as not covered: the fit said nothing usable there."""
    scored = mask & np.isfinite(truth)
    n = int(scored.sum())
    if n == 0:
        return float("nan"), float("nan"), 0
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(estimate[scored] - truth[scored]) / std[scored]
    z = np.where(np.isfinite(z) | np.isinf(std[scored]), z, np.inf)  # NaN → not covered; an infinite std covers
    return float(np.mean(z <= 1.0)), float(np.mean(z <= 2.0)), n


def mean_signed_z(estimate, std, truth, mask) -> float:
    """Mean of (estimate − truth)/σ over `mask`'s bins with a finite estimate and a finite, positive σ:
    an offset that the estimates share, which no ±σ drawn around each of them includes (NaN: nothing
    to score)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (estimate - truth) / std
    z = z[mask & np.isfinite(z) & np.isfinite(std) & (std > 0)]
    return float(np.mean(z)) if len(z) else float("nan")


def flag_counts(flags) -> dict[str, int]:
    flags = np.asarray(flags, dtype=np.int64)
    return {f.name: int(np.count_nonzero(flags & int(f))) for f in FitFlag if f and f.name and np.any(flags & int(f))}


def goal_met(c1: float, c2: float) -> bool:
    return abs(c1 - GOAL_1[0]) <= GOAL_1[1] and abs(c2 - GOAL_2[0]) <= GOAL_2[1]


def _maps(specs):
    from trimeter.bench.heldout import HELDOUT_DIR
    from trimeter.formats.appearance import AppearanceMap, find_map, shipped_maps

    if specs:
        return [AppearanceMap.load(find_map(s)) for s in specs]
    found = [AppearanceMap.load(p) for p in shipped_maps() if (HELDOUT_DIR / f"{p.stem}.held").is_file()]
    device = [m for m in found if m.recipe.get("geometry") == "device"]
    if not device:
        raise InputError("no shipped device map with a held-out set (maps/heldout/*.held); give --map")
    return device


class Case:
    """One map's held-out materials, tiled `draws` times: truth and noise-free intensities."""

    def __init__(self, amap, draws: int, part: str = "scored"):
        from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities, heldout_part

        _, _, h = heldout_for(amap)
        h = heldout_part(h, part)
        idx = np.tile(np.arange(len(h["alpha"])), draws)
        self.amap = amap
        self.truth = {k: h[k][idx] for k in PARAMS}
        I_b, I_w = heldout_intensities(h, *amap.reference_rhos)
        self.I = (I_b[idx], I_w[idx], heldout_collimated(amap, h)[idx])
        self.render_std = (h["std_b"][idx], h["std_w"][idx], np.zeros(len(idx)))

    def draw(self, level: float, rng):
        """Noisy intensities at relative noise `level` and the stds of the noise they carry."""
        return self.draw_from(self.I, level, rng)

    def draw_from(self, intensities, level: float, rng):
        noisy = tuple(x * (1.0 + level * rng.standard_normal(x.shape)) for x in intensities)
        stds = tuple(np.hypot(level * x, r) for x, r in zip(intensities, self.render_std, strict=True))
        return noisy, stds

    def at_thickness(self, ratio):
        """The intensities of these materials cut `ratio` × the map's thickness, read on the map: the
        renders moved by the forward model's change from σt to σt·ratio (its own error cancels)."""
        from trimeter.inversion.artifacts import load_artifacts

        grid = load_artifacts(self.amap).grid
        a, s, g = (self.truth[k] for k in PARAMS)
        rb, rw = self.amap.reference_rhos
        moved, here = grid.intensities(a, s * ratio, g, rb, rw), grid.intensities(a, s, g, rb, rw)
        return tuple(x + m - h for x, m, h in zip(self.I, moved, here, strict=True))


def _fit(cases, noisy, stds, mode, thickness_std=None, cache=None):
    from trimeter.inversion.artifacts import fit

    amaps = [c.amap for c in cases]
    I = [np.stack([n[i] for n in noisy]) for i in range(3)]
    kw: dict[str, Any] = {}
    if mode == "given":
        kw = dict(I_b_std=np.stack([s[0] for s in stds]), I_w_std=np.stack([s[1] for s in stds]),
                  I_c_std=np.stack([s[2] for s in stds]))
        if thickness_std is not None:
            kw["thickness_std_mm"] = thickness_std
    maps = amaps if len(amaps) > 1 else amaps[0]
    if len(amaps) == 1:
        I = [x[0] for x in I]
        kw = {k: (v[0] if isinstance(v, np.ndarray) else v) for k, v in kw.items()}
    return fit(maps, I[0], I[1], I[2], method="lut", cache=cache, **kw)


class TableCase:
    """A case's map's device table: the instrument's fit (native.TableFitter) and its stds (TableStds)."""

    def __init__(self, case: Case):
        from trimeter.inversion import native
        from trimeter.inversion.artifacts import map_table
        from trimeter.inversion.table_std import TableStds

        table = map_table(case.amap)
        self.fitter, self.stds, self.thickness_mm = native.TableFitter(table.to_bytes()), TableStds(table), \
            table.thickness_mm
        self.rhos = table.reference_rhos

    def fit(self, noisy, stds, mode, thickness_std=None):
        I_b, I_w, I_c = noisy
        rb, rw = (np.full(len(I_b), r) for r in self.rhos)
        kw: dict[str, Any] = {}
        if mode == "given":
            kw = dict(I_b_std=stds[0], I_w_std=stds[1], I_c_std=stds[2])
            if thickness_std is not None:
                kw["thickness_rel_std"] = thickness_std / self.thickness_mm
        return self.stds.result(self.fitter.fit(I_b, I_w, I_c, rb, rw), I_b, I_w, I_c, rb, rw, **kw)


def _sources(spec: str) -> list[str]:
    sources = [s.strip() for s in spec.split(",") if s.strip()]
    if not sources or any(s not in ("map", "table") for s in sources):
        raise InputError(f"--sources: {spec!r}: choose from map, table")
    return sources


def _row(label, level, mode, result, truth):
    clean = result.flags == 0
    row = {"case": label, "noise": level, "mode": mode, "bins": int(len(clean)), "unflagged": int(clean.sum()),
           "flags": flag_counts(result.flags)}
    for p in PARAMS:
        c1, c2, n = coverage(getattr(result, p), getattr(result, f"{p}_std"), truth[p], clean)
        row[p] = {"within_1sigma": c1, "within_2sigma": c2, "scored": n, "goal_met": goal_met(c1, c2),
                  "mean_z": mean_signed_z(getattr(result, p), getattr(result, f"{p}_std"), truth[p], clean)}
    return row


def run(args) -> int:
    from trimeter.model import grid

    scales = _scales(args.leave_one_out_scale)
    reports = []
    for scale in scales:
        with _leave_one_out_scale(scale):
            print(f"\nheld-out sets: their {args.part} part; map-error scale LEAVE_ONE_OUT_SCALE = "
                  f"{grid.LEAVE_ONE_OUT_SCALE:g}" + (" (shipped)" if scale is None else ""))
            report = measure(args)
            _print(report["rows"], report["map_error"])
            reports.append(report)
    if len(reports) > 1:
        _print_sweep(reports)
    write_figures(reports[0] if len(reports) == 1 else {"sweep": reports}, args.out / "results.json")
    return 0


def _scales(spec: str | None) -> list[float | None]:
    if spec is None:
        return [None]
    try:
        scales = [float(x) for x in spec.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--leave-one-out-scale: {spec!r} is not a comma-separated list of numbers") from None
    if not scales or any(not (0 <= x < 10) for x in scales):
        raise InputError("--leave-one-out-scale: each scale must be in [0, 10)")
    return list(scales)


@contextlib.contextmanager
def _leave_one_out_scale(scale: float | None):
    """The map-error scale the maps loaded inside are given (None: the shipped one). The bench loads its maps
    into a cache of its own (measure), so the shipped process-wide ones are not touched."""
    from trimeter.model import grid

    saved = grid.LEAVE_ONE_OUT_SCALE
    if scale is not None:
        grid.LEAVE_ONE_OUT_SCALE = scale
    try:
        yield
    finally:
        grid.LEAVE_ONE_OUT_SCALE = saved


def goal_distance(rows) -> float:
    """Mean of |±1σ share − 68 %| + |±2σ share − 95 %| over the parameters and the rows fitted with the noise's
    stds given (where the σ fit() reports can be right, the map's error term is what is left to set; the fixed
    noise model's rows measure that model): how a map-error scale is chosen."""
    given = [r for r in rows if r["mode"] == "given"] or rows
    d = [abs(r[p]["within_1sigma"] - GOAL_1[0]) + abs(r[p]["within_2sigma"] - GOAL_2[0]) for r in given for p in PARAMS]
    return float(np.nanmean(d))


def _print_sweep(reports) -> None:
    distances = [goal_distance(r["rows"]) for r in reports]
    best = int(np.nanargmin(distances))
    print("\nmap-error scale sweep: mean |1σ share − 68 %| + |2σ share − 95 %| over the rows with given stds and "
          "the parameters (goal_distance)")
    for i, (r, d) in enumerate(zip(reports, distances, strict=True)):
        mark = "  ← nearest" if i == best else ""
        print(f"   LEAVE_ONE_OUT_SCALE {r['leave_one_out_scale']:<6g} {d * 100:6.2f} points{mark}")


def measure(args) -> dict:
    """Every figure `run` prints: {"kernel", "draws", "rows": one per (case, noise, mode) with coverage
    and mean z per parameter and flag counts, "map_error": the map's own error per (case, mode)}."""
    from trimeter.inversion import native

    try:
        levels = [float(x) for x in args.noise.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--noise: {args.noise!r} is not a comma-separated list of numbers") from None
    if not levels or any(not (0 < x < 0.5) for x in levels):
        raise InputError("--noise: levels must be in (0, 0.5)")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in ("given", "fixed") for m in modes):
        raise InputError(f"--modes: {args.modes!r}: choose from given, fixed")
    if args.draws < 1:
        raise InputError("--draws must be ≥ 1")
    if not (0 <= args.thickness_rel_std < 0.5):
        raise InputError("--thickness-rel-std must be in [0, 0.5)")
    sources = _sources(getattr(args, "sources", "map"))
    from trimeter.inversion.artifacts import ArtifactCache
    from trimeter.model import grid

    print(f"inversion kernel: {native.status()}")
    part = getattr(args, "part", "scored")
    cache = ArtifactCache()  # the maps' error terms at this run's LEAVE_ONE_OUT_SCALE
    cases = [Case(m, args.draws, part) for m in _maps(args.maps)]
    print(f"held-out materials ({part} part): " + ", ".join(f"{c.amap.name} {len(c.truth['alpha']) // args.draws}"
                                                            for c in cases))
    # (label, cases, the fit of one draw: (noisy, stds, mode, thickness std or None) → FitResult)
    groups = []
    if "map" in sources:
        groups = [(c.amap.name, [c], _map_fitter([c], cache)) for c in cases]
        if len(cases) == 2 and all(np.array_equal(cases[0].truth[k], cases[1].truth[k]) for k in PARAMS):
            groups.append(("both thicknesses", cases, _map_fitter(cases, cache)))
    if "table" in sources:  # one thickness per table: the instrument fits one sample
        groups += [(f"{c.amap.name} table", [c], _table_fitter(TableCase(c))) for c in cases]
    rng = np.random.default_rng(args.seed)
    rows, bias = [], []
    for label, group, fit_draw in groups:
        truth = group[0].truth
        clean = fit_draw([c.I for c in group], [c.render_std for c in group], "fixed", None)
        for level in levels:
            draws = [c.draw(level, rng) for c in group]
            noisy, stds = [d[0] for d in draws], [d[1] for d in draws]
            for mode in modes:
                result = fit_draw(noisy, stds, mode, None)
                rows.append(_row(label, level, mode, result, truth))
                if level == min(levels):
                    bias.append(_map_error(label, mode, clean, result, truth))
        if args.thickness_rel_std > 0:
            level = levels[len(levels) // 2]
            # each sample's real thickness ℓ' off the map's, drawn per sample: two samples are two cuts
            draws = [c.draw_from(c.at_thickness(1.0 + args.thickness_rel_std * rng.standard_normal(len(c.I[0]))),
                                 level, rng) for c in group]
            noisy, stds = [d[0] for d in draws], [d[1] for d in draws]
            for mode in modes:
                thickness_std = [args.thickness_rel_std * c.amap.thickness_mm for c in group]
                result = fit_draw(noisy, stds, mode, thickness_std if len(group) > 1 else thickness_std[0])
                rows.append(_row(f"{label}, ℓ ±{args.thickness_rel_std:.0%}", level, mode, result, truth))
    return {"kernel": native.status(), "draws": args.draws, "heldout_part": part,
            "heldout_materials": {c.amap.name: len(c.truth["alpha"]) // args.draws for c in cases},
            "leave_one_out_scale": grid.LEAVE_ONE_OUT_SCALE, "rows": rows, "map_error": bias}


def _map_fitter(group, cache):
    return lambda noisy, stds, mode, thickness_std: _fit(group, noisy, stds, mode, thickness_std, cache=cache)


def _table_fitter(table: TableCase):
    return lambda noisy, stds, mode, thickness_std: table.fit(noisy[0], stds[0], mode, thickness_std)


def _map_error(label, mode, clean, noisy_result, truth) -> dict:
    """The noise-free fit's error over the σ reported at the lowest noise level, on unflagged bins."""
    out = {"case": label, "mode": mode}
    ok = (clean.flags == 0) & (noisy_result.flags == 0)
    for p in PARAMS:
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.abs(getattr(clean, p) - truth[p]) / getattr(noisy_result, f"{p}_std")
        r = r[ok & np.isfinite(r)]
        out[p] = {"median": float(np.median(r)) if len(r) else float("nan"),
                  "share_above_1": float(np.mean(r > 1)) if len(r) else float("nan")}
    return out


def _print(rows, bias):
    print(f"\ncoverage over unflagged bins: share of truths within ±1σ / ±2σ (goal {GOAL_1[0]:.0%} ± {GOAL_1[1]:.0%} / "
          f"{GOAL_2[0]:.0%} ± {GOAL_2[1]:.0%}; * = met)")
    head = f"   {'case':<34}{'noise':>6} {'stds':<6}{'unflagged':>10}"
    print(head + "".join(f"{p + ' 1σ':>11}{'2σ':>7}" for p in ("α", "σt", "g")))
    for r in rows:
        line = f"   {r['case']:<34}{r['noise'] * 100:>5.1f}% {r['mode']:<6}{r['unflagged']:>5}/{r['bins']:<4}"
        for p in PARAMS:
            c = r[p]
            mark = "*" if c["goal_met"] else " "
            line += f"{c['within_1sigma'] * 100:>10.1f}%{c['within_2sigma'] * 100:>6.1f}%{mark}"
        print(line)
    print("\nmean signed (estimate − truth) / σ over the same bins: an offset the estimates share, which their ±σ "
          "does not include\n(0.3 costs the ±1σ share ~2 points; combining thicknesses shrinks σ, not the offset)")
    print(f"   {'case':<34}{'noise':>6} {'stds':<6}" + "".join(f"{p:>8}" for p in ("α", "σt", "g")))
    for r in rows:
        print(f"   {r['case']:<34}{r['noise'] * 100:>5.1f}% {r['mode']:<6}"
              + "".join(f"{r[p]['mean_z']:>+8.2f}" for p in PARAMS))
    print("\nflagged bins (not scored above), per flag:")
    seen = set()
    for r in rows:
        key = (r["case"], r["mode"])
        if key in seen:
            continue
        seen.add(key)
        flags = ", ".join(f"{k} {v}" for k, v in r["flags"].items()) or "none"
        print(f"   {r['case']:<34}{r['noise'] * 100:>5.1f}% {r['mode']:<6} {flags}")
    print("\nthe map's own error: noise-free fit |error| / σ reported at the lowest noise level (unflagged bins)")
    print(f"   {'case':<34}{'stds':<7}" + "".join(f"{p + ' median':>12}{'>1':>7}" for p in ("α", "σt", "g")))
    for b in bias:
        print(f"   {b['case']:<34}{b['mode']:<7}" + "".join(
            f"{b[p]['median']:>12.2f}{b[p]['share_above_1'] * 100:>6.0f}%" for p in PARAMS))
