"""The sample set-up a map, a table and a forward grid all describe: the one source of n, ℓ and the
cover slides."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.measurement import thickness_matches
from trimeter.geometry import cover_slide_n
from trimeter.model.collimated import (beer_lambert_limit, beer_lambert_sigma_t, collimated_derivative,
                                       collimated_transmittance, stack_constants)


@dataclass(frozen=True)
class SampleSetup:
    """Sample index n, thickness ℓ [mm] and the cover slides' index (None: no slides), with the
    instrument geometry's name and parameters as the map's recipe records them (empty for a set-up
    read back from a device table, which keeps only the numbers)."""
    n: float
    thickness_mm: float
    cover_slide_n: float | None = None
    geometry: str = ""
    geometry_params: dict | None = None

    @classmethod
    def from_recipe(cls, recipe: dict) -> SampleSetup:
        params = recipe.get("geometry_params", {}) or {}
        return cls(float(recipe["n"]), float(recipe["thickness_mm"]), cover_slide_n(params),
                   str(recipe.get("geometry", "")), recipe.get("geometry_params"))

    def matches_thickness(self, declared_mm: ArrayLike) -> np.ndarray:
        """Whether a declared thickness (or each of an array of them) is this set-up's ℓ: a map or table of
        another ℓ scales σt by the ratio (trimeter.domain.measurement.thickness_matches)."""
        return thickness_matches(self.thickness_mm, declared_mm)

    # ------------------------------------------------------------------------- the collimated beam
    def collimated(self, sigma_t: ArrayLike) -> np.ndarray:
        """The unscattered collimated beam through the sample (Beer-Lambert with the Fresnel stack)."""
        return collimated_transmittance(sigma_t, self.thickness_mm, self.n, self.cover_slide_n)

    def collimated_derivative(self, sigma_t: ArrayLike) -> np.ndarray:
        return collimated_derivative(sigma_t, self.thickness_mm, self.n, self.cover_slide_n)

    def beer_lambert_sigma_t(self, I_c: ArrayLike) -> np.ndarray:
        """σt from I_c alone (collimated's exact inverse; NaN outside (0, T(σt = 0)])."""
        return beer_lambert_sigma_t(I_c, self.thickness_mm, self.n, self.cover_slide_n)

    @property
    def stack_constants(self) -> tuple[float, float, float]:
        """(a, b, T(σt = 0)) of I_c = a·x / (1 − b·x²), x = exp(−σt ℓ)."""
        return stack_constants(self.n, self.cover_slide_n)

    @cached_property
    def transmittance_limits(self) -> tuple[float, float]:
        """(T(σt = 0), the largest I_c the Beer-Lambert inverse takes): computed once per set-up."""
        return float(self.collimated(0.0)), float(beer_lambert_limit(self.n, self.cover_slide_n))
