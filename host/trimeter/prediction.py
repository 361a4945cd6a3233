"""Predicted appearance: the spectral reflectance and sRGB colour of a slab of any thickness, on black and on
white, for a measured material or a mixture by volume fractions (paper Sec. 5.2: a color checker of ink
mixtures 5 mm thick, predicted from parameters measured on 0.4 and 0.8 mm samples).

Computed with the project's tracer (trimeter.forward.transport, public API: Stack.from_recipe, trace_column):
per wavelength node one column at the material's σt and g, evaluated at its α, gives A, B, C of
I(ρ) = A + Bρ/(1 − Cρ), so both backgrounds come from one trace. A trace per spectrometer pixel would be
slow; the slab is traced at WAVELENGTHS_NM (31 nodes, 400-700 nm every 10 nm: where the colour-matching
functions weigh) and its colour integrates those nodes, interpolated linearly. All nodes share one seed,
so the Monte Carlo error is smooth in λ and cancels in colour differences. Geometry: `ideal` (a laterally
infinite slab of index n in air on a Lambertian background, lit by a uniform sky, seen along the normal:
reflectance factors as a colorimeter with diffuse illumination reads them) or `device` (the instrument).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from trimeter.errors import InputError
from trimeter.results.medium import SpectralMaterial

WAVELENGTHS_NM = np.arange(400.0, 701.0, 10.0)
DEFAULT_PATHS = 1 << 16
TRUNCATION = 1e-5
SKY_SAMPLE_PREFIX = "sample:"


@dataclass(frozen=True)
class Prediction:
    wavelengths_nm: np.ndarray
    on_black: np.ndarray          # reflectance factor per node
    on_white: np.ndarray
    stderr_black: np.ndarray
    stderr_white: np.ndarray
    srgb_black: np.ndarray        # linear sRGB (D65) of the reflectance on black
    srgb_white: np.ndarray
    info: dict


def load_material(spec: str) -> tuple[SpectralMaterial, str]:
    """A material from a measurement directory, a parameters file, or `sample:NAME` (the twin's catalogue)."""
    if spec.startswith(SKY_SAMPLE_PREFIX):
        from trimeter.twin.optics import material_spectra

        name = spec[len(SKY_SAMPLE_PREFIX):]
        lam = np.arange(340.0, 1001.0, 5.0)
        return SpectralMaterial(lam, **material_spectra(name, lam)), name
    from trimeter.results.export import load_result

    result = load_result(spec)
    return result.material, str(result.source.get("sample") or result.source.get("label") or Path(spec).name)


def mixture(materials: Iterable[SpectralMaterial], fractions: ArrayLike | None = None) -> SpectralMaterial:
    """One material (no fractions) or their mixture by volume fractions (SpectralMaterial.mixture)."""
    materials = list(materials)
    if fractions is None:
        if len(materials) != 1:
            raise InputError("several materials need --fractions (one volume fraction each)")
        return materials[0]
    return SpectralMaterial.mixture(materials, fractions)


def predict_slab(material: SpectralMaterial, thickness_mm: float, *, geometry: str = "ideal", n: float = 1.5,
                 rho_black: float = 0.0, rho_white: float = 1.0, paths: int = DEFAULT_PATHS, seed: int = 1,
                 wavelengths_nm: ArrayLike | None = None) -> Prediction:
    """Reflectance of a slab of `material`, `thickness_mm` thick, on backgrounds ρ_black and ρ_white."""
    from trimeter.geometry import load_geometry
    from trimeter.forward.transport import Stack, k_max_for, trace_column
    from trimeter.results.export import spectra_to_linear_srgb

    for name, value, lo, hi in (("thickness", thickness_mm, 0.0, 1e4), ("n", n, 1.0, 4.0),
                                ("rho_black", rho_black, 0.0, 1.0), ("rho_white", rho_white, 0.0, 1.0)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
            raise InputError(f"{name} must be within {lo:g}-{hi:g}, got {value!r}")
    if thickness_mm <= 0:
        raise InputError(f"thickness must be positive [mm], got {thickness_mm!r}")
    if int(paths) < 1024:
        raise InputError(f"paths must be at least 1024, got {paths!r}")
    m = material.at(WAVELENGTHS_NM if wavelengths_nm is None else wavelengths_nm)
    stack = Stack.from_recipe(geometry, load_geometry(geometry), float(n), float(thickness_mm))
    k_max = k_max_for(float(m.alpha.max()), TRUNCATION)
    out = np.empty((4, len(m.wavelengths_nm)))
    t0 = time.monotonic()
    for i, (alpha, sigma_t, g) in enumerate(zip(m.alpha, m.sigma_t, m.g, strict=True)):
        # σt = 0 has no free flight to sample; 1e-9/mm is clear glass to any printed precision
        tally = trace_column(stack, max(float(sigma_t), 1e-9), float(g), int(paths), seed, k_max)
        A, B, C = (float(v[0]) for v in tally.abc([alpha]))
        out[0, i] = A + B * rho_black / (1 - C * rho_black)
        out[1, i] = A + B * rho_white / (1 - C * rho_white)
        out[2, i] = float(tally.stderr([alpha], rho_black)[0])
        out[3, i] = float(tally.stderr([alpha], rho_white)[0])
    srgb = spectra_to_linear_srgb(m.wavelengths_nm, out[:2])
    info = {"thickness_mm": float(thickness_mm), "geometry": geometry, "n": float(n), "rho_black": rho_black,
            "rho_white": rho_white, "paths_per_node": int(paths), "nodes": len(m.wavelengths_nm),
            "seconds": round(time.monotonic() - t0, 2), "illuminant": "D65",
            "method": "trimeter.forward.transport per wavelength node (A, B, C at the material's α)"}
    return Prediction(m.wavelengths_nm, out[0], out[1], out[2], out[3], srgb[0], srgb[1], info)


def predict(materials: object, thickness_mm: float, *, fractions: ArrayLike | None = None,
            **options: object) -> Prediction:
    """`trimeter.predict`: the reflectance and colour of a slab of a measured material, or of a mixture.

    Parameters
    ----------
    materials : Measurement, SpectralMaterial, str or Path, or a list of them
        What the slab is made of: a loaded measurement (`trimeter.load`), a material, a results
        directory, a parameters file or ``"sample:NAME"`` (the twin's catalogue). Several: a mixture.
    thickness_mm : float
        The slab's thickness.
    fractions : array_like, optional
        Volume fractions of the materials in the mixture (one each; required for several).
    **options
        geometry ("ideal" or "device"), n, rho_black, rho_white, paths, seed, wavelengths_nm: see
        `predict_slab`.

    Returns
    -------
    Prediction
        Reflectance factors on black and on white per wavelength node, their standard errors and
        linear sRGB colours (`hex_colour` turns one into ``#rrggbb``).
    """
    listed = materials if isinstance(materials, (list, tuple)) else [materials]
    return predict_slab(mixture([_as_material(m) for m in listed], fractions), thickness_mm, **options)  # type: ignore[arg-type]


def _as_material(spec: object) -> SpectralMaterial:
    if isinstance(spec, SpectralMaterial):
        return spec
    if isinstance(spec, (str, Path)):
        return load_material(str(spec))[0]
    material = getattr(spec, "material", None)  # a trimeter.load result
    if callable(material):
        found = material()
        if isinstance(found, SpectralMaterial):
            return found
    raise InputError(f"a material is a trimeter.load result, a SpectralMaterial, a results directory or a "
                     f"parameters file, not {type(spec).__name__}")


def hex_colour(linear_rgb: ArrayLike) -> str:
    from trimeter.results.export import srgb_encode

    return "#" + "".join(f"{round(float(v) * 255):02x}" for v in srgb_encode(linear_rgb))


def write_spectra_csv(path: Path, rows: list[tuple[str, Prediction]]) -> None:
    from trimeter.atomic import atomic_write

    lines = ["patch,background,srgb_hex," + ",".join(f"R_{w:g}nm" for w in rows[0][1].wavelengths_nm)]
    for label, p in rows:
        for background, values, rgb in (("black", p.on_black, p.srgb_black), ("white", p.on_white, p.srgb_white)):
            lines.append(f"{label},{background},{hex_colour(rgb)}," + ",".join(f"{v:.6f}" for v in values))
    atomic_write(path, "\n".join(lines) + "\n")


def draw_swatches(path: Path, rows: list[tuple[str, Prediction]], *, columns: int, title: str) -> Path:
    """A grid of patches, each split: the slab on white above, on black below (sRGB, D65)."""
    from matplotlib.figure import Figure  # not pyplot: a caller's plotting backend stays as it is
    from matplotlib.patches import Rectangle

    from trimeter.atomic import atomic_output
    from trimeter.results.export import srgb_encode

    n_rows = math.ceil(len(rows) / columns)
    fig = Figure(figsize=(1.6 * columns + 0.4, 1.75 * n_rows + 0.6))
    ax = fig.subplots()
    ax.set_xlim(0, columns)
    ax.set_ylim(n_rows, 0)
    ax.set_axis_off()
    ax.set_facecolor("0.5")
    fig.patch.set_facecolor("0.5")
    for k, (label, p) in enumerate(rows):
        r, c = divmod(k, columns)
        for y0, rgb in ((0.05, p.srgb_white), (0.42, p.srgb_black)):
            ax.add_patch(Rectangle((c + 0.05, r + y0), 0.9, 0.37, color=srgb_encode(rgb)))
        ax.text(c + 0.5, r + 0.9, label.replace("+", "\n+"), ha="center", va="center", fontsize=7, color="white")
    ax.set_title(title, fontsize=9, color="white")
    with atomic_output(path) as f:
        fig.savefig(f, format="png", dpi=110, facecolor=fig.get_facecolor())
    return path
