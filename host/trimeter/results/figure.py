"""The measurement figure, after the paper's Fig. 10: α, σt (with the Beer's-law estimate) and g over
wavelength; the combined estimate thick with a ±1σ band, single thicknesses dashed."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from trimeter.atomic import atomic_output
from trimeter.domain.measurement import Estimate


def plot_parameters(path: str | Path, combined: Estimate, per_thickness: Sequence[Estimate] = (), *, title: str = "",
                    truth: dict | None = None) -> Path:
    # a Figure of its own, not pyplot's: choosing a backend here would switch off the plots of a notebook
    # or program that measures in-process
    from matplotlib.figure import Figure

    wl = combined.wavelengths_nm
    fig = Figure(figsize=(13, 3.8), layout="constrained")
    axes = fig.subplots(1, 3)
    panels = (("alpha", "albedo α", (0, 1.0)), ("sigma_t", "extinction σt [1/mm]", None),
              ("g", "anisotropy g", (-1, 1)))
    for ax, (name, label, ylim) in zip(axes, panels, strict=True):
        value, std = getattr(combined, name), getattr(combined, f"{name}_std")
        band = np.isfinite(std) & np.isfinite(value)
        if ylim and band.any():  # the data's range, not the parameter's whole one: a ±1σ of 0.001 stays visible
            lo, hi = np.nanmin((value - std)[band]), np.nanmax((value + std)[band])
            pad = max(0.02, 0.1 * (hi - lo))
            ylim = (max(ylim[0], lo - pad), min(ylim[1], hi + pad))
        if name == "sigma_t":
            finite = np.concatenate([a[np.isfinite(a)] for a in (value, combined.sigma_t_beer)] + [np.zeros(1)])
            ylim = (0, max(1e-3, 1.15 * np.percentile(finite, 99)))
        scale = _band_scale(value, std, band, ylim)
        if band.any():
            half = np.where(band, scale * std, np.nan)
            band_label = "±1σ" if scale == 1 else f"±1σ ×{scale} (narrower than the line at scale)"
            ax.fill_between(wl, value - half, value + half, color="tab:blue", alpha=0.35, lw=0.6,
                            edgecolor="tab:blue", label=band_label)
        ax.plot(wl, value, color="k", lw=1.2, label="combined" if per_thickness else "estimate")
        for p in per_thickness:
            ax.plot(wl, getattr(p, name), ls="--", lw=1, label=f"ℓ = {p.thickness_mm:g} mm")
        if name == "sigma_t":
            ax.plot(wl, combined.sigma_t_beer, color="tab:red", lw=1, ls=":", label="Beer's law (Eq. 2)")
        if truth is not None and name in truth:
            ax.plot(truth["wavelengths_nm"], truth[name], color="tab:green", lw=1, label="truth (twin)")
        if ylim:
            ax.set_ylim(*ylim)
        ax.set_xlabel("wavelength [nm]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")  # each panel: its band's scale may differ
    if title:
        fig.suptitle(title)
    with atomic_output(path) as f:
        fig.savefig(f, dpi=110, format=Path(path).suffix.lstrip(".") or "png")
    return Path(path)


def _band_scale(value: np.ndarray, std: np.ndarray, band: np.ndarray, ylim: tuple[float, float] | None) -> int:
    """1, or the factor (5, 10, 50, …) that widens a ±1σ band narrower than ~1.5 % of the panel to
    about that: otherwise it hides under the line. The legend says so."""
    if not band.any():
        return 1
    finite = value[band]
    span = (ylim[1] - ylim[0]) if ylim else float(np.ptp(finite)) or float(np.max(np.abs(finite))) or 1.0
    median = float(np.median(std[band][np.isfinite(std[band])])) if np.isfinite(std[band]).any() else 0.0
    if not (median > 0) or 2 * median >= 0.015 * span:
        return 1
    for scale in (5, 10, 50, 100, 500, 1000):
        if 2 * median * scale >= 0.015 * span:
            return scale
    return 1000
