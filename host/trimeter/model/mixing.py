"""Mixtures by volume fractions: the one rule, for measured materials (results.medium.SpectralMaterial.mixture)
and the twin's virtual samples alike.

Each material's particles keep their cross-sections in a mixture, so the absorption and scattering
coefficients add in proportion to the volume fractions, σa = Σ f_i σa_i and σs = Σ f_i σs_i, and the
mixture's anisotropy is the scattering-weighted mean g = Σ f_i σs_i g_i / σs (the fractions' mean of g
where nothing scatters). A mixture is written NAME:FRACTION+NAME:FRACTION… (`parse_fractions`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from trimeter.errors import InputError

MIXTURE_SEPARATOR, FRACTION_SEPARATOR = "+", ":"


def mix_coefficients(sigma_a: ArrayLike, sigma_s: ArrayLike, g: ArrayLike, fractions: ArrayLike
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(σa, σs, g) of the mixture of materials given as rows (materials, bins) at volume `fractions`
    (one per material; normalised to sum to 1)."""
    f = np.asarray(fractions, dtype=float)
    sa, ss, gg = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (sigma_a, sigma_s, g))
    if f.ndim != 1 or len(f) == 0 or not (sa.shape == ss.shape == gg.shape) or sa.shape[0] != len(f):
        raise InputError("a mixture needs one volume fraction per material")
    if not np.all(np.isfinite(f)) or (f < 0).any() or f.sum() <= 0:
        raise InputError("volume fractions must be finite, ≥ 0 and not all 0")
    f = (f / f.sum())[:, None]
    mixed_sa, mixed_ss = (f * sa).sum(axis=0), (f * ss).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mixed_g = np.where(mixed_ss > 0, (f * ss * gg).sum(axis=0) / mixed_ss, (f * gg).sum(axis=0))
    return mixed_sa, mixed_ss, mixed_g


def parse_fractions(spec: str) -> list[tuple[str, float]]:
    """A mixture written NAME:FRACTION+NAME:FRACTION… (volume fractions > 0 of distinct names, summing to 1)."""
    parts = []
    for part in spec.split(MIXTURE_SEPARATOR):
        name, _, fraction = part.rpartition(FRACTION_SEPARATOR)
        try:
            value = float(fraction)
        except ValueError:
            value = math.nan
        if not name or not (math.isfinite(value) and value > 0):
            raise InputError(f"mixture {spec!r}: each part is NAME:FRACTION with a fraction > 0, got {part!r}")
        parts.append((name, value))
    total = sum(f for _, f in parts)
    if abs(total - 1.0) > 1e-3 or len({n for n, _ in parts}) != len(parts):
        raise InputError(f"mixture {spec!r}: volume fractions of distinct materials summing to 1 (they sum to "
                         f"{total:g})")
    return parts
