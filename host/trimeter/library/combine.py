"""Several measurements of one material combined into one estimate, with the spread between them.

Per wavelength bin and parameter (α, σt, g), the members' estimates x_i with their stds s_i:
- the combined value is the inverse-variance mean x̄ = Σ w_i x_i / Σ w_i, w_i = 1/s_i², and its std
  1/√Σw_i (what the members' own uncertainties allow); where a member reports no std for the bin, the
  plain mean, with no std, and the bin carries NO_STD;
- the spread is the repeats' sample standard deviation about x̄ (n ≥ 2; NaN for one member): the
  uncertainty a user of the material should expect between samples, which the stds do not know of
  (preparation, thickness, placement);
- χ² = Σ w_i (x_i − x̄)² against n − 1 degrees of freedom: where its p-value is below
  DISAGREE_P for any parameter, the repeats disagree beyond their stds and the bin carries
  REPEATS_DISAGREE.
Every member must be over the same wavelengths (the same instrument); their fit flags are OR-ed.

Two thicknesses, jointly: when the members were measured at different thicknesses, each one alone
(0.4 mm here, 0.8 mm there), the two-thickness fit is what resolves α and g best (the paper's Sec. 3).
Then every thickness's reflectances (I_b, I_w, I_c, ρ_b, ρ_w) are averaged over the members measured
at it (inverse variance, by the stds the capture recorded) and fitted once, jointly, by trimeter.fit
with the maps the members were fitted with; the spread and χ² still come from the members' own
estimates. Members measured at the same thicknesses (each one or each two) are combined by the
inverse-variance mean alone: their own fits were already joint.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntFlag

import numpy as np

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.results.reader import Measurement
from trimeter.results.writer import Parameters

PARAMETERS = ("alpha", "sigma_t", "g")
DISAGREE_P = 0.01   # a χ² p-value below this: the repeats disagree beyond their stds


class LibraryFlag(IntFlag):
    """Per-bin flags of a combined material (its own; the members' FitFlags are kept beside them)."""
    NONE = 0
    REPEATS_DISAGREE = 1   # χ² of the repeats about the combined value has p < DISAGREE_P (any parameter)
    SINGLE_MEMBER = 2      # fewer than two members with a value here: no spread
    NO_STD = 4             # a member gave no std here: plain mean, no combined std


FLAG_MEANING = {LibraryFlag.REPEATS_DISAGREE: f"the repeats disagree beyond their stds (χ² p < {DISAGREE_P})",
                LibraryFlag.SINGLE_MEMBER: "fewer than two members with a value: no spread",
                LibraryFlag.NO_STD: "a member gave no std: the plain mean, without a combined std"}


@dataclass(frozen=True)
class Combined:
    """A combined estimate over `wavelengths_nm`: value, std (from the members' stds), spread (between
    repeats) and χ² p-value per parameter, the members' count, library flags and OR-ed fit flags."""
    wavelengths_nm: np.ndarray
    values: dict[str, np.ndarray]
    stds: dict[str, np.ndarray]
    spreads: dict[str, np.ndarray]
    chi2_p: dict[str, np.ndarray]
    members: np.ndarray
    flags: np.ndarray
    fit_flags: np.ndarray
    method: str                      # "inverse-variance" or "joint-refit"
    thicknesses_mm: list[float]

    def parameters(self) -> Parameters:
        """The estimate as a results.Parameters (what exports and predictions take)."""
        v, s = self.values, self.stds
        fit = FitResult(v["alpha"], v["sigma_t"], v["g"], s["alpha"], s["sigma_t"], s["g"], self.fit_flags,
                        np.full(len(self.wavelengths_nm), np.nan), self.method)
        return Parameters.from_fit(self.wavelengths_nm, fit)


def weighted_mean(x: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                             np.ndarray, np.ndarray]:
    """Over axis 0 (members) of (members, bins) arrays, NaN: no value. Returns (mean, std of the mean,
    spread, χ² p-value, count, no_std) per bin."""
    from scipy.stats import chi2

    have = np.isfinite(x)
    n = have.sum(axis=0)
    has_std = np.isfinite(std) & (std > 0)
    no_std = (have & ~has_std).any(axis=0)
    w = np.where(have & has_std, 1.0 / np.where(has_std, std, 1.0) ** 2, 0.0)
    w = np.where(no_std[None, :], have.astype(float), w)       # a bin without every std: equal weights
    xz = np.where(have, x, 0.0)
    sw = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, (w * xz).sum(axis=0) / sw, np.nan)
        mean_std = np.where((n > 0) & ~no_std, 1.0 / np.sqrt(sw), np.nan)
        dev = np.where(have, xz - mean, 0.0)
        spread = np.where(n >= 2, np.sqrt((dev ** 2).sum(axis=0) / np.maximum(n - 1, 1)), np.nan)
        chi = (w * dev ** 2).sum(axis=0)
        p = np.where((n >= 2) & ~no_std, chi2.sf(chi, np.maximum(n - 1, 1)), np.nan)
    return mean, mean_std, spread, p, n, no_std


def _stack(members: Sequence[Measurement], name: str) -> np.ndarray:
    return np.stack([np.asarray(getattr(m, name), float) for m in members])


def _common_wavelengths(members: Sequence[Measurement]) -> np.ndarray:
    if not members:
        raise InputError("a material needs at least one measurement")
    wl = members[0].wavelength_nm
    for m in members[1:]:
        if m.wavelength_nm.shape != wl.shape or not np.allclose(m.wavelength_nm, wl, rtol=0, atol=1e-6):
            raise InputError(f"{m.path}: not over the wavelengths of {members[0].path} (members must come from "
                             "one instrument)")
    return wl


def combine(members: Sequence[Measurement], *, joint: bool = True) -> Combined:
    """The members' combined estimate (module docstring); `joint`: re-fit members measured at different
    thicknesses jointly from their reflectances."""
    wl = _common_wavelengths(members)
    values, stds, spreads, ps = {}, {}, {}, {}
    count = np.zeros(len(wl), int)
    flags = np.zeros(len(wl), np.int64)
    for name in PARAMETERS:
        mean, mean_std, spread, p, n, no_std = weighted_mean(_stack(members, name), _stack(members, f"{name}_std"))
        values[name], stds[name], spreads[name], ps[name] = mean, mean_std, spread, p
        count = np.maximum(count, n)
        flags |= np.where(no_std & (n > 0), int(LibraryFlag.NO_STD), 0)
        flags |= np.where(np.nan_to_num(p, nan=1.0) < DISAGREE_P, int(LibraryFlag.REPEATS_DISAGREE), 0)
    flags |= np.where(count < 2, int(LibraryFlag.SINGLE_MEMBER), 0)
    fit_flags = np.bitwise_or.reduce(np.stack([np.asarray(m.flags, np.int64) for m in members]), axis=0)
    thickness_sets = {tuple(m.thicknesses_mm) for m in members}
    thicknesses = sorted({t for m in members for t in m.thicknesses_mm})
    method = "inverse-variance"
    if joint and len(thickness_sets) > 1 and len(thicknesses) > 1:
        refit = joint_refit(members, thicknesses)
        for name in PARAMETERS:
            values[name], stds[name] = getattr(refit, name), getattr(refit, f"{name}_std")
        fit_flags = np.asarray(refit.flags, np.int64)
        method = "joint-refit"
    return Combined(wl, values, stds, spreads, ps, count, flags, fit_flags, method, thicknesses)


def joint_refit(members: Sequence[Measurement], thicknesses: Sequence[float]) -> FitResult:
    """One fit of every thickness's member-averaged reflectances together (module docstring)."""
    from trimeter.inversion.artifacts import fit

    per: dict[float, list] = {t: [] for t in thicknesses}
    maps: dict[float, str] = {}
    methods = {m.method or "lut" for m in members}
    if len(methods) != 1:
        raise InputError(f"the members were fitted by different methods ({', '.join(sorted(methods))}): combine "
                         "them without the joint re-fit (--no-joint) or re-fit them alike first")
    for m in members:
        if len(m.maps) != len(m.thicknesses_mm):
            raise InputError(f"{m.path}: its measurement.json names {len(m.maps)} map(s) for "
                             f"{len(m.thicknesses_mm)} thickness(es): no joint re-fit possible (--no-joint)")
        for t, refl, amap in zip(m.thicknesses_mm, m.reflectances, m.maps, strict=True):
            per[t].append(refl)
            maps.setdefault(t, amap)
    columns = {}
    for key in ("I_b", "I_w", "I_c", "rho_b", "rho_w"):
        rows, row_stds = [], []
        for t in thicknesses:
            x = np.stack([np.asarray(getattr(r, key), float) for r in per[t]])
            s = (np.stack([np.asarray(getattr(r, f"{key}_std"), float) if getattr(r, f"{key}_std", None) is not None
                           else np.full(x.shape[1], np.nan) for r in per[t]]) if key.startswith("I_")
                 else np.full(x.shape, np.nan))
            mean, mean_std = weighted_mean(x, s)[:2]
            rows.append(mean)
            row_stds.append(mean_std)
        columns[key], columns[f"{key}_std"] = np.stack(rows), np.stack(row_stds)
    try:
        return fit([maps[t] for t in thicknesses], columns["I_b"], columns["I_w"], columns["I_c"], columns["rho_b"],
                   columns["rho_w"], methods.pop(), I_b_std=columns["I_b_std"], I_w_std=columns["I_w_std"],
                   I_c_std=columns["I_c_std"])
    except InputError as exc:
        raise InputError(f"the joint re-fit of {'+'.join(f'{t:g}' for t in thicknesses)} mm failed ({exc}); "
                         "combine without it (--no-joint)") from None
