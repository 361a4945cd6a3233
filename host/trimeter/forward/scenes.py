"""Mitsuba 3 scene dicts for the two geometry presets of hardware/geometry.toml.

Units are millimetres throughout, so a medium's `sigma_t` is σt in 1/mm as it stands. Each scene holds
only what its observable (one diffuse reflectance factor) needs: the sample, the background, the
light, one single-pixel sensor and a volumetric path tracer. Mitsuba is never imported here: these
are plain dicts; `trimeter.forward.render` loads them.

ideal  (paper Fig. 2) — a slab of width `slab_width_mm`, smooth `dielectric` faces of index n in air,
       perfectly mirroring sides (so it is laterally infinite, see _ideal), `homogeneous` medium with
       an `hg` phase function; a Lambertian rectangle, twice as wide, an air gap under it (ray
       offsets must not skip it, see _ideal; for an infinite slab the gap changes nothing), walled
       in by mirrors as well; a
       `constant` emitter of radiance 1; one
       `radiancemeter` along the normal. I = radiance / 1.

device (paper Figs. 6-8) — the frame is the instrument's: z = 0 is the back face of the sample stack
       (where it rests in the holder), +z points at the detector. The sample (sample_width_mm square,
       thickness ℓ) is sandwiched between cover slides of index `cover_slide_n` with index-matched
       oil, so there are four smooth interfaces air|glass|sample|glass|air (collimated.py uses the
       same stack). It is built from rectangles rather than cubes so that no two surfaces coincide:
       each face carries the dielectric of the two media it separates and the sample's faces carry
       the medium as `interior`. The background (background_width_mm square) lies `background_gap_mm`
       behind the stack. Two Lambertian rectangles of radiance 1 (the LED panels; `width_mm` runs
       horizontally, perpendicular to the plane holding the panel axis and the normal, `height_mm`
       lies in that plane) face the origin from `distance_mm` at `elevation_deg` from the normal.
       The detector is an `orthographic` 1×1 sensor along −z covering a square of the spot's area
       (a pinhole spatial filter with a 0.5° acceptance is, to this accuracy, parallel rays).

Reflectance factor (device): the calibration divides the sample's signal by the white reference's
(a Lambertian of reflectance ρ_ref at the background plane, no sample) and multiplies by ρ_ref. The
reference's radiance is ρ_ref·E/π, with E the irradiance the two panels (radiance 1) give at the
spot, so the factor is I = L·π/E, independent of ρ_ref. E is computed here once per geometry in
closed form (Lambert's formula for a polygonal Lambertian source); tests/forward renders the white
reference and checks that it comes back as ρ_ref.
"""

from __future__ import annotations

import math

import numpy as np

from trimeter.errors import InputError
from trimeter.geometry import cover_slide_n, cover_slide_thickness_mm, load_geometry

MEDIUM_ID = "sample_medium"
MIN_GAP_MM = 1e-3
# The parameters a cached, loaded scene updates in place between renders (mi.traverse keys).
PARAM_KEYS = {
    "alpha": f"{MEDIUM_ID}.albedo.value.value",
    "sigma_t": f"{MEDIUM_ID}.sigma_t.value.value",
    "g": f"{MEDIUM_ID}.phase_function.g",
    "rho": "background.bsdf.reflectance.value",
}


def resolve_geometry(geometry) -> tuple[str, dict]:
    """(preset name, parameters) from a preset name or a preset's dict (e.g. a map recipe's
    `geometry_params`); a dict with `panels` is a device geometry, otherwise ideal."""
    if isinstance(geometry, str):
        return geometry, load_geometry(geometry)
    if isinstance(geometry, dict):
        return ("device" if "panels" in geometry else "ideal"), geometry
    raise InputError(f"geometry must be a preset name or a preset dict, got {type(geometry).__name__}")


ROULETTE_MAX_ALPHA = 0.95
TRUNCATION = 1e-6
EVENTS_PER_SCATTERING = 16


def integrator_for(alpha: float) -> dict:
    """The volpath settings for albedo α. Volpath continues a path with probability
    min(throughput·η², 0.95): at α > 0.95 a path's throughput hardly falls, so survivors gain 1/0.95
    per event and the long paths of thick, high-albedo samples carry weights like 0.95^−1000
    (measured at α = 0.9989, σt = 27/mm, ℓ = 0.5 mm, ρ = 0.99: 0.77 ± 0.06 against adding-doubling's
    0.869; without roulette 0.8688 ± 0.0003). So above α = 0.95: no roulette, and paths are cut at a
    power-of-two depth D ≥ 16·ln(1e-6)/ln α (16 interactions per scattering event leave room for
    Fresnel and background bounces; the cut path's remaining weight is ≤ α^(D/16) ≤ 1e-6; bucketed
    so few kernels get compiled). At α ≤ 0.95 roulette weights never grow: volpath's default."""
    if alpha <= ROULETTE_MAX_ALPHA:
        return {"type": "volpath", "max_depth": -1, "rr_depth": 5}
    if alpha >= 1.0:
        return {"type": "volpath", "max_depth": -1, "rr_depth": 1 << 30}
    depth = EVENTS_PER_SCATTERING * math.log(TRUNCATION) / math.log(alpha)
    return {"type": "volpath", "max_depth": 1 << max(8, math.ceil(math.log2(depth))), "rr_depth": 1 << 30}


def scene_dict(geometry, alpha: float, sigma_t: float, g: float, n: float, thickness_mm: float,
               rho: float, spp: int = 65536, integrator: dict | None = None, phase: str = "hg") -> dict:
    """The scene for one material, sample and background; `integrator` replaces volpath (the fast
    map builder passes its own); `phase` the medium's phase function plugin (trimeter.forward.phase).
    Values are not validated here (trimeter.validation does it)."""
    name, params = resolve_geometry(geometry)
    medium = {"type": "homogeneous", "id": MEDIUM_ID, "albedo": float(alpha), "sigma_t": float(sigma_t),
              "scale": 1.0, "phase": {"type": phase, "g": float(g)}}
    scene = {"type": "scene", "integrator": integrator or integrator_for(float(alpha)), MEDIUM_ID: medium}
    if name == "ideal":
        scene.update(_ideal(params, float(n), float(thickness_mm), float(rho), int(spp)))
    else:
        scene.update(_device(params, float(n), float(thickness_mm), float(rho), int(spp)))
    return scene


def translated(scene: dict, dz: float) -> dict:
    """The scene moved by `dz` along +z as a whole (shapes, sensor): the same optics, but Mitsuba's ray
    offsets, which grow with the coordinates (trimeter.forward.render.render_diffuse_offset_free), grow."""
    shift = np.eye(4)
    shift[2, 3] = dz
    out = {}
    for key, value in scene.items():
        if isinstance(value, dict):
            value = dict(value)
            if isinstance(value.get("to_world"), _Transform):
                value["to_world"] = _Transform(shift @ value["to_world"].matrix)
            if value.get("type") == "radiancemeter":
                value["origin"] = [value["origin"][0], value["origin"][1], value["origin"][2] + dz]
        out[key] = value
    return out


def top_face_z(geometry, thickness_mm: float) -> float:
    """z of the sample stack's top face in the scene (ideal: the slab's, at 0; device: the front cover
    slide's, the stack's back face at 0)."""
    name, params = resolve_geometry(geometry)
    if name == "ideal":
        return 0.0
    return float(thickness_mm) + 2 * cover_slide_thickness_mm(params)


def reflectance_scale(geometry) -> float:
    """Factor turning the scene's sensor radiance into the reflectance factor I: 1 for `ideal`
    (illumination radiance 1), π/E for `device` (the white-reference calibration, see module doc)."""
    name, params = resolve_geometry(geometry)
    if name == "ideal":
        return 1.0
    return math.pi / panel_irradiance(params, np.array([0.0, 0.0, -_gap(params)]))


# ------------------------------------------------------------------------------------------ ideal
def _ideal(p: dict, n: float, ell: float, rho: float, spp: int) -> dict:
    half = float(p["slab_width_mm"]) / 2
    # Mitsuba offsets spawned rays by ~1e-4 × (1 + |position|) in float32: a background closer than
    # that to the slab is skipped near the edges and the emitter shines through from below (+6 % at
    # α = 0.99, σt = 1/mm, ℓ = 0.5 mm, g = 0.8 with a 1 µm gap under a 1000 mm slab). For an infinite
    # slab on a Lambertian background the air gap changes nothing, so keep one of 1 % of the width.
    gap = max(float(p.get("background_gap_mm", 0.0)), 0.01 * 2 * half)
    medium = {"type": "ref", "id": MEDIUM_ID}
    boundary = _interface(n, 1.0)
    # Top face at z = 0. The side faces are perfect mirrors: by the method of images a mirror-walled
    # slab under uniform light is the infinite slab, at any width. (Light that total internal
    # reflection traps travels ~1/(σt(1 − α)) sideways — 100 mm at α = 0.99, σt = 1/mm — and would
    # otherwise leave, or the sky enter, through open sides.)
    shapes = {
        "illumination": {"type": "constant", "radiance": {"type": "uniform", "value": 1.0}},
        "slab_top": _rect([0, 0, 0.0], [0, 0, 1], [half, half], boundary, interior=medium),
        "slab_bottom": _rect([0, 0, -ell], [0, 0, -1], [half, half], boundary, interior=medium),
        # Wider than the slab, so the whole lower hemisphere under the slab sees background.
        "background": _lambertian_rect([0, 0, -ell - gap], [2 * half, 2 * half], rho),
        "sensor": {"type": "radiancemeter", "origin": [0.0, 0.0, 1.0], "direction": [0.0, 0.0, -1.0],
                   "film": _one_pixel_film(), "sampler": {"type": "independent", "sample_count": spp}},
    }
    # A conductor is one-sided: its normal faces the slab, whose medium is therefore its exterior.
    mirror = {"type": "conductor", "material": "none"}
    for i, (normal, centre) in enumerate(_side_walls(half, -ell / 2)):
        shapes[f"slab_side{i}"] = {**_rect(centre, [-c for c in normal], [half, ell / 2], mirror), "exterior": medium}
    # The air gap is walled in too: through its open sides the sky lit the background at grazing angles
    # (figures: the git history of maps/README.md).
    for i, (normal, centre) in enumerate(_side_walls(half, -ell - gap / 2)):
        shapes[f"gap_side{i}"] = _rect(centre, [-c for c in normal], [half, gap / 2], mirror)
    return shapes


# ----------------------------------------------------------------------------------------- device
def _gap(p: dict) -> float:
    return max(float(p.get("background_gap_mm", 0.0)), MIN_GAP_MM)


def _device(p: dict, n: float, ell: float, rho: float, spp: int) -> dict:
    half = float(p["sample_width_mm"]) / 2
    n_slides = cover_slide_n(p)
    t_s = cover_slide_thickness_mm(p)
    n_s = n_slides if n_slides is not None else 1.0
    z_back, z_front = t_s, t_s + ell                 # the sample's own faces
    medium = {"type": "ref", "id": MEDIUM_ID}
    shapes = {}
    # Front (+z) and back (−z) faces of the sample: sample | glass (or air without slides).
    inner = _interface(n, n_s)
    shapes["sample_front"] = _rect([0, 0, z_front], [0, 0, 1], [half, half], inner, interior=medium)
    shapes["sample_back"] = _rect([0, 0, z_back], [0, 0, -1], [half, half], inner, interior=medium)
    for i, (normal, centre) in enumerate(_side_walls(half, (z_back + z_front) / 2)):
        shapes[f"sample_side{i}"] = _rect(centre, normal, [half, ell / 2], _interface(n, 1.0), interior=medium)
    if n_slides is not None:
        glass = _interface(n_slides, 1.0)
        shapes["slide_front"] = _rect([0, 0, z_front + t_s], [0, 0, 1], [half, half], glass)
        shapes["slide_back"] = _rect([0, 0, 0.0], [0, 0, -1], [half, half], glass)
        for zc, tag in ((z_front + t_s / 2, "front"), (t_s / 2, "back")):
            for i, (normal, centre) in enumerate(_side_walls(half, zc)):
                shapes[f"slide_{tag}_side{i}"] = _rect(centre, normal, [half, t_s / 2], glass)
    bg_half = float(p["background_width_mm"]) / 2
    shapes["background"] = _lambertian_rect([0, 0, -_gap(p)], [bg_half, bg_half], rho)
    for i, (centre, size) in enumerate(_panels(p)):
        # Black: pure Lambertian emitters, as the closed-form normalisation assumes. (Mitsuba's default
        # diffuse 0.5 lets each panel reflect the other's light onto the sample: +1.6 % on the white
        # reference.) The calibration divides any such stray light out anyway.
        facing = list(-centre / np.linalg.norm(centre))
        shapes[f"panel{i}"] = {**_rect(centre, facing, size, _BLACK, up=[0.0, 1.0, 0.0]),
                               "emitter": {"type": "area", "radiance": {"type": "uniform", "value": 1.0}}}
    det = p["detector"]
    side = float(det["spot_diameter_mm"]) * math.sqrt(math.pi) / 2  # square of the spot's area
    z_det = z_front + t_s + float(det["distance_mm"])
    shapes["sensor"] = {
        "type": "orthographic",
        "to_world": _look_at([0, 0, z_det], [0, 0, z_det - 1], [0, 1, 0], scale=[side / 2, side / 2, 1]),
        "film": _one_pixel_film(), "sampler": {"type": "independent", "sample_count": spp}}
    return shapes


_BLACK = {"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}}


def _interface(n_inside: float, n_outside: float) -> dict:
    if abs(n_inside - n_outside) < 1e-9:
        return {"type": "null"}                       # index-matched: no interface at all
    return {"type": "dielectric", "int_ior": n_inside, "ext_ior": n_outside}


def _side_walls(half: float, z_centre: float):
    return [((sx, sy, 0.0), (sx * half, sy * half, z_centre))
            for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1))]


def _panels(p: dict):
    """(centre, half-size along the rectangle's local x, y) for each panel, aimed at the origin."""
    pan = p["panels"]
    elev = math.radians(float(pan["elevation_deg"]))
    dist = float(pan["distance_mm"])
    out = []
    for az_deg in pan["azimuths_deg"][: int(pan["count"])]:
        az = math.radians(float(az_deg))
        centre = dist * np.array([math.sin(elev) * math.cos(az), math.sin(elev) * math.sin(az), math.cos(elev)])
        # With up = +y, look_at's local x lies in the plane of the axis and the normal (height),
        # local y is horizontal (width) — exact for azimuths 0° and 180°.
        out.append((centre, [float(pan["height_mm"]) / 2, float(pan["width_mm"]) / 2]))
    return out


def panel_corners(p: dict) -> list[np.ndarray]:
    """World-space corners (4×3, in order around the rectangle) of each panel."""
    corners = []
    for centre, (hx, hy) in _panels(p):
        axis = -centre / np.linalg.norm(centre)
        ex, ey = _frame(axis, np.array([0.0, 1.0, 0.0]))
        corners.append(np.array([centre + sx * hx * ex + sy * hy * ey
                                 for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]))
    return corners


def panel_irradiance(p: dict, point: np.ndarray, normal=(0.0, 0.0, 1.0)) -> float:
    """Irradiance at `point` (surface normal `normal`) from the panels at radiance 1, by Lambert's
    contour formula E = ½ Σ_edges Γ_i n̂·(r_i × r_{i+1})/|r_i × r_{i+1}| (exact for an unoccluded
    planar polygon wholly above the receiver's horizon)."""
    normal = np.asarray(normal, dtype=float)
    total = 0.0
    for quad in panel_corners(p):
        r = quad - point
        r = r / np.linalg.norm(r, axis=1, keepdims=True)
        e = 0.0
        for i in range(len(r)):
            a, b = r[i], r[(i + 1) % len(r)]
            c = np.cross(a, b)
            gamma = math.acos(max(-1.0, min(1.0, float(a @ b))))
            e += gamma * float(normal @ c) / float(np.linalg.norm(c))
        total += abs(e) / 2
    return total


# ------------------------------------------------------------------------------------- helpers
def _one_pixel_film() -> dict:
    return {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "luminance"}


def _lambertian_rect(centre, half_size, rho: float) -> dict:
    return {"type": "rectangle", "to_world": _translate_scale(centre, [half_size[0], half_size[1], 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "uniform", "value": float(rho)}}}


def _rect(centre, normal, half_size, bsdf: dict, interior: dict | None = None, up=None) -> dict:
    """A rectangle centred at `centre` whose normal (the dielectric's exterior side) is `normal`."""
    normal = np.asarray(normal, dtype=float)
    if up is None:
        up = [0.0, 1.0, 0.0] if abs(normal[2]) > 0.5 else [0.0, 0.0, 1.0]
    centre = np.asarray(centre, dtype=float)
    shape = {"type": "rectangle", "bsdf": bsdf,
             "to_world": _look_at(centre, centre + normal, up, scale=[half_size[0], half_size[1], 1.0])}
    if interior is not None:
        shape["interior"] = interior
    return shape


def _frame(axis: np.ndarray, up: np.ndarray):
    """The local x, y axes Mitsuba's look_at gives for local z = axis."""
    left = np.cross(up, axis)
    left /= np.linalg.norm(left)
    new_up = np.cross(axis, left)
    return left, new_up


def _matrix(translate, columns, scale) -> np.ndarray:
    m = np.eye(4)
    for j in range(3):
        m[:3, j] = np.asarray(columns[j], dtype=float) * scale[j]
    m[:3, 3] = translate
    return m


def _look_at(origin, target, up, scale=(1.0, 1.0, 1.0)):
    origin, target, up = (np.asarray(v, dtype=float) for v in (origin, target, up))
    axis = (target - origin) / np.linalg.norm(target - origin)
    left, new_up = _frame(axis, up)
    return _Transform(_matrix(origin, (left, new_up, axis), scale))


def _translate_scale(centre, scale):
    return _Transform(_matrix(np.asarray(centre, dtype=float), np.eye(3), scale))


class _Transform:
    """A 4×4 matrix that becomes a mitsuba.ScalarTransform4f when the scene is loaded (keeps this
    module free of a Mitsuba import; trimeter.forward.render converts)."""

    def __init__(self, matrix: np.ndarray):
        self.matrix = matrix

    def __repr__(self):
        return f"_Transform({self.matrix.tolist()})"
