"""AppearanceMap: the forward relation (α, σt, g, ρ_b, ρ_w) → (I_b, I_w, I_c) for one sample set-up.

Representation (one concept, one place):
- Per grid point (α_i, σt_j, g_k) the background-response coefficients A, B, C such that the diffuse
  observable against a Lambertian background of reflectance ρ is

      I(ρ) = A + B·ρ / (1 − C·ρ)

  (exact for the ideal geometry — A: the slab's own reflectance, B: T_down·T_up, C: the slab's
  diffuse reflectance seen from below — and verified against direct renders for the device). So
  I_b = I(ρ_b(λ)) and I_w = I(ρ_w(λ)) for any per-wavelength background without re-rendering.
- I_c is analytic (trimeter.model.collimated) from σt, ℓ, n and the cover slides (AppearanceMap.setup).
- Std-errors: `std_b`, `std_w` — the Monte Carlo standard error of I at the recipe's reference
  backgrounds `reference_rho_b`, `reference_rho_w`.
Axes are strictly increasing. Between the nodes the map is evaluated as the inversion polishes on it
(AppearanceMap.between_nodes: cubic in α and ln σt, PCHIP in g, refined, then trilinear).

File: a trimeter container (trimeter.formats.container) of kind "appearance-map" whose meta holds the
recipe (geometry preset + its parameters, n, thickness_mm, reference ρ's, sampling), provenance
(Mitsuba version, builder, timings) and the map format version.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from trimeter.errors import InputError, MapFileError
from trimeter.formats.container import read_container, write_container
from trimeter.formats.schema import (GEOMETRY_PARAMS, PROVENANCE, REFLECTANCE, SAMPLE_N, THICKNESS_MM, ArraySpec,
                                  ContainerSchema, Flag, Table, Text)
from trimeter.formats.stages import rebuild_command
from trimeter.model.grid import ForwardGrid, node_model_variance
from trimeter.model.inscatter_table import InscatterTable
from trimeter.model.response import background_response
from trimeter.model.sample_setup import SampleSetup
from trimeter.paths import MAPS_DIR

MAP_KIND = "appearance-map"
MAP_FORMAT_VERSION = 1
MAP_SUFFIX = ".tmap"
_COEFFS = ("A", "B", "C")
_REQUIRED = ("alpha", "sigma_t", "g", *_COEFFS, "std_b", "std_w")
_GRID = ("n_alpha", "n_sigma_t", "n_g")
# What a map file must hold, checked before it is used (trimeter.formats.schema). A, B, C are fractions of
# light (Monte Carlo noise aside, in [0, 1]); C < 1 keeps I(ρ) finite for every ρ ≤ 1.
MAP_SCHEMA = ContainerSchema(
    version=("map_format_version", "map format version", MAP_FORMAT_VERSION),
    meta=Table({"recipe": Table({"geometry": Text(max_len=64), "n": SAMPLE_N, "thickness_mm": THICKNESS_MM,
                                 "name": Text(max_len=256), "description": Text(max_len=4096),
                                 "reference_rho_b": REFLECTANCE, "reference_rho_w": REFLECTANCE,
                                 "geometry_params": GEOMETRY_PARAMS, "polarisation": Flag()},
                                required=("geometry", "n", "thickness_mm"),
                                rules=((lambda r: r.get("reference_rho_b", 0.0) < r.get("reference_rho_w", 1.0),
                                        "reference_rho_b must be below reference_rho_w"),)),
                "provenance": PROVENANCE},
               required=("map_format_version", "recipe")),
    arrays={"alpha": ArraySpec(_GRID[:1], min_len=2, increasing=True, lo=0.0, hi=1.0),
            "sigma_t": ArraySpec(_GRID[1:2], min_len=2, increasing=True, lo=0.0, lo_open=True, hi=1e6),
            "g": ArraySpec(_GRID[2:], min_len=2, increasing=True, lo=-1.0, hi=1.0, lo_open=True, hi_open=True),
            "A": ArraySpec(_GRID, lo=-0.05, hi=1.0), "B": ArraySpec(_GRID, lo=-0.05, hi=1.0),
            "C": ArraySpec(_GRID, lo=-0.05, hi=1.0, hi_open=True),
            "std_b": ArraySpec(_GRID, lo=0.0, hi=1.0), "std_w": ArraySpec(_GRID, lo=0.0, hi=1.0)})


@dataclass(frozen=True)
class AppearanceMap:
    recipe: dict
    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    std_b: np.ndarray
    std_w: np.ndarray
    provenance: dict = field(default_factory=dict)
    checksum: str = ""
    path: Path | None = None

    def __post_init__(self):
        shape = (len(self.alpha), len(self.sigma_t), len(self.g))
        for name, axis in (("alpha", self.alpha), ("sigma_t", self.sigma_t), ("g", self.g)):
            if axis.ndim != 1 or len(axis) < 2 or not np.all(np.diff(axis) > 0):
                raise MapFileError(f"map axis {name} must be strictly increasing with ≥ 2 points")
        for name in (*_COEFFS, "std_b", "std_w"):
            if getattr(self, name).shape != shape:
                raise MapFileError(f"map array {name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.sigma_t[0] <= 0:
            raise MapFileError("map axis sigma_t must be positive (it is interpolated in log space)")
        for key in ("geometry", "n", "thickness_mm"):
            if key not in self.recipe:
                raise MapFileError(f"map recipe lacks {key!r}")

    # ----------------------------------------------------------------------------------------- I/O
    @property
    def name(self) -> str:
        return str(self.recipe.get("name") or (self.path.stem if self.path else "unnamed"))

    @cached_property
    def setup(self) -> SampleSetup:
        """The sample set-up the map was traced for (its recipe's n, ℓ, cover slides, geometry)."""
        return SampleSetup.from_recipe(self.recipe)

    @property
    def thickness_mm(self) -> float:
        return self.setup.thickness_mm

    @property
    def n(self) -> float:
        return self.setup.n

    @property
    def cover_slide_n(self) -> float | None:
        return self.setup.cover_slide_n

    @property
    def reference_rhos(self) -> tuple[float, float]:
        """(ρ_b, ρ_w) the map was traced at and its std-errors refer to (a map without them in its
        recipe, e.g. a hand-made ideal test map: black and white, 0 and 1)."""
        return float(self.recipe.get("reference_rho_b", 0.0)), float(self.recipe.get("reference_rho_w", 1.0))

    def save(self, path: str | Path) -> str:
        meta = {"map_format_version": MAP_FORMAT_VERSION, "recipe": self.recipe, "provenance": self.provenance}
        arrays = {name: np.asarray(getattr(self, name), dtype=np.float64 if name in ("alpha", "sigma_t", "g")
                                   else np.float32) for name in _REQUIRED}
        return write_container(path, MAP_KIND, meta, arrays)

    @classmethod
    def load(cls, path: str | Path) -> "AppearanceMap":
        path = Path(path)
        meta, arrays, checksum = read_container(path, MAP_KIND, MAP_SCHEMA)
        try:
            return cls(recipe=meta.get("recipe", {}), provenance=meta.get("provenance", {}), checksum=checksum,
                       path=path, **{name: np.asarray(arrays[name], dtype=np.float64) for name in _REQUIRED})
        except MapFileError as exc:
            raise MapFileError(f"{path}: {exc}") from None

    def info(self) -> dict:
        return {
            "name": self.name,
            "path": str(self.path) if self.path else None,
            "checksum_sha256": self.checksum,
            "recipe": self.recipe,
            "provenance": self.provenance,
            "grid": {"alpha": len(self.alpha), "sigma_t": len(self.sigma_t), "g": len(self.g),
                     "points": int(self.A.size)},
            "range": {"alpha": [float(self.alpha[0]), float(self.alpha[-1])],
                      "sigma_t": [float(self.sigma_t[0]), float(self.sigma_t[-1])],
                      "g": [float(self.g[0]), float(self.g[-1])]},
            "mc_stderr": {"median": float(np.median(np.concatenate([self.std_b.ravel(), self.std_w.ravel()]))),
                          "max": float(max(self.std_b.max(), self.std_w.max()))},
        }

    # -------------------------------------------------------------------------------- evaluation
    @cached_property
    def between_nodes(self) -> ForwardGrid:
        """The map as evaluated between its nodes, the same way the inversion's polish does
        (trimeter.model.grid.ForwardGrid.between_nodes: cubic in α and ln σt, PCHIP in g)."""
        return ForwardGrid.from_map(self).between_nodes()

    def coefficients(self, alpha, sigma_t, g) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C) at materials between the nodes (see between_nodes); NaN outside the map's range."""
        alpha, sigma_t, g = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (alpha, sigma_t, g)))
        with np.errstate(invalid="ignore"):
            inside = ((alpha >= self.alpha[0]) & (alpha <= self.alpha[-1]) & (sigma_t >= self.sigma_t[0])
                      & (sigma_t <= self.sigma_t[-1]) & (g >= self.g[0]) & (g <= self.g[-1]))
        model = self.between_nodes
        values = model.coefficients(alpha.ravel(), model.sigma_cell(sigma_t.ravel()), g.ravel())[0]
        A, B, C = (np.where(inside, v.reshape(alpha.shape), np.nan) for v in values)
        return A, B, C

    def diffuse(self, alpha, sigma_t, g, rho):
        """I(ρ) = A + Bρ/(1 − Cρ) at interpolated coefficients."""
        return background_response(*self.coefficients(alpha, sigma_t, g), rho)

    def collimated(self, sigma_t):
        """The unscattered collimated beam through the sample (Beer-Lambert with the Fresnel stack)."""
        return self.setup.collimated(sigma_t)

    @cached_property
    def inscatter(self):
        """The in-scattering table traced for this map (`<map>.tins` next to it, `trimeter map inscatter`),
        or None: then I_c is modelled as the unscattered beam alone. A table that does not belong to
        the map (another n, ℓ or geometry) is an error, not ignored."""
        from trimeter.formats.inscatter_file import inscatter_path_for, load_inscatter

        if self.path is None or not inscatter_path_for(self.path).is_file():
            return None
        path = inscatter_path_for(self.path)
        table = load_inscatter(path)
        if why := inscatter_mismatch(table, self):
            raise MapFileError(f"{path} does not belong to map {self.name}: {why}")
        return table

    def collimated_measured(self, alpha, sigma_t, g):
        """I_c as the instrument reads it: the unscattered beam and the light scattered into the
        detector's aperture (with an in-scattering table)."""
        unscattered = self.collimated(sigma_t)
        if self.inscatter is None:
            return unscattered
        return unscattered * np.exp(self.inscatter.log1p_ratio(alpha, sigma_t, g))

    def query(self, alpha, sigma_t, g, rho_b, rho_w):
        """(I_b, I_w, I_c) for materials and backgrounds (arrays broadcast; NaN outside the map)."""
        A, B, C = self.coefficients(alpha, sigma_t, g)
        rho_b, rho_w = np.asarray(rho_b, dtype=float), np.asarray(rho_w, dtype=float)
        I_b = background_response(A, B, C, rho_b)
        I_w = background_response(A, B, C, rho_w)
        I_c = np.where(np.isnan(A), np.nan, self.collimated_measured(alpha, np.asarray(sigma_t, dtype=float), g))
        return I_b, I_w, I_c


def shipped_maps() -> list[Path]:
    """The maps that ship with trimeter (maps/*.tmap), sorted by name."""
    return sorted(MAPS_DIR.glob(f"*{MAP_SUFFIX}"))


def find_map(name_or_path: str | Path) -> Path:
    """A map given by path, or by the name of a shipped map (`device-l0.4`, …)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    for candidate in shipped_maps():
        if candidate.stem == str(name_or_path):
            return candidate
    names = ", ".join(c.stem for c in shipped_maps()) or "none built yet"
    raise InputError(f"map {str(name_or_path)!r} is neither a file nor a shipped map (shipped: {names})")


def inscatter_mismatch(table: InscatterTable, amap: AppearanceMap) -> str | None:
    """Why the table does not belong to the map (None when it does): another n, ℓ or geometry, or a
    parent stamp that is not this map's SHA-256 (a table is only as good as the map it was made for)."""
    if why := table.setup_mismatch(amap.setup):
        return why
    if amap.checksum and table.parent_sha256 != amap.checksum:
        made_for = (f"it was made for map {table.parent_sha256[:12]}…" if table.parent_sha256 else
                    "it does not record the map it was made for")
        return (f"{made_for}, and this map is {amap.checksum[:12]}… (rebuilt since?); rebuild the table: "
                f"{rebuild_command(amap, 'tins')}")
    return None


def map_model_variance(amap: AppearanceMap) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The map's own error variance of (I_b, I_w) at its nodes, at its reference backgrounds:
    (variances (na, ns, ng, 2), α, ln σt, g axes) for ForwardGrid.attach_model_variance."""
    rb, rw = amap.reference_rhos
    values = np.stack([background_response(amap.A, amap.B, amap.C, rho) for rho in (rb, rw)], axis=-1)
    axes = (np.asarray(amap.alpha, float), np.log(np.asarray(amap.sigma_t, float)), np.asarray(amap.g, float))
    var = node_model_variance(values, np.stack([amap.std_b, amap.std_w], axis=-1), *axes)
    return var, axes
