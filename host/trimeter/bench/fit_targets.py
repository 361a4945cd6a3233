"""The inversion's targets for lut and mlp, and their verdicts on a bench row: met or MISSED, each against the
paper method measured in the same run."""

from __future__ import annotations

from typing import Any

import numpy as np

Row = dict[str, Any]  # one printed and reported row of a bench's figures

# The inversion's noise-free p95 targets for lut/mlp; a reference resolves them where its own first-order
# std is below half of them (the well-conditioned subset).
ALPHA_TARGET, G_TARGET = 0.01, 0.015
# and its speed and σt targets: ≥ 50× paper's plain interpolation, ms per 1024 bins, σt relative p95
SPEEDUP_TARGET, MS_TARGET, SIGMA_REL_TARGET = 50.0, {"lut": 1.0, "mlp": 2.0}, 0.01


def target_checks(row: Row, paper: Row) -> dict[str, dict[str, Any]]:
    """The inversion targets for one lut/mlp row (noise-free, rendered references) against the paper row
    of the same run: {target: {"value", "limit", "met"}}. Figures a row lacks (the two-thickness rows
    have no cold time, σt or NaN figures) are not checked."""
    kind = row["variant"].split()[0]  # "lut" / "mlp"
    checks: dict[str, dict[str, Any]] = {}

    def check(name: str, value: float, limit: float, met: bool | np.bool_, issue_target: bool = True) -> None:
        checks[name] = {"value": value, "limit": limit, "met": bool(met), "issue_target": issue_target}

    # The speed-up target is a throughput figure (time per 1024 bins): warm, as in a batch of spectra.
    # Cold (one press-button fit after the caches were evicted) is this bench's own stricter view,
    # judged against the same limit but not a target: it is memory-bound (the
    # polish's refined forward model is ~22 MB) and moves ±15 % with the machine's state.
    for key, label, target in (("ms_per_1024", "× paper", True), ("ms_per_1024_cold", "× paper cold", False)):
        if key in row and key in paper:
            ratio = paper[key] / row[key]
            check(label, ratio, SPEEDUP_TARGET, ratio >= SPEEDUP_TARGET, target)
    check("ms per 1024 bins", row["ms_per_1024"], MS_TARGET[kind], row["ms_per_1024"] <= MS_TARGET[kind])
    check("α p95", row["alpha_p95"], ALPHA_TARGET, row["alpha_p95"] <= ALPHA_TARGET)
    if "sigma_rel_p95" in row:
        check("σt relative p95", row["sigma_rel_p95"], SIGMA_REL_TARGET, row["sigma_rel_p95"] <= SIGMA_REL_TARGET)
    check("g p95 (α ≥ 0.5)", row["g_p95"], G_TARGET, row["g_p95"] <= G_TARGET)
    if "nan_rate_measurable" in row:
        check("NaN in the gamut", row["nan_rate_measurable"], 0.0, row["nan_rate_measurable"] == 0)
    return checks


def show_check(name: str, c: dict[str, Any]) -> str:
    verdict = "" if c["met"] else (" MISSED" if c["issue_target"] else f" (below {c['limit']:g})")
    return f"{name} {c['value']:.3g}{verdict}" + ("" if c["issue_target"] else " [not a target]")


def print_targets(title: str, rows: list[Row]) -> dict[str, dict[str, dict[str, Any]]]:
    """One line per lut/mlp p≤8 variant: every inversion target, met or MISSED, from this run (the targets
    are noise-free: nothing to judge when --noise left out 0)."""
    paper = next((r for r in rows if r["variant"] == "paper"), None)
    if paper is None:
        print(f"\n   inversion targets, {title}: not judged (they are noise-free figures: include 0 in --noise)")
        return {}
    print(f"\n   inversion targets, {title} (noise-free, rendered references; ratios to paper in this run):")
    verdicts: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if r["variant"] not in ("lut p≤8", "mlp p≤8"):
            continue
        checks = target_checks(r, paper)
        verdicts[r["variant"]] = checks
        missed = [k for k, c in checks.items() if c["issue_target"] and not c["met"]]
        print(f"   {r['variant']:<10}" + "; ".join(show_check(k, c) for k, c in checks.items())
              + (f"  — MISSED: {', '.join(missed)}" if missed else "  — all targets met"))
    return verdicts

