"""Colour of a reflectance spectrum and colour differences: CIE 1931 2° observer, D65, CIELAB, CIEDE2000.

XYZ uses the export's tristimulus weights (trimeter.results.export: the CIE 1931 2° colour-matching
functions × the illuminant at 1 nm, Y of a perfect reflector = 1), so every colour in trimeter comes
from one table. CIELAB is relative to that perfect reflector; ΔE2000 follows Sharma, Wu and Dalal,
"The CIEDE2000 color-difference formula: implementation notes, supplementary test data, and
mathematical observations", Color Res. Appl. 30 (2005) 21-30, vectorised over any leading axes
(its 34 test pairs are the test).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

ILLUMINANT = "D65"


def reflectance_to_xyz(wavelengths_nm: ArrayLike, reflectance: ArrayLike, illuminant: str = ILLUMINANT
                       ) -> np.ndarray:
    """XYZ (Y of a perfect reflector = 1) of reflectance spectra (..., len(wavelengths)), interpolated
    linearly onto 1 nm and held constant beyond their ends."""
    from trimeter.results.export import _tristimulus_weights

    lam, weights = _tristimulus_weights(illuminant)
    wl = np.asarray(wavelengths_nm, dtype=float)
    values = np.asarray(reflectance, dtype=float)
    on = np.apply_along_axis(lambda v: np.interp(lam, wl, v), -1, values)
    return on @ weights


def xyz_to_lab(xyz: ArrayLike, illuminant: str = ILLUMINANT) -> np.ndarray:
    """CIELAB of XYZ (last axis), white: the perfect reflector under `illuminant`."""
    from trimeter.results.export import _tristimulus_weights

    white = _tristimulus_weights(illuminant)[1].sum(axis=0)
    t = np.asarray(xyz, dtype=float) / white
    delta = 6.0 / 29.0
    f = np.where(t > delta ** 3, np.cbrt(t), t / (3 * delta ** 2) + 4.0 / 29.0)
    return np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])],
                    axis=-1)


def delta_e_2000(lab1: ArrayLike, lab2: ArrayLike, kL: float = 1.0, kC: float = 1.0, kH: float = 1.0
                 ) -> np.ndarray:
    """CIEDE2000 between CIELAB colours (last axis L*, a*, b*), broadcast over the leading axes."""
    L1, a1, b1 = np.moveaxis(np.asarray(lab1, dtype=float), -1, 0)
    L2, a2, b2 = np.moveaxis(np.asarray(lab2, dtype=float), -1, 0)
    C_mean = (np.hypot(a1, b1) + np.hypot(a2, b2)) / 2.0
    G = 0.5 * (1.0 - np.sqrt(C_mean ** 7 / (C_mean ** 7 + 25.0 ** 7)))
    a1p, a2p = (1.0 + G) * a1, (1.0 + G) * a2
    C1p, C2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.where(C1p == 0, 0.0, np.degrees(np.arctan2(b1, a1p)) % 360.0)
    h2p = np.where(C2p == 0, 0.0, np.degrees(np.arctan2(b2, a2p)) % 360.0)
    dLp = L2 - L1
    dCp = C2p - C1p
    dh = h2p - h1p
    dh = np.where(dh > 180.0, dh - 360.0, np.where(dh < -180.0, dh + 360.0, dh))
    dh = np.where(C1p * C2p == 0, 0.0, dh)
    dHp = 2.0 * np.sqrt(C1p * C2p) * np.sin(np.radians(dh) / 2.0)
    Lp = (L1 + L2) / 2.0
    Cp = (C1p + C2p) / 2.0
    hsum = h1p + h2p
    hp = np.where(C1p * C2p == 0, hsum,
                  np.where(np.abs(h1p - h2p) <= 180.0, hsum / 2.0,
                           np.where(hsum < 360.0, (hsum + 360.0) / 2.0, (hsum - 360.0) / 2.0)))
    T = (1.0 - 0.17 * np.cos(np.radians(hp - 30.0)) + 0.24 * np.cos(np.radians(2.0 * hp))
         + 0.32 * np.cos(np.radians(3.0 * hp + 6.0)) - 0.20 * np.cos(np.radians(4.0 * hp - 63.0)))
    d_theta = 30.0 * np.exp(-(((hp - 275.0) / 25.0) ** 2))
    R_C = 2.0 * np.sqrt(Cp ** 7 / (Cp ** 7 + 25.0 ** 7))
    S_L = 1.0 + 0.015 * (Lp - 50.0) ** 2 / np.sqrt(20.0 + (Lp - 50.0) ** 2)
    S_C = 1.0 + 0.045 * Cp
    S_H = 1.0 + 0.015 * Cp * T
    R_T = -np.sin(np.radians(2.0 * d_theta)) * R_C
    l, c, h = dLp / (kL * S_L), dCp / (kC * S_C), dHp / (kH * S_H)
    return np.sqrt(l ** 2 + c ** 2 + h ** 2 + R_T * c * h)
