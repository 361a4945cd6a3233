"""Inversion of appearance maps: measured (I_b, I_w, I_c) per wavelength → (α, σt, g) with per-bin
uncertainty and flags.

    trimeter.fit(maps, I_b, I_w, I_c, rho_b=None, rho_w=None, method="lut") -> FitResult

Methods: `paper` (Iser et al. Sec. 4.3: Delaunay + linear interpolation, ε-median; the baseline),
`lut` (the compact map table, trimeter.inversion.table, + Newton polish on the forward map),
`mlp` (a small ONNX network next to the map + the same polish). Flags: trimeter.inversion.flags.
"""

from trimeter.inversion.flags import FitFlag


def __getattr__(name):
    # Lazy, so the flashing tool can import trimeter.inversion.table without scipy's heavier parts.
    if name in ("fit", "FitResult", "METHODS"):
        from trimeter.inversion import api

        return getattr(api, name)
    raise AttributeError(f"module 'trimeter.inversion' has no attribute {name!r}")


__all__ = ["fit", "FitResult", "FitFlag", "METHODS"]
