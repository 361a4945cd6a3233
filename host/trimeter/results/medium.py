"""The measured material as a spectral Mitsuba 3 `homogeneous` medium, ready to render.

Two equivalent forms: `medium.xml` (a scene fragment to paste or `<include>`) and `medium.json` (the
dict for `mi.load_dict`). Spectra use Mitsuba's wavelength:value pairs (`irregular` spectrum) over the
valid bins, resampled to `step_nm`; σt is in 1/mm, so `scale` converts to the scene's unit (1 for a
scene in millimetres). Mitsuba's `hg` phase function takes one g: we use the σs-weighted mean over the
valid bins and record the spectral g beside it.

Only Mitsuba's spectral variants (SPECTRAL_VARIANTS) render the medium as measured: an `_rgb` variant
turns each irregular spectrum into an sRGB triplet and a `_mono` variant into one luminance-weighted
constant, without a warning. For RGB renderers, `trimeter export --to rgb` converts through transmittance.

SpectralMaterial is the one place a measured material's spectra are resampled (window means of the
finite bins, so the per-pixel noise of a measurement averages out) and mixed.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from trimeter.atomic import atomic_write
from trimeter.domain.measurement import SpectralColumns
from trimeter.errors import InputError

SPECTRAL_VARIANTS = ("scalar_spectral", "llvm_ad_spectral", "cuda_ad_spectral", "scalar_spectral_polarized",
                     "llvm_ad_spectral_polarized", "cuda_ad_spectral_polarized")
VARIANT_NOTE = ("spectral only in Mitsuba's *_spectral variants (" + ", ".join(SPECTRAL_VARIANTS[:3]) +
                "); *_rgb variants convert each spectrum to one sRGB triplet, *_mono variants to a constant")


@dataclass(frozen=True)
class SpectralMaterial:
    """α(λ), σt(λ) [1/mm], g(λ) at increasing wavelengths, all finite."""

    wavelengths_nm: np.ndarray
    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray

    def __post_init__(self) -> None:
        wl = np.asarray(self.wavelengths_nm, dtype=float)
        arrays = [np.asarray(getattr(self, k), dtype=float) for k in ("alpha", "sigma_t", "g")]
        if wl.ndim != 1 or len(wl) < 2 or not np.all(np.diff(wl) > 0) or not np.all(np.isfinite(wl)):
            raise InputError("a material needs ≥ 2 strictly increasing, finite wavelengths")
        for name, a in zip(("alpha", "sigma_t", "g"), arrays, strict=True):
            if a.shape != wl.shape or not np.all(np.isfinite(a)):
                raise InputError(f"material {name}: {len(wl)} finite values expected")
        if (arrays[0] < 0).any() or (arrays[0] > 1).any():
            raise InputError("material alpha must be within [0, 1]")
        if (arrays[1] < 0).any():
            raise InputError("material sigma_t must be ≥ 0 [1/mm]")
        if (np.abs(arrays[2]) >= 1).any():
            raise InputError("material g must be within (−1, 1)")
        object.__setattr__(self, "wavelengths_nm", wl)
        for name, a in zip(("alpha", "sigma_t", "g"), arrays, strict=True):
            object.__setattr__(self, name, a)

    @classmethod
    def from_parameters(cls, parameters: SpectralColumns) -> SpectralMaterial:
        """The bins of a fit (results.Parameters or anything with those columns) where α, σt and g are finite."""
        wl = np.asarray(parameters.wavelengths_nm, dtype=float)
        alpha, sigma_t, g = (np.asarray(getattr(parameters, k), dtype=float) for k in ("alpha", "sigma_t", "g"))
        ok = np.isfinite(wl) & np.isfinite(alpha) & np.isfinite(sigma_t) & np.isfinite(g)
        if ok.sum() < 2:
            raise InputError("fewer than two wavelengths with a finite α, σt and g")
        for name, values, bad in (("alpha", alpha, (alpha < 0) | (alpha > 1)), ("sigma_t", sigma_t, sigma_t < 0),
                                  ("g", g, np.abs(g) >= 1)):
            if (bad & ok).any():
                i = int(np.flatnonzero(bad & ok)[0])
                raise InputError(f"{name} at {wl[i]:g} nm is {values[i]:g}: outside its physical range")
        order = np.argsort(wl[ok])
        return cls(wl[ok][order], alpha[ok][order], sigma_t[ok][order], np.clip(g[ok][order], -0.99, 0.99))

    @property
    def sigma_s(self) -> np.ndarray:
        return self.alpha * self.sigma_t

    @property
    def sigma_a(self) -> np.ndarray:
        return (1.0 - self.alpha) * self.sigma_t

    def g_mean(self) -> float:
        """One g for renderers with a single HG lobe: the σs-weighted mean (what scatters most counts most)."""
        w = self.sigma_s
        return float(np.clip(np.average(self.g, weights=w) if w.sum() > 0 else self.g.mean(), -0.99, 0.99))

    def at(self, wavelengths_nm: ArrayLike) -> SpectralMaterial:
        """On other wavelengths: α, σt and g interpolated linearly, held constant beyond the ends."""
        lam = np.asarray(wavelengths_nm, dtype=float)
        return SpectralMaterial(lam, *(np.interp(lam, self.wavelengths_nm, v) for v in (self.alpha, self.sigma_t,
                                                                                          self.g)))

    @classmethod
    def from_coefficients(cls, wavelengths_nm: ArrayLike, sigma_a: ArrayLike, sigma_s: ArrayLike,
                          g: ArrayLike) -> SpectralMaterial:
        sigma_t = np.asarray(sigma_a, dtype=float) + np.asarray(sigma_s, dtype=float)
        with np.errstate(invalid="ignore", divide="ignore"):
            alpha = np.where(sigma_t > 0, np.asarray(sigma_s, dtype=float) / sigma_t, 0.0)
        return cls(np.asarray(wavelengths_nm, dtype=float), np.clip(alpha, 0, 1), sigma_t, np.asarray(g, dtype=float))

    def resampled(self, step_nm: float = 5.0) -> "SpectralMaterial":
        """On a regular grid every `step_nm` over the covered range: the mean of the bins within ±step/2
        of each node (σa, σs and σs·g averaged, so α and g stay consistent), α, σt, g interpolated
        where a window holds no bin."""
        wl = self.wavelengths_nm
        grid = np.arange(np.ceil(wl[0] / step_nm) * step_nm, wl[-1] + 1e-9, step_nm)
        if len(grid) < 2:
            return self
        lo = np.searchsorted(wl, grid - step_nm / 2, side="left")
        hi = np.searchsorted(wl, grid + step_nm / 2, side="left")
        count = hi - lo
        out = []
        for v in (self.sigma_a, self.sigma_s, self.sigma_s * self.g):
            cum = np.concatenate([[0.0], np.cumsum(v)])
            out.append((cum[hi] - cum[lo]) / np.maximum(count, 1))
        sa, ss, ssg = out
        mean = SpectralMaterial.from_coefficients(grid, sa, ss, np.clip(np.divide(ssg, ss, out=np.zeros_like(ss),
                                                                                   where=ss > 0), -0.99, 0.99))
        between = self.at(grid)
        empty = count == 0
        return SpectralMaterial(grid, *(np.where(empty, getattr(between, k), getattr(mean, k))
                                        for k in ("alpha", "sigma_t", "g")))

    @staticmethod
    def mixture(materials: Iterable[SpectralMaterial], fractions: ArrayLike) -> SpectralMaterial:
        """A mixture by volume fractions on the first material's wavelengths (trimeter.model.mixing: σa and
        σs add in proportion, g is the σs-weighted mean)."""
        from trimeter.model.mixing import mix_coefficients

        materials = list(materials)
        if len(materials) == 0:
            raise InputError("a mixture needs one volume fraction per material")
        lam = materials[0].wavelengths_nm
        on = [m.at(lam) for m in materials]
        sa, ss, g = mix_coefficients([m.sigma_a for m in on], [m.sigma_s for m in on], [m.g for m in on], fractions)
        return SpectralMaterial.from_coefficients(lam, sa, ss, np.clip(g, -0.99, 0.99))


def medium_spectra(parameters: SpectralColumns,
                   step_nm: float = 5.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """(grid, albedo, σt, g_mean) for the Mitsuba medium, or None with fewer than two valid bins."""
    try:
        m = SpectralMaterial.from_parameters(parameters)
    except InputError:
        return None
    m = m.resampled(step_nm) if step_nm else m
    return m.wavelengths_nm, m.alpha, m.sigma_t, m.g_mean()


def _pairs(grid: np.ndarray, values: np.ndarray) -> str:
    return ", ".join(f"{w:.1f}:{v:.6g}" for w, v in zip(grid, values, strict=True))


def medium_dict(parameters: SpectralColumns, *, scale: float = 1.0, step_nm: float = 5.0) -> dict | None:
    spectra = medium_spectra(parameters, step_nm)
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


def write_medium(directory: str | Path, parameters: SpectralColumns, *, scale: float = 1.0,
                 step_nm: float = 5.0) -> dict:
    """Write medium.xml + medium.json (spectra every `step_nm`, 0: the bins as given); returns what was
    written (for measurement.json)."""
    directory = Path(directory)
    spectra = medium_spectra(parameters, step_nm)
    if spectra is None:
        return {"written": False, "reason": "fewer than two wavelengths with a valid α and σt"}
    grid, albedo, sigma_t, g = spectra
    xml = (
        "<!-- trimeter measurement as a Mitsuba 3 medium. sigma_t in 1/mm: scale = 1 for a scene in millimetres.\n"
        "     g is the scattering-weighted mean of the measured spectral g.\n"
        f"     {VARIANT_NOTE}. -->\n"
        '<medium type="homogeneous" id="trimeter_sample">\n'
        f'    <spectrum name="albedo" value="{_pairs(grid, albedo)}"/>\n'
        f'    <spectrum name="sigma_t" value="{_pairs(grid, sigma_t)}"/>\n'
        f'    <float name="scale" value="{scale:g}"/>\n'
        f'    <phase type="hg">\n        <float name="g" value="{g:.6g}"/>\n    </phase>\n'
        "</medium>\n")
    atomic_write(directory / "medium.xml", xml)
    atomic_write(directory / "medium.json", json.dumps(medium_dict(parameters, scale=scale, step_nm=step_nm), indent=1))
    return {"written": True, "files": ["medium.xml", "medium.json"], "g_mean": g, "bins": len(grid),
            "mitsuba_variants": VARIANT_NOTE}
