"""The measured material as a spectral Mitsuba 3 `homogeneous` medium, ready to render.

Two equivalent forms: `medium.xml` (a scene fragment to paste or `<include>`) and `medium.json` (the
dict for `mi.load_dict`). Spectra use Mitsuba's wavelength:value pairs (`irregular` spectrum) over the
valid bins, resampled to `step_nm`; σt is in 1/mm, so `scale` converts to the scene's unit (1 for a
scene in millimetres). Mitsuba's `hg` phase function takes one g: we use the σs-weighted mean over the
valid bins and record the spectral g beside it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from trimeter.atomic import atomic_write


def medium_spectra(parameters, step_nm: float = 5.0):
    wl = parameters.wavelengths_nm
    valid = np.isfinite(parameters.alpha) & np.isfinite(parameters.sigma_t)
    if valid.sum() < 2:
        return None
    grid = np.arange(np.ceil(wl[valid].min() / step_nm) * step_nm, wl[valid].max() + 1e-9, step_nm)
    if len(grid) < 2:
        grid = wl[valid]
    albedo = np.clip(np.interp(grid, wl[valid], parameters.alpha[valid]), 0, 1)
    sigma_t = np.maximum(np.interp(grid, wl[valid], parameters.sigma_t[valid]), 0)
    g_ok = valid & np.isfinite(parameters.g)
    weights = (parameters.alpha * parameters.sigma_t)[g_ok]
    g = float(np.average(parameters.g[g_ok], weights=weights)) if g_ok.any() and weights.sum() > 0 else 0.0
    return grid, albedo, sigma_t, float(np.clip(g, -0.99, 0.99))


def _pairs(grid, values) -> str:
    return ", ".join(f"{w:.1f}:{v:.6g}" for w, v in zip(grid, values))


def medium_dict(parameters, *, scale: float = 1.0) -> dict | None:
    spectra = medium_spectra(parameters)
    if spectra is None:
        return None
    grid, albedo, sigma_t, g = spectra
    return {"type": "homogeneous",
            "albedo": {"type": "irregular", "wavelengths": ", ".join(f"{w:.1f}" for w in grid),
                       "values": ", ".join(f"{v:.6g}" for v in albedo)},
            "sigma_t": {"type": "irregular", "wavelengths": ", ".join(f"{w:.1f}" for w in grid),
                        "values": ", ".join(f"{v:.6g}" for v in sigma_t)},
            "scale": scale,
            "phase": {"type": "hg", "g": g}}


def write_medium(directory: str | Path, parameters, *, scale: float = 1.0) -> dict:
    """Write medium.xml + medium.json; returns what was written (for measurement.json)."""
    directory = Path(directory)
    spectra = medium_spectra(parameters)
    if spectra is None:
        return {"written": False, "reason": "fewer than two wavelengths with a valid α and σt"}
    grid, albedo, sigma_t, g = spectra
    xml = (
        "<!-- trimeter measurement as a Mitsuba 3 medium (spectral variants). sigma_t in 1/mm: scale = 1 for a\n"
        "     scene in millimetres. g is the scattering-weighted mean of the measured spectral g. -->\n"
        '<medium type="homogeneous" id="trimeter_sample">\n'
        f'    <spectrum name="albedo" value="{_pairs(grid, albedo)}"/>\n'
        f'    <spectrum name="sigma_t" value="{_pairs(grid, sigma_t)}"/>\n'
        f'    <float name="scale" value="{scale:g}"/>\n'
        f'    <phase type="hg">\n        <float name="g" value="{g:.6g}"/>\n    </phase>\n'
        "</medium>\n")
    atomic_write(directory / "medium.xml", xml)
    atomic_write(directory / "medium.json", json.dumps(medium_dict(parameters, scale=scale), indent=1))
    return {"written": True, "files": ["medium.xml", "medium.json"], "g_mean": g, "bins": len(grid)}
