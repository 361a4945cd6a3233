"""Inversion of the forward model: measured (I_b, I_w, I_c) per wavelength → (α, σt, g) with per-bin
uncertainty and flags. It only solves: what it solves comes in as model objects (trimeter.model,
loaded from map files by trimeter.inversion.artifacts).

    trimeter.fit(maps, I_b, I_w, I_c, rho_b=None, rho_w=None, method="lut") -> FitResult

Methods (trimeter.inversion.methods): `paper` (Iser et al. Sec. 4.3: Delaunay + linear
interpolation, ε-median; the baseline), `lut` (the map table's guess + Newton polish on the forward
map), `mlp` (a small ONNX network next to the map + the same polish). Flags: trimeter.inversion.flags.
"""

from trimeter.inversion.flags import FitFlag

__all__ = ["FitFlag"]
