"""Scene geometry of the map tracer: the layer stack, its surroundings and lights (from a recipe), and
the closed-form intersections the paths need (side faces, panels, interfaces)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Panel:
    center: tuple[float, float, float]
    normal: tuple[float, float, float]      # facing the sample
    axis_u: tuple[float, float, float]
    axis_v: tuple[float, float, float]
    half_u: float
    half_v: float


@dataclass(frozen=True)
class Stack:
    """The layer stack and its surroundings in mm; z up, the sample's top face at z = ℓ (+ slide)."""

    layer_n: tuple[float, ...]              # refractive index of each layer, top → bottom
    plane_z: tuple[float, ...]              # z of the len(layer_n)+1 interfaces, top → bottom
    sample_layer: int
    background_z: float
    stack_half_width: float = math.inf      # lateral half-width of the stack (inf: slab)
    background_half_width: float = math.inf
    panels: tuple[Panel, ...] = ()          # empty: uniform sky of radiance 1 (ideal)
    detector_half_side: float = 0.0        # the detector's spot: a square of the spot's area
    scale: float = 1.0                      # observable per unit of radiance reaching the detector

    @property
    def factorises(self) -> bool:
        """Whether B = UT1·UTU holds exactly: a laterally unbounded stack over an unbounded Lambertian
        background under a uniform sky (the ideal geometry), where the background forgets where and
        from which direction a path arrived."""
        return (not self.panels and not math.isfinite(self.stack_half_width)
                and not math.isfinite(self.background_half_width))

    @classmethod
    def from_recipe(cls, geometry: str, geometry_params: dict, n: float, thickness_mm: float) -> "Stack":
        """The stack in the frame of trimeter.forward.scenes (the direct-render reference): z = 0 is
        the back face of the sample stack, +z points at the detector. Panels, their orientation and
        the white-reference normalisation come from that module, so both agree by construction."""
        if geometry == "ideal":
            gap = float(geometry_params.get("background_gap_mm", 0.0))
            return cls(layer_n=(n,), plane_z=(thickness_mm, 0.0), sample_layer=0, background_z=-gap)
        if geometry != "device":
            raise ValueError(f"unknown geometry {geometry!r}")
        from trimeter.forward.scenes import panel_corners, reflectance_scale
        from trimeter.geometry import cover_slide_n, cover_slide_thickness_mm

        p = geometry_params
        ng = cover_slide_n(p)
        layers: tuple[float, ...]
        planes: tuple[float, ...]
        if ng is not None:
            s = cover_slide_thickness_mm(p)
            layers, planes, sample = (ng, n, ng), (2 * s + thickness_mm, s + thickness_mm, s, 0.0), 1
        else:
            layers, planes, sample = (n,), (thickness_mm, 0.0), 0
        side = float(p["detector"]["spot_diameter_mm"]) * math.sqrt(math.pi) / 2  # square of the spot's area
        return cls(layer_n=layers, plane_z=planes, sample_layer=sample,
                   background_z=-float(p["background_gap_mm"]),
                   stack_half_width=float(p["sample_width_mm"]) / 2,
                   background_half_width=float(p["background_width_mm"]) / 2,
                   panels=tuple(_panel_from_corners(c) for c in panel_corners(p)),
                   detector_half_side=side / 2, scale=float(reflectance_scale(p)))


def panel_margin(stack: Stack) -> float:
    """How far [mm] the panel's hit point can move when a ray leaves the top of the stack rather than
    going straight on from the background: the refracted ray's sideways offset (at most the stack's
    thickness × the steepest panel direction's tanθ), × 3 for the slant onto the panel, + 1 mm."""
    if not stack.panels:
        return 0.0
    steepest = 0.0
    w = stack.background_half_width if math.isfinite(stack.background_half_width) else 0.0
    for p in stack.panels:
        for su in (-1, 1):
            for sv in (-1, 1):
                corner = [p.center[j] + su * p.half_u * p.axis_u[j] + sv * p.half_v * p.axis_v[j] for j in range(3)]
                for bx in (-w, w):
                    for by in (-w, w):
                        rise = corner[2] - stack.background_z
                        run = math.hypot(corner[0] - bx, corner[1] - by)
                        steepest = max(steepest, run / rise if rise > 0 else math.inf)
    thickness = stack.plane_z[0] - stack.plane_z[-1]
    return 3 * thickness * min(steepest, 20.0) + 1.0


def _panel_from_corners(corners) -> Panel:
    corners = np.asarray(corners, dtype=float)
    centre = corners.mean(axis=0)
    eu, ev = corners[1] - corners[0], corners[3] - corners[0]
    normal = np.cross(eu, ev)
    normal /= np.linalg.norm(normal)
    if normal @ centre > 0:          # face the sample (the origin)
        normal = -normal
    def floats(v):  # plain floats: numpy scalars must not meet Dr.Jit arrays
        return tuple(float(c) for c in v)

    return Panel(floats(centre), floats(normal), floats(eu / np.linalg.norm(eu)), floats(ev / np.linalg.norm(ev)),
                 float(np.linalg.norm(eu)) / 2, float(np.linalg.norm(ev)) / 2)



def side_entry(dr, half_width, z_bottom, z_top, px, py, pz, dx, dy, dz):
    """Where a ray in the air outside the stack's footprint (|x| or |y| > half_width), rising, meets
    one of the stack's side faces (between z_bottom and z_top): (meets an x face, meets a y face,
    distance). A convex box has one way in, so at most one is true; a ray from under the footprint
    meets the bottom face first, or passes outward. Dr.Jit arrays of one backend."""
    entries = []
    for pos, d, other_pos, other_d in ((px, dx, py, dy), (py, dy, px, dx)):
        face = dr.select(pos > 0, half_width, -half_width)
        t = (face - pos) / d
        zt, ot = pz + t * dz, other_pos + t * other_d
        entries.append(((dr.abs(pos) > half_width) & (pos * d < 0) & (zt >= z_bottom) & (zt <= z_top)
                        & (dr.abs(ot) <= half_width), t))
    (meets_x, t_x), (meets_y, t_y) = entries
    return meets_x, meets_y, dr.select(meets_x, t_x, t_y)


def sees_panel(dr, p: Panel, px, py, pz, dx, dy, dz):
    """Whether rays from (px, py, pz) in direction (dx, dy, dz) meet panel `p` from its front."""
    nx, ny, nz = p.normal
    denom = dx * nx + dy * ny + dz * nz
    t = ((p.center[0] - px) * nx + (p.center[1] - py) * ny + (p.center[2] - pz) * nz) / denom
    hx, hy, hz = px + t * dx - p.center[0], py + t * dy - p.center[1], pz + t * dz - p.center[2]
    u = hx * p.axis_u[0] + hy * p.axis_u[1] + hz * p.axis_u[2]
    v = hx * p.axis_v[0] + hy * p.axis_v[1] + hz * p.axis_v[2]
    return (denom < 0) & (t > 0) & (dr.abs(u) <= p.half_u) & (dr.abs(v) <= p.half_v)


def sees_light(dr, Bool, stack: Stack, px, py, pz, dx, dy, dz):
    """Radiance-1 light seen by a ray leaving upward: the sky (ideal) or the panels (device)."""
    if not stack.panels:
        return dz > 0
    seen = Bool(False)
    for p in stack.panels:
        seen |= sees_panel(dr, p, px, py, pz, dx, dy, dz)
    return seen
