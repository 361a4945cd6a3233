"""The twin's virtual samples computed directly, not read off any appearance map: traced by the maps' own
tracer (not independent of the maps' physics: the same tracer, the same I(ρ) model), or, for the ideal
geometry, by adding-doubling (an integrator of its own).

The map the host inverts is an interpolant of the forward model; a twin that made its samples' I_b,
I_w, I_c with that same map would hide the map's own error (node spacing, its Monte Carlo noise), so
every round trip would look better than a real instrument can. Instead, `tools/make_twin_observables.py`
computes each catalogue material once per set-up (geometry, n, ℓ) at a coarse set of wavelength nodes,
with one of two integrators (the file's `integrator`):
- `tracer`: the project's tracer (trimeter.forward.transport, at the material's own α, σt, g — no map);
  per node the background-response coefficients (A, B, C of I(ρ) = A + Bρ/(1 − Cρ)) and the collimated
  beam's in-scattering L = ln(1 + r) (trimeter.forward.transport.inscatter_tracer's direct tracer; 0 for the
  ideal geometry, whose detector takes only the unscattered beam). All nodes of one material share their
  random numbers, so the Monte Carlo error is smooth in λ. The file's `polarisation` says whether the tracer
  tracked the two polarisations at the faces (as the map recipe of the same set-up does). L stays unpolarised,
  as the maps' in-scattering tables are: a small correction to I_c whose light enters and leaves near normal
  incidence, where s and p reflect alike (its bounces inside the slab at other angles are not tracked).
- `adding-doubling` (ideal geometry only): Prahl's adding-doubling (trimeter.forward.adding_doubling), exact
  for the ideal geometry up to its quadrature, which the file bounds per node by the change from doubling
  the quadrature points. No Monte Carlo, no tracer: a round trip against it shows the whole error of a map
  the tracer built.
Between the nodes the coefficients are interpolated with a cubic spline in λ: the materials are smooth
sums of Gaussian bands of ≥ 35 nm width. The spline is part of the twin's truth's own error: through the
traced files' 20 nm nodes it misses the catalogue's sharpest band (the white ink's edge) by about the
traces' Monte Carlo error; through the adding-doubling files' 5 nm nodes it is far below their quadrature's
error. The unscattered beam is analytic (Beer-Lambert with the Fresnel stack) at every pixel.

Data: host/trimeter/data/twin_observables/<geometry>-n<n>-l<ℓ>.json, one file per set-up, with the
hash of each material's catalogue entry and of the geometry: a material or geometry changed since
the computation makes the data stale (an error, naming the tool to re-run).

What traced observables cannot show: errors the maps' tracer and their I(ρ) model make (e.g. one return
coefficient C; Fresnel unpolarised where neither tracks polarisation, every scattering depolarising where both
do), since the twin's samples are made the same way. What adding-doubling shares with the maps: only the ideal
geometry's model itself (an infinite slab over a Lambertian background under uniform light, unpolarised
Fresnel).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy.interpolate import CubicSpline

from trimeter.errors import InputError
from trimeter.geometry import cover_slide_n
from trimeter.maps.recipe import fresnel_model
from trimeter.model.collimated import collimated_transmittance

DATA_DIR = Path(__file__).resolve().parents[1] / "data" / "twin_observables"
FORMAT_VERSION = 1
MAX_FILE_BYTES = 4_000_000
# The integrators a file's observables may come from (its `integrator`; a file without one was traced), and
# the name a virtual sample's physics takes from each (trimeter.twin.optics.PHYSICS).
INTEGRATOR_PHYSICS = {"tracer": "traced", "adding-doubling": "adding-doubling"}


def setup_name(geometry: str, n: float, thickness_mm: float) -> str:
    return f"{geometry}-n{n:g}-l{thickness_mm:g}"


def content_hash(value: object) -> str:
    """A short stable hash of a JSON-able value (a material's catalogue entry, a geometry preset)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class SetupObservables:
    """One set-up's directly computed observables (traced, or by adding-doubling: `integrator`): per material,
    coefficients at wavelength nodes."""

    geometry: str
    n: float
    thickness_mm: float
    geometry_hash: str
    materials: dict          # name → {"material_hash", "wavelength_nm", "A", "B", "C", "L", ...}
    provenance: dict
    path: Path
    integrator: str = "tracer"   # a key of INTEGRATOR_PHYSICS
    polarisation: bool = False   # traced with the two polarisations tracked at the faces

    @property
    def physics(self) -> str:
        """Where a sample of this set-up comes from, as trimeter.twin.optics.PHYSICS names it."""
        return INTEGRATOR_PHYSICS[self.integrator]

    def observables(self, name: str, material_entry: dict, geometry_params: dict, wavelengths_nm: ArrayLike,
                    rho_b: np.ndarray, rho_w: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """(I_b, I_w, L, I_open) of material `name` at `wavelengths_nm` on backgrounds ρ_b(λ), ρ_w(λ)
        (L: the collimated beam's in-scattering, for `collimated`), or None if it was not traced."""
        if name not in self.materials:
            return None
        m = self.materials[name]
        stale = []
        if m["material_hash"] != content_hash(material_entry):
            stale.append(f"material {name!r} changed in materials.toml")
        if self.geometry_hash != content_hash(geometry_params):
            stale.append(f"geometry {self.geometry!r} changed in hardware/geometry.toml")
        if stale:
            raise InputError(f"{self.path.name} is stale ({'; '.join(stale)}): re-run tools/make_twin_observables.py")
        lam = np.asarray(wavelengths_nm, dtype=float)
        nodes = np.asarray(m["wavelength_nm"], dtype=float)
        A, B, C, L = (CubicSpline(nodes, np.asarray(m[k], dtype=float))(lam) for k in ("A", "B", "C", "L"))
        C = np.clip(C, 0.0, 0.999)
        I_b = A + B * rho_b / (1.0 - C * rho_b)
        I_w = A + B * rho_w / (1.0 - C * rho_w)
        return I_b, I_w, L, A

    def source(self) -> str:
        """How these observables were made: the file and its provenance (tool, integrator, paths per node and
        seed, or quadrature points)."""
        p = {**self.provenance, "integrator": self.integrator}
        if self.integrator == "tracer":
            p["Fresnel"] = fresnel_model(self.polarisation)
        made = ", ".join(f"{k} {p[k]}" for k in ("tool", "integrator", "Fresnel", "paths_per_node", "seed",
                                                 "quad_points", "written_utc") if k in p)
        return f"{self.path.name} ({made or 'no provenance recorded'})"

    def collimated(self, sigma_t: np.ndarray, L: np.ndarray, geometry_params: dict) -> np.ndarray:
        """I_c: the analytic unscattered beam times (1 + r), r the traced in-scattered fraction."""
        unscattered = collimated_transmittance(sigma_t, self.thickness_mm, self.n, cover_slide_n(geometry_params))
        return unscattered * np.exp(L)


def _check(doc: dict, path: Path) -> None:
    if not isinstance(doc, dict) or doc.get("format_version") != FORMAT_VERSION:
        raise InputError(f"{path}: not a version-{FORMAT_VERSION} twin observables file")
    for key in ("geometry", "n", "thickness_mm", "geometry_hash", "materials"):
        if key not in doc:
            raise InputError(f"{path}: lacks {key!r}")
    if doc.get("integrator", "tracer") not in INTEGRATOR_PHYSICS:
        raise InputError(f"{path}: integrator must be one of {', '.join(INTEGRATOR_PHYSICS)}, got "
                         f"{doc.get('integrator')!r}")
    if not isinstance(doc.get("polarisation", False), bool):
        raise InputError(f"{path}: polarisation must be true or false, got {doc.get('polarisation')!r}")
    for name, m in doc["materials"].items():
        nodes = np.asarray(m.get("wavelength_nm", []), dtype=float)
        if nodes.ndim != 1 or len(nodes) < 4 or not np.all(np.diff(nodes) > 0):
            raise InputError(f"{path}: {name}: wavelength_nm must be ≥ 4 increasing nodes")
        for k in ("A", "B", "C", "L"):
            v = np.asarray(m.get(k, []), dtype=float)
            if v.shape != nodes.shape or not np.all(np.isfinite(v)):
                raise InputError(f"{path}: {name}: {k} must be {len(nodes)} finite numbers")


@lru_cache(maxsize=16)
def _load(path: Path) -> SetupObservables:
    if path.stat().st_size > MAX_FILE_BYTES:
        raise InputError(f"{path}: larger than {MAX_FILE_BYTES} bytes")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: unreadable ({exc})") from None
    _check(doc, path)
    return SetupObservables(geometry=doc["geometry"], n=float(doc["n"]), thickness_mm=float(doc["thickness_mm"]),
                            geometry_hash=doc["geometry_hash"], materials=doc["materials"],
                            provenance=doc.get("provenance", {}), path=path, integrator=doc.get("integrator", "tracer"),
                            polarisation=doc.get("polarisation", False))


def setup_observables(geometry: str, n: float, thickness_mm: float) -> SetupObservables | None:
    """The directly computed observables of a set-up (traced or by adding-doubling), or None when there are
    none for it."""
    path = DATA_DIR / f"{setup_name(geometry, n, thickness_mm)}.json"
    if not math.isfinite(thickness_mm) or not path.is_file():
        return None
    return _load(path)


def available_setups() -> list[str]:
    return sorted(p.stem for p in DATA_DIR.glob("*.json"))
