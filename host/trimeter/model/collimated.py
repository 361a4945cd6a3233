"""I_c analytically: unscattered transmittance of the collimated beam through the layer stack,
with incoherent Fresnel inter-reflections at normal incidence (paper Sec. 3.2, Eq. 1).

I_c is normalised by the open-slot reference (no sample, no slides), as the calibration measures it,
so it is exactly the stack's transmittance. Light scattered into the detector aperture is a separate
factor (trimeter.model.inscatter).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from trimeter.model.fresnel import normal_incidence_reflectance


# The measurable gamut: below this collimated transmittance the spectrometer's I_c is noise, σt only
# a lower bound (FitFlag.SIGMA_LOWER_BOUND territory); benchmarks score and maps refine only above it.
MEASURABLE_IC = 1e-3


def _combine(a, b):
    """Incoherent combination of two stack elements, each (R_front, R_back, T)."""
    ra, ra_back, ta = a
    rb, rb_back, tb = b
    denom = 1.0 - ra_back * rb
    return (ra + ta * ta * rb / denom,
            rb_back + tb * tb * ra_back / denom,
            ta * tb / denom)


def stack_transmittance(indices, internal_transmittances):
    """Transmittance of a stack of interfaces between media `indices[0..k]` with the internal
    (Beer-Lambert) transmittances of the k-1 layers between them. Arrays broadcast."""
    if len(internal_transmittances) != len(indices) - 2:
        raise ValueError("need one internal transmittance per layer between the outer media")
    r = normal_incidence_reflectance(indices[0], indices[1])
    element = (r, r, 1.0 - r)
    for layer_t, (n1, n2) in zip(internal_transmittances, zip(indices[1:-1], indices[2:], strict=True), strict=True):
        element = _combine(element, (0.0, 0.0, layer_t))
        r = normal_incidence_reflectance(n1, n2)
        element = _combine(element, (r, r, 1.0 - r))
    return element[2]


def collimated_transmittance(sigma_t, thickness_mm: float, n: float,
                             cover_slide_n: float | None = None):
    """I_c for extinction `sigma_t` [1/mm] (array), sample thickness ℓ [mm] and index n.

    With `cover_slide_n`, the sample is sandwiched between index-matched oil + cover slides
    (the device): interfaces air|glass, glass|sample, sample|glass, glass|air; the slides don't absorb.
    """
    sigma_t = np.asarray(sigma_t, dtype=float)
    t_sample = np.exp(-sigma_t * thickness_mm)
    if cover_slide_n is None:
        return stack_transmittance([1.0, n, 1.0], [t_sample])
    return stack_transmittance([1.0, cover_slide_n, n, cover_slide_n, 1.0], [1.0, t_sample, 1.0])


@lru_cache(maxsize=64)
def stack_constants(n: float, cover_slide_n: float | None = None) -> tuple[float, float, float]:
    """(a, b, T(σt=0)) with T = a·x / (1 − b·x²) in x = exp(−σt ℓ).

    Every stack here is E1 · exp(−σt ℓ) · E2 with non-absorbing E1, E2, whose transmittance has
    that form; a, b follow from two evaluations of the forward stack: t1 at x = 1 and th at x = 1/2."""
    t1 = float(collimated_transmittance(0.0, 1.0, n, cover_slide_n))
    th = float(collimated_transmittance(np.log(2.0), 1.0, n, cover_slide_n))
    b = (2 * th - t1) / (th / 2 - t1)
    return t1 * (1 - b), b, t1


def collimated_derivative(sigma_t, thickness_mm: float, n: float, cover_slide_n: float | None = None):
    """∂I_c/∂σt, analytic: dT/dσt = −ℓ·a·x·(1 + b·x²)/(1 − b·x²)² with x = exp(−σt ℓ)."""
    a, b, _ = stack_constants(n, cover_slide_n)
    x = np.exp(-np.asarray(sigma_t, dtype=float) * thickness_mm)
    bx2 = b * x * x
    return -thickness_mm * a * x * (1.0 + bx2) / ((1.0 - bx2) * (1.0 - bx2))


def beer_lambert_limit(n: float, cover_slide_n: float | None = None) -> float:
    """The largest I_c beer_lambert_sigma_t inverts: T(σt = 0), widened by 1e-12 for rounding."""
    return stack_constants(n, cover_slide_n)[2] * (1 + 1e-12)


def beer_lambert_sigma_t(I_c, thickness_mm: float, n: float, cover_slide_n: float | None = None):
    """Invert collimated_transmittance for σt (paper Eq. 2, with the same Fresnel stack). NaN where
    I_c is not inside (0, T(σt=0)]. Used as the consistency column of a fit."""
    I_c = np.asarray(I_c, dtype=float)
    # T = a·x / (1 − b·x²) (stack_constants): solving b·I·x² + a·x − I = 0 for x is exact.
    a, b, _ = stack_constants(n, cover_slide_n)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        x = 2 * I_c / (a + np.sqrt(a * a + 4 * b * I_c * I_c))  # the stable root of the quadratic
        sigma = -np.log(x) / thickness_mm
    ok = np.isfinite(I_c) & (I_c > 0) & (I_c <= beer_lambert_limit(n, cover_slide_n))
    return np.where(ok, np.maximum(sigma, 0.0), np.nan)
