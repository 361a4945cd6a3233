"""What a model the shipped maps leave out costs the fits on a device map's held-out set, if that model is right:
- `--model series`: the bounce series in place of the maps' single return coefficient C;
- `--model polarisation`: the two polarisations tracked at the interfaces in place of unpolarised Fresnel (a map
  traced without them; the shipped device maps track them).
Each (σt, g) column of the held-out set is traced twice from one seed, as the maps trace it and with the model.
With the series, A and B are bit for bit the same and only C differs (C matched to the series at the white);
with polarisation the walks part where a reflection's odds differ, so the pair shares much of its noise,
not all. The difference in I_b, I_w is added to the held-out set's intensities, and both sets are fitted with
the map (lut, trimeter.fit's defaults) and scored as `trimeter bench fit` scores its noise-free rows. I_c is
left as it is (at normal incidence both polarisations see the same Fresnel factors; the in-scattered part of
I_c is not re-traced).

    .venv/bin/python tools/model_effect_check.py maps/device-n1.5-l0.8.tmap --model series --paths 8388608 \
        --out out/series-effect-l0.8.json        # ~15-35 s per column at 8M paths, 64 columns

Resumable: columns already in --out (same map, model, paths, orders and seed) are not traced again. The
paired difference still carries noise (the series: the two C's, background paths against the series' own),
which the report shows as the clear materials' mean ± its std-error.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so")

CLEAR_TAU = 0.5  # σt·ℓ below it: a clear sample, where the background's light matters most
MODELS = {"series": "the bounce series in place of one C", "polarisation": "polarisation tracked at the faces"}


def trace_columns(amap, h, model: str, paths: int, orders: int, seed: int, done: dict, save,
                  limit: int | None = None) -> dict:
    """The paired difference per held-out column (keyed by its index among the set's unique (σt, g)), for the
    first `limit` columns in the set's order (None: all)."""
    from trimeter.forward.transport import N_BACKGROUND_ORDERS, Stack, k_max_for, trace_column
    from trimeter.model.response import background_response

    # the set-up as the map was traced (its stored recipe), as tools/make_heldout.py traces its recipe
    stack = Stack.from_recipe(amap.recipe["geometry"], amap.recipe["geometry_params"], amap.n, amap.thickness_mm)
    k_max = k_max_for(float(amap.alpha[-1]), float(amap.recipe["sampling"]["truncation"]))
    as_maps = bool(amap.recipe.get("polarisation", False))
    orders_with = orders if model == "series" else N_BACKGROUND_ORDERS
    rb, rw = amap.reference_rhos
    uniq, first, column = np.unique(np.column_stack([h["sigma_t"], h["g"]]), axis=0, return_index=True,
                                    return_inverse=True)
    column = column.ravel()
    order = np.argsort(first)[:limit]
    for n, c in enumerate(order):
        if str(int(c)) in done:
            continue
        s, g = (float(v) for v in uniq[c])
        idx = np.flatnonzero(column == c)
        alpha = h["alpha"][idx]
        started = time.perf_counter()
        maps = trace_column(stack, s, g, paths, seed + int(c), k_max, polarisation=as_maps)
        t_maps = time.perf_counter() - started
        started = time.perf_counter()
        other = trace_column(stack, s, g, paths, seed + int(c), k_max, background_orders=orders_with,
                             polarisation=as_maps or model == "polarisation")
        t_model = time.perf_counter() - started
        (A1, B1, C1), (A2, B2, C2) = maps.abc(alpha), other.abc(alpha)
        done[str(int(c))] = {
            "idx": idx.tolist(), "sigma_t": s, "g": g, "alpha": alpha.tolist(),
            "dIb": (background_response(A2, B2, C2, rb) - background_response(A1, B1, C1, rb)).tolist(),
            "dIw": (background_response(A2, B2, C2, rw) - background_response(A1, B1, C1, rw)).tolist(),
            "Iw": background_response(A1, B1, C1, rw).tolist(),
            "AB_same": bool(np.array_equal(A1, A2) and np.array_equal(B1, B2)),
            "t_maps": t_maps, "t_model": t_model}
        save()
        print(f"\r{n + 1}/{len(order)} columns traced ({t_maps:.1f} s + {t_model:.1f} s)", end="", file=sys.stderr,
              flush=True)
    print(file=sys.stderr)
    return done


def summarise(amap, h, columns: dict, fit_map=None) -> dict:
    """The differences, the fitted shifts and both sets' noise-free scores, over the materials traced; the set
    with the model fitted with `fit_map` where given (e.g. a map built with the model), else with the map."""
    import trimeter
    from trimeter.bench.fit_scoring import error_budget, error_figures, percentile
    from trimeter.bench.fit_variants import DEFAULT_POLISH
    from trimeter.bench.heldout import heldout_collimated, heldout_intensities

    rb, rw = amap.reference_rhos
    n_set = len(h["alpha"])
    dIb, dIw, Iw = np.full(n_set, np.nan), np.full(n_set, np.nan), np.full(n_set, np.nan)
    for rec in columns.values():
        dIb[rec["idx"]], dIw[rec["idx"]], Iw[rec["idx"]] = rec["dIb"], rec["dIw"], rec["Iw"]
    traced = ~np.isnan(dIw)  # all of them, unless --columns stopped short
    h = {k: v[traced] for k, v in h.items()}
    dIb, dIw, Iw = dIb[traced], dIw[traced], Iw[traced]
    truth = (h["alpha"], h["sigma_t"], h["g"])
    I_b, I_w = heldout_intensities(h, rb, rw)
    I_c = heldout_collimated(amap, h)
    budget = error_budget(amap, h, rb, rw)
    as_traced = trimeter.fit(amap, I_b, I_w, I_c, method="lut", **DEFAULT_POLISH)
    with_model = trimeter.fit(fit_map or amap, I_b + dIb, I_w + dIw, I_c, method="lut", **DEFAULT_POLISH)
    measurable, g_scored = budget["measurable"], budget["g_scored"]
    clear = measurable & (h["sigma_t"] * amap.thickness_mm < CLEAR_TAU)
    rest = measurable & ~clear
    rel = dIw / Iw
    shift = {"alpha": np.abs(with_model.alpha - as_traced.alpha)[measurable],
             "sigma_rel": np.abs(with_model.sigma_t / as_traced.sigma_t - 1)[measurable],
             "g": np.abs(with_model.g - as_traced.g)[g_scored]}
    signed = (with_model.alpha - as_traced.alpha)[clear]

    def mean_sem(x: np.ndarray) -> tuple[float, float]:
        mean = float(np.mean(x)) if len(x) else float("nan")
        return mean, float(np.std(x, ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")

    return {
        "materials": int(traced.sum()), "set_materials": n_set, "measurable": int(measurable.sum()),
        "clear": int(clear.sum()),
        "dIw_rel": {"clear_mean_sem": mean_sem(rel[clear]), "clear_p95_abs": percentile(np.abs(rel[clear]), 95),
                    "rest_mean_sem": mean_sem(rel[rest]), "rest_p95_abs": percentile(np.abs(rel[rest]), 95)},
        "dIb_rel": {"clear_mean_sem": mean_sem((dIb / I_b)[clear]), "rest_mean_sem": mean_sem((dIb / I_b)[rest])},
        "shift": {f"{k}_{q}": percentile(v, q) for k, v in shift.items() for q in (50, 95)},
        "clear_alpha_shift_mean_sem": mean_sem(signed),
        "scores": {"as_traced": error_figures(as_traced, truth, budget),
                   "with_model": error_figures(with_model, truth, budget)},
        "trace_seconds": {"maps": sum(c["t_maps"] for c in columns.values()),
                          "model": sum(c["t_model"] for c in columns.values())},
        "AB_same_everywhere": all(c["AB_same"] for c in columns.values()),
        "fitted_with": (fit_map or amap).name,
    }


def report(name: str, model: str, paths: int, orders: int, s: dict) -> None:
    d, sh, sc, t = s["dIw_rel"], s["shift"], s["scores"], s["trace_seconds"]
    what = f"series to {orders} orders" if model == "series" else "polarisation"
    print(f"{name}, {MODELS[model]}: {s['materials']} of {s['set_materials']} held-out materials "
          f"({s['measurable']} measurable, {s['clear']} clear: σt·ℓ < {CLEAR_TAU:g}), {paths} paths per column; "
          f"A and B the same in both traces: {s['AB_same_everywhere']}")
    (cm, cs), (rm, rs) = d["clear_mean_sem"], d["rest_mean_sem"]
    (bcm, bcs), (brm, brs) = s["dIb_rel"]["clear_mean_sem"], s["dIb_rel"]["rest_mean_sem"]
    print(f"  I_w, {what} − as the maps, relative: clear mean {cm:+.2e} ± {cs:.1e} (p95 |·| {d['clear_p95_abs']:.2e}); "
          f"the rest {rm:+.2e} ± {rs:.1e} (p95 |·| {d['rest_p95_abs']:.2e})")
    print(f"  I_b, relative: clear mean {bcm:+.2e} ± {bcs:.1e}; the rest {brm:+.2e} ± {brs:.1e}")
    am, asem = s["clear_alpha_shift_mean_sem"]
    print(f"  fitted shift, measurable: |Δα| p50 {sh['alpha_50']:.4f} p95 {sh['alpha_95']:.4f}; |Δσt|/σt p50 "
          f"{sh['sigma_rel_50']:.2%} p95 {sh['sigma_rel_95']:.2%}; |Δg| (α ≥ 0.5) p50 {sh['g_50']:.4f} p95 "
          f"{sh['g_95']:.4f}; clear materials' Δα mean {am:+.4f} ± {asem:.4f}")
    fitted_with = "" if s["fitted_with"] == name else f", fitted with {s['fitted_with']}"
    print("  noise-free fit errors:")
    for label, key in (("truth as the maps trace it", "as_traced"), (f"truth with {what}{fitted_with}", "with_model")):
        r = sc[key]
        print(f"    {label}: α p95 {r['alpha_p95']:.4f} (well-conditioned "
              f"{r['alpha_p95_well']:.4f}), σt p95 {r['sigma_rel_p95']:.2%}, g p95 {r['g_p95']:.4f} "
              f"(well-conditioned {r['g_p95_well']:.4f})")
    print(f"  trace time at the same path count: as the maps {t['maps']:.0f} s, {what} {t['model']:.0f} s "
          f"(×{t['model'] / t['maps']:.2f}; not a build time: a build traces each column to its criterion)")


def main(argv: list[str] | None = None) -> int:
    from trimeter.bench.heldout import heldout_for
    from trimeter.errors import InputError
    from trimeter.formats.appearance import AppearanceMap

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, help="a device map (.tmap) with a held-out set")
    p.add_argument("--model", choices=sorted(MODELS), default="series")
    p.add_argument("--paths", type=int, default=1 << 23, help="detector paths per trace")
    p.add_argument("--orders", type=int, default=5, help="background orders the series traces")
    p.add_argument("--seed", type=int, default=1000, help="column c is traced from seed + c")
    p.add_argument("--columns", type=int, help="trace only the set's first N columns (a quick look)")
    p.add_argument("--fit-map", type=Path, help="fit the set with the model with this map (e.g. one built with it)")
    p.add_argument("--out", type=Path, required=True, help="JSON: the columns' differences and the summary")
    args = p.parse_args(argv)
    try:
        amap = AppearanceMap.load(args.map)
        if amap.recipe.get("geometry") != "device":
            raise InputError("a device map: the ideal geometry's background is unbounded (one C is exact there) and "
                             "its held-out set is adding-doubling's")
        if args.model == "polarisation" and amap.recipe.get("polarisation"):
            raise InputError(f"{amap.name} was traced with polarisation already: nothing to compare")
        if args.paths < 1024 or not 3 <= args.orders <= 16 or (args.columns is not None and args.columns < 1):
            raise InputError("needs at least 1024 paths, 3-16 orders and at least one column")
        _, _, h = heldout_for(amap)
        fit_map = AppearanceMap.load(args.fit_map) if args.fit_map else None
        if fit_map is not None and (fit_map.recipe.get("geometry"), fit_map.n, fit_map.thickness_mm) != (
                amap.recipe.get("geometry"), amap.n, amap.thickness_mm):
            raise InputError(f"--fit-map {fit_map.name} is not the same set-up (geometry, n, thickness) as {amap.name}")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    stamp = {"map": amap.name, "model": args.model, "paths": args.paths, "orders": args.orders, "seed": args.seed}
    doc = json.loads(args.out.read_text()) if args.out.is_file() else {}
    if {k: doc.get(k) for k in stamp} != stamp:
        doc = {**stamp, "columns": {}}
    args.out.parent.mkdir(parents=True, exist_ok=True)

    def save() -> None:
        args.out.write_text(json.dumps(doc))

    trace_columns(amap, h, args.model, args.paths, args.orders, args.seed, doc["columns"], save, args.columns)
    doc["summary"] = summarise(amap, h, doc["columns"], fit_map)
    save()
    report(amap.name, args.model, args.paths, args.orders, doc["summary"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
