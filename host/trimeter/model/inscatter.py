"""The in-scattering table: how much forward-scattered light the collimated measurement picks up besides
the unscattered beam, as L = ln(1 + r) per material. I_c = T(σt)·e^L; the fit takes σt from I_c·e^−L.
trimeter.forward.transport.inscatter_tracer traces it, trimeter.maps.inscatter_file reads and writes `<map>.tins`."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from trimeter.errors import MapFileError
from trimeter.model.cells import regular_cell, trilinear
from trimeter.model.setup import SampleSetup

TAU_MAX = 10.0  # beyond, I_c is far under any noise floor (e^-10): σt is only a lower bound there anyway


class InscatterTable:
    """L = ln(1 + r), r the in-scattered over the unscattered collimated light, on a regular grid in
    u = −ln(1 − α) (α 0 … 0.999), τ = σt·ℓ (0 … TAU_MAX) and v = −ln(1 − g) (g 0 … 0.9), for one sample
    index n, thickness ℓ and the device's collimated geometry. Evaluation: trilinear, clamped to the
    grid, the same operations as invert.c's inscatter_log1p."""

    def __init__(self, L: ArrayLike, *, u_max: float, tau_max: float, v_max: float, n: float, thickness_mm: float,
                 geometry_params: dict, provenance: dict | None = None, parent_sha256: str | None = None,
                 producer: dict | None = None) -> None:
        self.L = np.ascontiguousarray(L, dtype=np.float64)
        if self.L.ndim != 3 or min(self.L.shape) < 2 or not np.all(np.isfinite(self.L)) or self.L.min() < 0:
            raise MapFileError("in-scatter table: L must be a finite, non-negative (u, τ, g) grid, ≥ 2 per axis")
        self.u_max, self.tau_max, self.v_max = float(u_max), float(tau_max), float(v_max)
        self.n, self.thickness_mm = float(n), float(thickness_mm)
        self.geometry_params = geometry_params
        self.provenance = provenance or {}
        # the map it was traced for (its SHA-256) and what traced it: trimeter.maps.pipeline stamps both
        self.parent_sha256, self.producer = parent_sha256, producer
        self.checksum: str | None = None  # the file's SHA-256 once saved or loaded
        nu, nt, nv = self.L.shape
        self.inv_du, self.inv_dt, self.inv_dv = (nu - 1) / self.u_max, (nt - 1) / self.tau_max, (nv - 1) / self.v_max

    @staticmethod
    def axes(nu: int = 25, nt: int = 21, nv: int = 13, u_max: float = math.log(1000.0), tau_max: float = TAU_MAX,
             v_max: float = math.log(10.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(α nodes, τ nodes, g nodes) of a table with these sizes."""
        return (-np.expm1(-np.linspace(0.0, u_max, nu)), np.linspace(0.0, tau_max, nt),
                -np.expm1(-np.linspace(0.0, v_max, nv)))

    def log1p_ratio(self, alpha: ArrayLike, sigma_t: ArrayLike, g: ArrayLike) -> np.ndarray:
        """L at materials (arrays broadcast), clamped to the grid."""
        alpha, sigma_t, g = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (alpha, sigma_t, g)))
        alpha, sigma_t, g = (np.where(np.isfinite(x), x, 0.0) for x in (alpha, sigma_t, g))  # NaN: 0, as in C
        nu, nt, nv = self.L.shape
        iu, wu = regular_cell(-np.log1p(-np.clip(alpha, 0.0, 0.999)) * self.inv_du, nu)
        it, wt = regular_cell(np.clip(sigma_t * self.thickness_mm, 0.0, self.tau_max) * self.inv_dt, nt)
        iv, wv = regular_cell(-np.log1p(-np.clip(g, 0.0, 0.9)) * self.inv_dv, nv)
        return trilinear(self.L, iu, wu, it, wt, iv, wv)

    def setup_mismatch(self, setup: SampleSetup) -> str | None:
        """Why this table was not traced for `setup` (another n, ℓ or geometry), or None."""
        if abs(self.n - setup.n) > 1e-9 or abs(self.thickness_mm - setup.thickness_mm) > 1e-9:
            return f"it is for n = {self.n:g}, ℓ = {self.thickness_mm:g} mm, the map for n = {setup.n:g}, " \
                   f"ℓ = {setup.thickness_mm:g} mm"
        if self.geometry_params != setup.geometry_params:
            return "it was traced for another instrument geometry than the map's"
        return None
