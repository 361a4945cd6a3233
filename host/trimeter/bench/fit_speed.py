"""`bench fit`'s speed figures beyond its tables: where the paper method's time goes (inputs inside or outside
the hull of the map's nodes), and the whole lut fit with uncertainty against a bare lookup of the same bins."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from trimeter.bench.fit_variants import DEFAULT_POLISH
from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities
from trimeter.bench.timing import timed_ms

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.fit_model import FitModel


def hull_split(artifacts: FitModel, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rb: float, rw: float,
               repeats: int) -> dict[str, float]:
    """The paper method's time depends on where its inputs fall: scipy's Delaunay search rejects a
    point outside the hull's bounding box at once, but one inside the box and outside the hull costs
    a brute-force pass over every simplex (~0.3 ms). So: paper core and whole fit() against lut's
    default fit() on the inputs inside the hull alone (tiled to 1024), next to the whole set."""
    from trimeter.inversion.api import fit
    from trimeter.inversion.paper import coordinates, interpolator

    interp = interpolator(artifacts.map, round(rb, 3), round(rw, 3), artifacts.paper_cache)
    pts = coordinates(I_b, I_w, I_c)
    inside = interp.tri.find_simplex(pts) >= 0  # type: ignore[attr-defined]  # scipy sets .tri; its stubs omit it
    out: dict[str, float] = {"outside_hull": int((~inside).sum()), "of": len(inside)}
    if not inside.any():
        return out
    idx = np.resize(np.flatnonzero(inside), 1024)
    calls: dict[str, Callable[[], object]] = {"paper_core_ms": lambda: interp(pts[idx]),
             "paper_ms": lambda: fit(artifacts, I_b[idx], I_w[idx], I_c[idx], method="paper", samples=0),
             "lut_ms": lambda: fit(artifacts, I_b[idx], I_w[idx], I_c[idx], method="lut", **DEFAULT_POLISH)}
    for key, fn in calls.items():
        fn()
        out[key] = min(timed_ms(fn) for _ in range(repeats))
    return out


# The speed targets of a fit with per-bin stds and flags: one thickness against a bare scipy lookup of
# the same bins (a ratio, so that the machine's speed drops out), two thicknesses in absolute time.
SPEED_LOOKUP_RATIO_MAX, SPEED_TWO_MS_MAX = 0.8, 0.8


def speed(amaps: list[AppearanceMap], median_bins: int, repeats: int) -> dict[str, Any]:
    """The whole lut fit (validation, flags, stds) on 1024 bins against, in the same run and timed
    round-robin (the machine is shared): a bare scipy LinearNDInterpolator lookup of the same bins on
    the map's nodes (the paper's interpolant, built beforehand: the call alone) and the paper's fixed
    method (the ε-median of `samples` interpolations, timed on median_bins bins, scaled to 1024).
    Bins: the ideal (else the first) map's held-out materials inside the hull of its nodes, noise-free,
    tiled to 1024. Two thicknesses: where two
    maps share geometry and n at other thicknesses, the same materials' intensities from each map's
    forward model, fitted together. The lut fits run in the default kernel's threads and, where that is more
    than one, in one thread as well; the one-thickness fit of the first of them is timed beside it."""
    import trimeter
    from trimeter.inversion.paper import coordinates, interpolator
    from trimeter.inversion.artifacts import load_artifacts
    from trimeter.inversion.kernel import NativeKernel, default_kernel

    amap = next((m for m in amaps if m.recipe.get("geometry") == "ideal"), amaps[0])
    artifacts = load_artifacts(amap)
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    interp = interpolator(amap, round(rb, 3), round(rw, 3), artifacts.paper_cache)
    # inside the hull of the map's nodes only: the lookup's fastest case (see hull_split), so the ratio
    # is the lookup's best against the fit
    I_b, I_w = heldout_intensities(h, rb, rw)
    I_c = heldout_collimated(amap, h)
    inside = np.flatnonzero(interp.tri.find_simplex(coordinates(I_b, I_w, I_c)) >= 0)  # type: ignore[attr-defined]
    tile = np.resize(inside if len(inside) else np.arange(len(I_b)), 1024)
    I_b, I_w, I_c = I_b[tile], I_w[tile], I_c[tile]
    calls: dict[str, Callable[[], object]] = {
        "bare lookup": lambda: interp(coordinates(I_b, I_w, I_c)),
        "lut": lambda: trimeter.fit(amap, I_b, I_w, I_c, method="lut", **DEFAULT_POLISH)}
    pair = next(((a, b) for i, a in enumerate(amaps) for b in amaps[i + 1:]
                 if (a.recipe.get("geometry"), a.n) == (b.recipe.get("geometry"), b.n)
                 and a.thickness_mm != b.thickness_mm), None)
    kernel = default_kernel()
    threads = kernel.fit_threads() if isinstance(kernel, NativeKernel) else 1
    one_thread = NativeKernel(threads=1) if threads > 1 else None
    if one_thread is not None:
        calls["lut, one thread"] = lambda: trimeter.fit(amap, I_b, I_w, I_c, method="lut", kernel=one_thread,
                                                        **DEFAULT_POLISH)
    if pair is not None:
        _, _, hp = heldout_for(pair[0])
        tp = np.resize(np.arange(len(hp["alpha"])), 1024)
        a, s, g = (hp[k][tp] for k in ("alpha", "sigma_t", "g"))
        forward = [load_artifacts(m).grid.intensities(a, s, g, *m.reference_rhos) for m in pair]
        stacked = [np.stack([f[i] for f in forward]) for i in range(3)]
        first = [x[0] for x in stacked]
        calls[f"lut, {pair[0].name} alone"] = lambda: trimeter.fit(pair[0], first[0], first[1], first[2],
                                                                    method="lut", **DEFAULT_POLISH)
        calls["lut, two thicknesses"] = lambda: trimeter.fit(list(pair), stacked[0], stacked[1], stacked[2],
                                                             method="lut", **DEFAULT_POLISH)
        if one_thread is not None:
            calls["lut, two thicknesses, one thread"] = lambda: trimeter.fit(
                list(pair), stacked[0], stacked[1], stacked[2], method="lut", kernel=one_thread, **DEFAULT_POLISH)
    # a round in this order: the one-thickness fit right after a lookup in threads and in one thread alike
    order = [*calls]
    if one_thread is not None:
        order.insert(order.index("lut, one thread"), "bare lookup")
    best = {name: np.inf for name in calls}
    for fn in calls.values():
        fn()
    for _ in range(max(repeats, 1) * 20):
        for name in order:
            best[name] = min(best[name], timed_ms(calls[name]))
    nb = max(1, min(median_bins, 1024))
    median = functools.partial(trimeter.fit, amap, I_b[:nb], I_w[:nb], I_c[:nb], method="paper")
    median()
    paper_ms = timed_ms(median) * 1024 / nb
    lookup = best["bare lookup"]
    print(f"\n== speed with uncertainty: {amap.name}, 1024 bins (its held-out materials inside the hull of its "
          f"nodes, noise-free), "
          + (f"the lut fits in {threads} threads unless said, the rest in one" if threads > 1 else "one core")
          + f", best of {max(repeats, 1) * 20} round-robin rounds")
    print(f"   {'':44s} {'ms_per_1024':>12s} {'× bare lookup':>14s} {'× paper faster':>15s}")
    print(f"   {'paper ε-median (fixed; ' + str(nb) + ' bins, scaled)':44s} {paper_ms:12.4g} "
          f"{paper_ms / lookup:14.3g} {1.0:15.3g}")
    for name, ms in best.items():
        print(f"   {name:44s} {ms:12.4g} {ms / lookup:14.3g} {paper_ms / ms:15.3g}")
    ratio = best["lut"] / lookup
    verdicts = {"lut_over_lookup": {"value": ratio, "max": SPEED_LOOKUP_RATIO_MAX,
                                    "met": ratio <= SPEED_LOOKUP_RATIO_MAX}}
    line = (f"   targets: whole lut fit ≤ {SPEED_LOOKUP_RATIO_MAX:g}× a bare lookup: ×{ratio:.3g} "
            f"{'met' if ratio <= SPEED_LOOKUP_RATIO_MAX else 'MISSED'}")
    if pair is not None:
        two = best["lut, two thicknesses"]
        verdicts["two_thicknesses_ms"] = {"value": two, "max": SPEED_TWO_MS_MAX, "met": two <= SPEED_TWO_MS_MAX}
        line += (f"; two thicknesses ({pair[0].name} + {pair[1].name}, {threads} thread{'s' * (threads > 1)}) "
                 f"≤ {SPEED_TWO_MS_MAX:g} ms: {two:.3g} ms {'met' if two <= SPEED_TWO_MS_MAX else 'MISSED'}")
        if "lut, two thicknesses, one thread" in best:
            one = best["lut, two thicknesses, one thread"]
            verdicts["two_thicknesses_one_thread_ms"] = {"value": one, "max": SPEED_TWO_MS_MAX,
                                                         "met": one <= SPEED_TWO_MS_MAX}
            line += f"; in one thread: {one:.3g} ms {'met' if one <= SPEED_TWO_MS_MAX else 'MISSED'}"
    print(line)
    return {"map": amap.name, "ms_per_1024": {**best, "paper ε-median": paper_ms}, "targets": verdicts,
            "fit_threads": threads, "round": order}
