"""The measurement figure, after the paper's Fig. 10: α, σt (with the Beer's-law estimate) and g over
wavelength; the combined estimate thick with a ±1σ band, single thicknesses dashed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trimeter.atomic import atomic_output


def plot_parameters(path: str | Path, combined, per_thickness=(), *, title: str = "",
                    truth: dict | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wl = combined.wavelengths_nm
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    panels = (("alpha", "albedo α", (0, 1.0)), ("sigma_t", "extinction σt [1/mm]", None),
              ("g", "anisotropy g", (-1, 1)))
    for ax, (name, label, ylim) in zip(axes, panels):
        value, std = getattr(combined, name), getattr(combined, f"{name}_std")
        ax.plot(wl, value, color="k", lw=2.2, label="combined" if per_thickness else "estimate")
        band = np.isfinite(std)
        if band.any():
            ax.fill_between(wl, value - np.where(band, std, 0), value + np.where(band, std, 0), color="k", alpha=0.18,
                            lw=0, label="±1σ")
        for p in per_thickness:
            ax.plot(wl, getattr(p, name), ls="--", lw=1, label=f"ℓ = {p.thickness_mm:g} mm")
        if name == "sigma_t":
            ax.plot(wl, combined.sigma_t_beer, color="tab:red", lw=1, ls=":", label="Beer's law (Eq. 2)")
            finite = np.concatenate([a[np.isfinite(a)] for a in (value, combined.sigma_t_beer)] + [np.zeros(1)])
            ax.set_ylim(0, max(1e-3, 1.15 * np.percentile(finite, 99)))
        if truth is not None and name in truth:
            ax.plot(truth["wavelengths_nm"], truth[name], color="tab:green", lw=1, label="truth (twin)")
        if ylim:
            ax.set_ylim(*ylim)
        ax.set_xlabel("wavelength [nm]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title)
    try:
        with atomic_output(path) as f:
            fig.savefig(f, dpi=110, format=Path(path).suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return Path(path)
