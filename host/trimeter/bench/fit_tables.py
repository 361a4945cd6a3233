"""What `bench fit` prints and draws: its table per noise level with ratios to paper, the error budget, and
the Pareto plot of time against α and g error."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trimeter.atomic import atomic_output
from trimeter.bench.fit_scoring import G_MIN_ALPHA
from trimeter.bench.fit_targets import ALPHA_TARGET, G_TARGET, Row

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap


def print_table(sub: list[Row], title: str) -> None:
    cols = ("ms_per_1024", "ms_per_1024_cold", "core_ms_per_1024", "alpha_p50", "alpha_p95", "sigma_rel_p50",
            "sigma_rel_p95", "g_p50", "g_p95", "nan_rate", "flag_rate", "files_kB", "model_kB", "peak_kB")
    base = next(r for r in sub if r["variant"] == "paper")
    print(f"\n   {title:<19}" + " ".join(f"{c:>13}" for c in cols))
    for r in sub:
        print(f"   {r['variant']:<18}" + " ".join(f"{r[c]:>13.4g}" for c in cols))
        if r["variant"] != "paper":
            ratios = []
            for c in cols:
                if c.startswith(("ms_", "core_ms")):
                    ratios.append(f"{'×%.1f faster' % (base[c] / r[c]) if r[c] else '-':>13}")
                else:
                    ratios.append(f"{'%.3g' % (r[c] / base[c]) if base[c] else '-':>13}")
            print(f"   {'  ratio to paper':<18}" + " ".join(ratios))


def print_budget(summary: dict[str, dict[str, float]], rows: list[Row], exact_rows: list[Row]) -> None:
    ref, err, wc = summary["reference_noise_floor"], summary["map_error_floor"], summary["well_conditioned"]
    print(f"\n   error budget, noise-free (first order through the map's Jacobian; α over the measurable gamut, "
          f"g over α ≥ {G_MIN_ALPHA:g}):")
    print(f"   {'':<52}{'α p50':>9}{'α p95':>9}{'g p50':>9}{'g p95':>9}")
    for label, d in (("reference noise floor (held-out MC std-error → std)", ref),
                     ("map error floor (map forward − held-out I → error)", err),
                     ("  its MC part (map nodes' std-error → std, ≤)", summary["map_noise_floor"]),
                     ("  map error floor over the well-conditioned subset",
                      summary["map_error_floor_well_conditioned"])):
        print(f"   {label:<52}" + "".join(f"{d[k]:>9.4f}" for k in ("alpha_p50", "alpha_p95", "g_p50", "g_p95")))
    print(f"   well-conditioned (reference floor below half the target): α std < {wc['alpha_floor_std_below']:g} for "
          f"{wc['alpha_count']}/{wc['alpha_of']} materials, g std < {wc['g_floor_std_below']:g} for "
          f"{wc['g_count']}/{wc['g_of']}")
    print(f"\n   noise-free p95 {'':<5}{'rendered α':>11}{'g':>9} | {'well-cond. α':>12}{'g':>9} | "
          f"{'map-exact α':>12}{'g':>9} | {'determined α':>12}{'g':>9}{'share':>7}   "
          f"(targets α {ALPHA_TARGET:g}, g {G_TARGET:g}; determined: no UNDERDETERMINED flag)")
    exact = {r["variant"]: r for r in exact_rows}
    for r in (r for r in rows if r["noise"] == 0):
        e = exact[r["variant"]]
        print(f"   {r['variant']:<20}{r['alpha_p95']:>11.4f}{r['g_p95']:>9.4f} | {r['alpha_p95_well']:>12.4f}"
              f"{r['g_p95_well']:>9.4f} | {e['alpha_p95']:>12.4f}{e['g_p95']:>9.4f} | "
              f"{r['alpha_p95_determined']:>12.4f}{r['g_p95_determined']:>9.4f}{r['determined_rate']:>7.0%}")
    print(f"\n   noise-free, rendered: bins over the α target ({ALPHA_TARGET:g}), and how many of them the fit "
          f"itself flags UNDERDETERMINED")
    for r in (r for r in rows if r["noise"] == 0 and r["variant"] != "paper-median"):
        line = f"   {r['variant']:<20}{r['alpha_misses']:>4} of {r['measurable']:<4}"
        if r["alpha_misses"]:
            line += (f" {r['alpha_misses_flagged']:>4} flagged; smallest fit α std among them "
                     f"{r['alpha_misses_min_std']:.3g}")
        print(line)


def pareto_plot(rows: list[Row], exact_rows: list[Row], summary: dict[str, dict[str, float]], amap: AppearanceMap,
            out: Path) -> Path:
    """Time against α / g p95, noise-free: rendered references (filled), map-exact (hollow, the
    method's own error, joined to its rendered point) and the budget's floors (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clean = [r for r in rows if r["noise"] == 0] or rows
    exact = {r["variant"]: r for r in exact_rows}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "alpha_p95", "α abs error p95"), (axes[1], "g_p95", "g abs error p95 (α ≥ 0.5)")):
        for i, r in enumerate(clean):
            colour = f"C{i % 10}"
            ax.scatter(r["ms_per_1024"], r[key], s=30, color=colour)
            ax.annotate(r["variant"], (r["ms_per_1024"], r[key]), fontsize=7, xytext=(3, 3), textcoords="offset points")
            e = exact.get(r["variant"])
            if e is not None and e[key] > 0:
                ax.scatter(e["ms_per_1024"], e[key], s=30, facecolors="none", edgecolors=colour)
                ax.plot([r["ms_per_1024"], e["ms_per_1024"]], [r[key], e[key]], color=colour, lw=0.5, alpha=0.5)
        for floor, style in (("reference_noise_floor", "--"), ("map_error_floor", ":")):
            value = summary[floor][key]
            if np.isfinite(value) and value > 0:
                ax.axhline(value, color="grey", ls=style, lw=1, label=floor.replace("_", " ") + " (p95)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per 1024 bins [ms] (whole fit(), one core)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"trimeter bench fit — {amap.name}, noise-free: rendered held-out (filled), map-exact (hollow)")
    fig.tight_layout()
    png = out / f"pareto-{amap.name}.png"
    with atomic_output(png) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)
    return png
