"""Map recipes: a TOML file → a validated `Recipe` (impossible values → InputError naming the field).

    name = "ideal-n1.5-l0.5"
    geometry = "ideal"              # a preset of hardware/geometry.toml
    n = 1.5
    thickness_mm = 0.5
    reference_rho_b = 0.02          # backgrounds at which per-point std-errors are reported
    reference_rho_w = 0.9
    seed = 1
    polarisation = false            # optional: track s and p at the interfaces (Walk's model; off: unpolarised Fresnel)

    [grid]
    alpha = { max = 0.999, count = 40 }            # 0 … max, log-spaced in 1 − α (finer near 1)
    sigma_t = { min = 0.05, max = 50, count = 24 }  # log-spaced [1/mm] (finer at low σt)
    g = { min = 0.0, max = 0.9, count = 10, spacing = "log1m" }  # log-spaced in 1 − g (default: even)
    # any axis may instead be an explicit strictly increasing list: g = [0, 0.3, 0.6, 0.9]

    [sampling]
    target_stderr = 5e-4     # per (σt, g) column: max over α of the std-error of I at both reference ρ
    min_paths = 131072       # first batch
    max_paths = 2097152      # cap per column (the std-error reached is recorded either way)
    target_alpha_stderr = 1e-3  # optional: also trace until the α std-error (g held) is this small
    truncation = 1e-5        # paths stop after K scatterings with α_max^K ≤ truncation

The recipe dict stored in a map (`Recipe.to_dict`) holds all of this plus `geometry_params`, the
preset as loaded, so a map is self-describing even if hardware/geometry.toml changes later.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from trimeter.errors import InputError
from trimeter.geometry import PRESETS, load_geometry
from trimeter.model.response import REFERENCE_RHOS
from trimeter.validation import require_number, require_reflectance, require_sample

_TOP_KEYS = {"name", "geometry", "n", "thickness_mm", "reference_rho_b", "reference_rho_w", "seed", "grid",
             "sampling", "description", "polarisation"}
_SAMPLING_DEFAULTS = {"target_stderr": 5e-4, "min_paths": 131072, "max_paths": 2097152, "truncation": 1e-5,
                      "target_alpha_stderr": None}


def fresnel_model(polarisation: bool) -> str:
    """How a recipe's (a map's, a held-out set's, the twin's) faces reflect, as every listing names it."""
    return "per polarisation" if polarisation else "unpolarised"


@dataclass(frozen=True)
class Sampling:
    target_stderr: float = 5e-4
    min_paths: int = 131072
    max_paths: int = 2097152
    truncation: float = 1e-5
    # Optional second criterion in α units: what the inversion sees. A uniform intensity target
    # leaves clear samples (σt·ℓ ≪ 1, where I barely changes with α) 10× noisier in α than
    # optically dense ones; this one spends the paths where they change the answer.
    target_alpha_stderr: float | None = None

    def to_dict(self) -> dict:
        # unset options are left out, so recipes that do not use them keep their fingerprint
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True)
class Recipe:
    name: str
    geometry: str
    geometry_params: dict
    n: float
    thickness_mm: float
    reference_rho_b: float
    reference_rho_w: float
    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray
    seed: int = 1
    sampling: Sampling = field(default_factory=Sampling)
    description: str = ""
    # the tracer's `polarisation` option (trimeter.forward.transport.walk.Walk)
    polarisation: bool = False

    def to_dict(self) -> dict:
        """The recipe as stored in a map's metadata (the keys AppearanceMap relies on included);
        `polarisation` only when on, so recipes without it keep their fingerprint."""
        out = {"name": self.name, "description": self.description, "geometry": self.geometry,
               "geometry_params": self.geometry_params, "n": self.n, "thickness_mm": self.thickness_mm,
               "reference_rho_b": self.reference_rho_b, "reference_rho_w": self.reference_rho_w,
               "seed": self.seed, "sampling": self.sampling.to_dict(),
               "grid": {"alpha": self.alpha.tolist(), "sigma_t": self.sigma_t.tolist(), "g": self.g.tolist()}}
        if self.polarisation:
            out["polarisation"] = True
        return out

    @property
    def shape(self) -> tuple[int, int, int]:
        return len(self.alpha), len(self.sigma_t), len(self.g)


def load_recipe(path: str | Path) -> Recipe:
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise InputError(f"recipe {path}: cannot read ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"recipe {path}: not valid TOML ({exc})") from None
    return parse_recipe(data, default_name=path.stem)


def parse_recipe(data: dict, default_name: str = "map") -> Recipe:
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise InputError(f"recipe: unknown key {unknown[0]!r} (known: {', '.join(sorted(_TOP_KEYS))})")
    geometry = data.get("geometry")
    if geometry not in PRESETS:
        raise InputError(f"geometry must be one of {', '.join(PRESETS)}, got {geometry!r}")
    n, thickness = require_sample(data.get("n"), data.get("thickness_mm"))
    rho_b = require_reflectance("reference_rho_b", data.get("reference_rho_b", REFERENCE_RHOS[0]))
    rho_w = require_reflectance("reference_rho_w", data.get("reference_rho_w", REFERENCE_RHOS[1]))
    seed = int(require_number("seed", data.get("seed", 1), lo=0, hi=2**31 - 1))
    name = data.get("name", default_name)
    polarisation = data.get("polarisation", False)
    if not isinstance(polarisation, bool):
        raise InputError(f"polarisation must be true or false, got {polarisation!r}")
    # the name becomes a file and checkpoint directory name: nothing a file system refuses or reads as a path
    if not isinstance(name, str) or not name or len(name) > 200 or name in (".", "..") \
            or any(c in "/\\" or ord(c) < 0x20 or ord(c) == 0x7F for c in name):
        raise InputError(f"name must be 1-200 characters without '/', '\\' or control characters (NUL, newline), "
                         f"got {name[:80]!r}" if isinstance(name, str) else f"name must be a string, got {name!r}")

    grid = data.get("grid")
    if not isinstance(grid, dict):
        raise InputError("grid: missing table [grid] with alpha, sigma_t, g")
    extra = sorted(set(grid) - {"alpha", "sigma_t", "g"})
    if extra:
        raise InputError(f"grid: unknown key {extra[0]!r}")
    alpha = _axis("grid.alpha", grid.get("alpha"), _alpha_axis)
    sigma_t = _axis("grid.sigma_t", grid.get("sigma_t"), _log_axis)
    g = _axis("grid.g", grid.get("g"), _linear_axis)
    if alpha[0] < 0 or alpha[-1] >= 1:
        raise InputError(f"grid.alpha must lie in [0, 1) (α = 1 never ends a path), got {alpha[0]:g}…{alpha[-1]:g}")
    if sigma_t[0] <= 0:
        raise InputError(f"grid.sigma_t must be > 0 [1/mm], got {sigma_t[0]:g}")
    if g[0] <= -1 or g[-1] >= 1:
        raise InputError(f"grid.g must lie in (-1, 1), got {g[0]:g}…{g[-1]:g}")

    s = data.get("sampling", {})
    if not isinstance(s, dict):
        raise InputError("sampling must be a table")
    extra = sorted(set(s) - set(_SAMPLING_DEFAULTS))
    if extra:
        raise InputError(f"sampling: unknown key {extra[0]!r}")
    s = {**_SAMPLING_DEFAULTS, **s}
    sampling = Sampling(
        target_stderr=require_number("sampling.target_stderr", s["target_stderr"], lo=0.0, lo_open=True),
        min_paths=int(require_number("sampling.min_paths", s["min_paths"], lo=1024)),
        max_paths=int(require_number("sampling.max_paths", s["max_paths"], lo=1024)),
        truncation=require_number("sampling.truncation", s["truncation"], lo=0.0, hi=0.1, lo_open=True),
        target_alpha_stderr=(None if s["target_alpha_stderr"] is None else
                             require_number("sampling.target_alpha_stderr", s["target_alpha_stderr"], lo=0.0,
                                            hi=1.0, lo_open=True)))
    if sampling.max_paths < sampling.min_paths:
        raise InputError(f"sampling.max_paths ({sampling.max_paths}) must be >= sampling.min_paths "
                         f"({sampling.min_paths})")
    return Recipe(name=name, geometry=geometry, geometry_params=load_geometry(geometry), n=n, thickness_mm=thickness,
                  reference_rho_b=rho_b, reference_rho_w=rho_w, alpha=alpha, sigma_t=sigma_t, g=g, seed=seed,
                  sampling=sampling, description=str(data.get("description", "")), polarisation=polarisation)


def _axis(field_name: str, spec: object, generator: Callable[[str, dict, int], np.ndarray]) -> np.ndarray:
    if spec is None:
        raise InputError(f"{field_name}: missing")
    if isinstance(spec, list):
        values = np.array([require_number(f"{field_name}[{i}]", v) for i, v in enumerate(spec)], dtype=float)
    elif isinstance(spec, dict):
        extra = sorted(set(spec) - {"min", "max", "count", "spacing"})
        if extra:
            raise InputError(f"{field_name}: unknown key {extra[0]!r}")
        count = int(require_number(f"{field_name}.count", spec.get("count"), lo=2, hi=10000))
        values = generator(field_name, spec, count)
    else:
        raise InputError(f"{field_name} must be a list or a table {{min, max, count}}")
    if len(values) < 2 or not np.all(np.diff(values) > 0):
        raise InputError(f"{field_name} must be strictly increasing with at least 2 values")
    return values


def _alpha_axis(field_name: str, spec: dict, count: int) -> np.ndarray:
    top = require_number(f"{field_name}.max", spec.get("max"), lo=0.0, hi=1.0, lo_open=True, hi_open=True)
    lo = require_number(f"{field_name}.min", spec.get("min", 0.0), lo=0.0, hi=top, hi_open=True)
    # log-spaced in 1 − α: as many points between 0.9 and 0.99 as between 0.99 and 0.999
    return 1 - np.geomspace(1 - lo, 1 - top, count)


def _log_axis(field_name: str, spec: dict, count: int) -> np.ndarray:
    lo = require_number(f"{field_name}.min", spec.get("min"), lo=0.0, lo_open=True)
    hi = require_number(f"{field_name}.max", spec.get("max"), lo=lo, lo_open=True)
    return np.geomspace(lo, hi, count)


def _linear_axis(field_name: str, spec: dict, count: int) -> np.ndarray:
    """Evenly spaced, or with spacing = "log1m" log-spaced in 1 − g: equal steps in the reduced
    extinction σt(1 − g), so finer towards g → 1 where I changes fastest."""
    lo = require_number(f"{field_name}.min", spec.get("min"))
    hi = require_number(f"{field_name}.max", spec.get("max"), lo=lo, lo_open=True)
    spacing = spec.get("spacing", "linear")
    if spacing == "linear":
        return np.linspace(lo, hi, count)
    if spacing == "log1m":
        if hi >= 1:
            raise InputError(f"{field_name}.max must be < 1 for spacing = 'log1m', got {hi:g}")
        return 1 - np.geomspace(1 - lo, 1 - hi, count)
    raise InputError(f"{field_name}.spacing must be 'linear' or 'log1m', got {spacing!r}")
