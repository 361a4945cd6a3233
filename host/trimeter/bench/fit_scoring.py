"""Scoring a fit against held-out truth: its error figures (α, σt, g percentiles over the measurable gamut, NaN
and flag rates, the bins the fit itself calls determined), and an error budget that says what limits them.

The rendered held-out set is `bench fit`'s headline, but on this instrument its figures mix three errors. The
error budget per map (noise-free, measurable gamut) separates them, all to first order through the map's
Jacobian (trimeter.model.grid.ForwardGrid):
- reference noise floor: the α / g standard deviation implied by the held-out renders' own MC
  std-error (std_b, std_w per material) — how precisely the references can check any method;
- map error floor: the α / g error implied by model-forward − held-out intensities, where the model
  is the forward map lut and mlp polish on (the table's, refined in σt with cubic splines): the map's
  MC noise plus its interpolation — what even an exact inversion of that model gets wrong;
- map-exact rows: every variant on the same off-grid materials with I_b, I_w, I_c from that same
  forward model, which isolates the inversion method's error (what the lut/mlp targets measure about
  the method);
- well-conditioned columns: α / g p95 over the materials whose reference noise floor is below half
  the target (α std < 0.005, g std < 0.0075), where the rendered references can resolve the targets.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from trimeter.bench.fit_targets import ALPHA_TARGET, G_TARGET, Row
from trimeter.bench.heldout import Heldout, heldout_intensities
from trimeter.inversion.flags import FitFlag
from trimeter.model.collimated import MEASURABLE_IC

if TYPE_CHECKING:
    from trimeter.domain.parameters import FitResult
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.fit_model import FitModel

G_MIN_ALPHA = 0.5  # g is scored over α ≥ 0.5 only (below, g barely changes the intensities)


def _solve_alpha_g(J: np.ndarray, d_b: np.ndarray, d_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First-order (δα, δg) from intensity offsets (δI_b, δI_w) at known σt: J2⁻¹ δI with J2 =
    ∂(I_b, I_w)/∂(α, g) (Cramer's rule, vectorized); ±inf where J2 is singular."""
    a, b, c, d = J[:, 0, 0], J[:, 0, 2], J[:, 1, 0], J[:, 1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        det = a * d - b * c
        da, dg = (d * d_b - b * d_w) / det, (a * d_w - c * d_b) / det
    return np.nan_to_num(da, nan=np.inf), np.nan_to_num(dg, nan=np.inf)


def error_budget(amap: AppearanceMap, h: Heldout, rho_b: float, rho_w: float,
                 artifacts: FitModel | None = None) -> dict[str, Any]:
    """Per held-out material, what limits the rendered-reference figures (see the module docstring):
    reference noise floor (first-order α / g std from the renders' MC std-error), map error floor
    (first-order signed α / g error of an exact map inversion: map forward − rendered intensities),
    the map-exact intensities (I_b, I_w, I_c from the map's own forward model) and the masks
    (measurable gamut, g scored, well-conditioned for α and for g). artifacts: the map's, loaded
    (default: through the process's cache)."""
    from trimeter.inversion.kernel import default_kernel
    from trimeter.inversion.artifacts import load_artifacts
    from trimeter.model.grid import ForwardGrid

    a, s, g = h["alpha"], h["sigma_t"], h["g"]
    n = len(a)
    rb, rw = np.full(n, rho_b), np.full(n, rho_w)
    kernel = default_kernel()
    grid = (artifacts or load_artifacts(amap)).grid  # the forward model lut and mlp polish on
    I_b, I_w = heldout_intensities(h, rho_b, rho_w)
    map_b, map_w, map_c = grid.intensities(a, s, g, rb, rw)
    J = grid.jacobian(a, s, g, rb, rw)
    # I_c is analytic in both (no MC noise, no interpolation): its std is 0 here.
    alpha_std, _, g_std = kernel.propagate(J, np.column_stack([h["std_b"], h["std_w"], np.zeros(n)]))
    alpha_err, g_err = _solve_alpha_g(J, I_b - map_b, I_w - map_w)
    # The map's own MC part of that error: its nodes' std-errors interpolated like A, B, C (an upper
    # bound: exact when a cell's node errors are fully correlated, as along α within one traced column).
    node_std = ForwardGrid(amap.alpha, np.log(amap.sigma_t), amap.g,
                           np.stack([amap.std_b, amap.std_w, np.zeros_like(amap.std_b)], axis=-1),
                           setup=amap.setup)
    map_std = node_std.coefficients(a, node_std.sigma_cell(s), g)[0]
    alpha_map_std, _, g_map_std = kernel.propagate(J, np.column_stack([map_std[0], map_std[1], np.zeros(n)]))
    measurable = amap.collimated(s) >= MEASURABLE_IC
    g_scored = measurable & (a >= G_MIN_ALPHA)
    return {"alpha_floor_std": alpha_std, "g_floor_std": g_std, "alpha_map_err": alpha_err, "g_map_err": g_err,
            "alpha_map_std": alpha_map_std, "g_map_std": g_map_std,
            "map_exact": (map_b, map_w, map_c), "measurable": measurable, "g_scored": g_scored,
            "well_alpha": measurable & (alpha_std < ALPHA_TARGET / 2),
            "well_g": g_scored & (g_std < G_TARGET / 2)}


def percentile(x: np.ndarray, q: float) -> float:
    x = np.asarray(x, dtype=float)
    x = x[~np.isnan(x)]
    return float(np.percentile(x, q)) if len(x) else float("nan")


def budget_summary(b: dict[str, Any]) -> dict[str, dict[str, float]]:
    def p50_p95(key: str, mask: np.ndarray) -> dict[str, float]:
        x = np.abs(b[key][mask])
        return {f"{key.split('_')[0]}_p50": percentile(x, 50), f"{key.split('_')[0]}_p95": percentile(x, 95)}

    return {
        "reference_noise_floor": {**p50_p95("alpha_floor_std", b["measurable"]),
                                  **p50_p95("g_floor_std", b["g_scored"])},
        "map_error_floor": {**p50_p95("alpha_map_err", b["measurable"]), **p50_p95("g_map_err", b["g_scored"])},
        "map_noise_floor": {**p50_p95("alpha_map_std", b["measurable"]), **p50_p95("g_map_std", b["g_scored"])},
        # what is left of the rendered well-conditioned figures once the references are precise
        "map_error_floor_well_conditioned": {**p50_p95("alpha_map_err", b["well_alpha"]),
                                             **p50_p95("g_map_err", b["well_g"])},
        "well_conditioned": {"alpha_count": int(b["well_alpha"].sum()), "alpha_of": int(b["measurable"].sum()),
                             "alpha_floor_std_below": ALPHA_TARGET / 2, "g_count": int(b["well_g"].sum()),
                             "g_of": int(b["g_scored"].sum()), "g_floor_std_below": G_TARGET / 2},
    }


def error_figures(res: FitResult | SimpleNamespace, truth: tuple[np.ndarray, ...], budget: dict[str, Any]) -> Row:
    """Error figures of a fit's columns (a FitResult, or any result with its alpha, sigma_t, g, flags and
    alpha_std) against the true (α, σt, g)."""
    a, s, g = truth
    measurable = budget["measurable"]
    ea = np.abs(res.alpha - a)
    es = np.abs(res.sigma_t / s - 1)[measurable]
    eg = np.abs(res.g - g)
    nan_meas = float(np.mean(~np.isfinite(res.alpha[measurable]) | ~np.isfinite(res.sigma_t[measurable])))
    # the bins the fit itself calls determined (no FitFlag.UNDERDETERMINED)
    determined = (res.flags & int(FitFlag.UNDERDETERMINED)) == 0
    # the bins over the α target (NaN included): does the fit itself say it does not know α there?
    miss = measurable & ~(ea <= ALPHA_TARGET)
    miss_std = res.alpha_std[miss & np.isfinite(res.alpha_std)]
    return {"alpha_p50": percentile(ea[measurable], 50), "alpha_p95": percentile(ea[measurable], 95),
            "sigma_rel_p50": percentile(es, 50), "sigma_rel_p95": percentile(es, 95),
            "g_p50": percentile(eg[budget["g_scored"]], 50), "g_p95": percentile(eg[budget["g_scored"]], 95),
            "nan_rate": float(np.mean(~np.isfinite(res.alpha))), "nan_rate_measurable": nan_meas,
            "flag_rate": float(np.mean(res.flags != 0)),
            "alpha_p95_well": percentile(ea[budget["well_alpha"]], 95),
            "g_p95_well": percentile(eg[budget["well_g"]], 95),
            "alpha_p95_determined": percentile(ea[measurable & determined], 95),
            "g_p95_determined": percentile(eg[budget["g_scored"] & determined], 95),
            "determined_rate": float(np.mean(determined[measurable])),
            "alpha_misses": int(miss.sum()), "alpha_misses_flagged": int((miss & ~determined).sum()),
            "alpha_misses_min_std": float(miss_std.min()) if len(miss_std) else float("nan"),
            "measurable": int(measurable.sum())}
