"""The printable parts, generated from hardware/geometry.toml with build123d (the `hardware` extra).

Every optical dimension comes from the [device] preset (the one the maps and the twin use), every
mechanical one from the [mechanics] table, so the printed instrument and the simulated one cannot
drift apart. Parts are modelled in the optics' frame (z = 0 the sample stack's back face, +z towards
the detector, panels along ±x, the slider travelling along y), placed as assembled, so a test can
measure distances between parts directly; the panel mounts, which sit on the frame far from the
axis, are modelled in their own frame (base on z = 0).

    parts = build_parts(load_mechanics())      # {name: Part}
    write_stls(parts, Path("build/hardware"))
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
GEOMETRY = ROOT / "hardware" / "geometry.toml"
# STL chord tolerance: well below FDM resolution, and below what the dimension tests allow.
STL_TOLERANCE_MM = 0.01
STL_ANGULAR_TOLERANCE = 0.1


class HardwareError(Exception):
    """A geometry or BOM file the generators cannot use; the message names the file and key."""


@dataclass(frozen=True)
class Mechanics:
    """The values the parts are built from: optical ones from [device], the rest from [mechanics]."""
    device: dict
    mech: dict

    def get(self, dotted: str) -> object:
        """A value by dotted path from the file's top level, e.g. 'device.collimated.beam_diameter_mm'."""
        node: object = {"device": self.device, "mechanics": self.mech}
        for key in dotted.split("."):
            if not isinstance(node, dict) or key not in node:
                table, _, item = dotted.rpartition(".")
                raise HardwareError(f"{GEOMETRY.name}: missing [{table}] {item}")
            node = node[key]
        return node

    def mm(self, dotted: str) -> float:
        value = self.get(dotted)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise HardwareError(f"{GEOMETRY.name}: {dotted} must be a non-negative number, got {value!r}")
        return float(value)

    def mm_list(self, dotted: str, count: int) -> list[float]:
        """`count` non-negative lengths, e.g. 'mechanics.panel_mount.base_mm' = [length, width]."""
        value = self.get(dotted)
        if not isinstance(value, list) or len(value) != count or not all(
                not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v >= 0
                for v in value):
            raise HardwareError(f"{GEOMETRY.name}: {dotted} must list {count} non-negative numbers, got {value!r}")
        return [float(v) for v in value]

    def slot_order(self) -> list[str]:
        """The slider's slots from the first one: black, white and open, each once."""
        order = self.get("mechanics.slider.slot_order")
        if not isinstance(order, list) or not all(isinstance(name, str) for name in order) \
                or sorted(order) != ["black", "open", "white"]:
            raise HardwareError(f"{GEOMETRY.name}: mechanics.slider.slot_order must name black, white and open once")
        return order

    # --- derived values, each stated once
    @property
    def slide_mm(self) -> float:
        return self.mm("device.cover_slide_thickness_mm") if self.device.get("cover_slides") else 0.0

    def stack_mm(self, ell: float) -> float:
        """The sample stack's thickness: slide | sample | slide."""
        return ell + 2 * self.slide_mm

    @property
    def thicknesses(self) -> list[float]:
        values = self.get("mechanics.holder.sample_thicknesses_mm")
        if not isinstance(values, list) or not values or not all(isinstance(v, (int, float)) and v > 0 for v in values):
            raise HardwareError(f"{GEOMETRY.name}: mechanics.holder.sample_thicknesses_mm must list positive numbers")
        return [float(v) for v in values]

    @property
    def reference_thickness(self) -> float:
        """The sample thickness the fixed parts (detector tube) are placed for: the first listed."""
        return self.thicknesses[0]

    @property
    def tray_mm(self) -> float:
        """Every tray is equally thick (so one frame takes them all): the thickest stack on the thinnest lip."""
        return max(self.stack_mm(ell) for ell in self.thicknesses) + self.mm("mechanics.holder.lip_thickness_mm")

    def front_z(self, ell: float) -> float:
        return self.stack_mm(ell)

    def slot_positions_mm(self) -> dict[str, float]:
        """Carriage travel from home at which each slot is on the axis (the firmware's slot_*_mm)."""
        order = self.slot_order()
        first, pitch = self.mm("mechanics.slider.first_slot_from_home_mm"), self.mm("mechanics.slider.slot_pitch_mm")
        return {name: first + k * pitch for k, name in enumerate(order)}

    @property
    def pocket_mm(self) -> float:
        """A background's pocket in the slider: the background plus the fit clearance each side."""
        return self.mm("device.background_width_mm") + 2 * self.mm("mechanics.fit_clearance_mm")

    @property
    def tube_near_z(self) -> float:
        """The detector tube's near end: far enough from the stack that the panels' light, at
        elevation_deg, reaches the whole detector spot past the tube."""
        r_out = self.mm("mechanics.detector_tube.bore_mm") / 2 + self.mm("mechanics.detector_tube.wall_mm")
        # the ray from the spot's far edge passes the tube's rim this far from the axis at height h:
        # h·tan(elevation) − spot/2, which must exceed the tube's radius plus the clearance
        reach = (r_out + self.mm("device.detector.spot_diameter_mm") / 2
                 + self.mm("mechanics.detector_tube.beam_clearance_mm"))
        elevation = math.radians(self.mm("device.panels.elevation_deg"))
        return self.front_z(self.reference_thickness) + reach / math.tan(elevation)

    @property
    def aperture_z(self) -> float:
        return self.front_z(self.reference_thickness) + self.mm("device.collimated.aperture_distance_mm")


def load_mechanics(path: Path = GEOMETRY) -> Mechanics:
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise HardwareError(f"cannot read {path}: {exc}") from None
    for table in ("device", "mechanics"):
        if not isinstance(doc.get(table), dict):
            raise HardwareError(f"{path.name}: missing table [{table}]")
    return Mechanics(doc["device"], doc["mechanics"])


@dataclass(frozen=True)
class Part:
    name: str
    description: str
    shape: object          # a build123d Part/Solid
    assembled: bool        # placed in the optics' frame (else in its own frame)


def _bd():
    try:
        import build123d
    except ImportError:
        raise HardwareError("build123d is not installed: pip install -e '.[hardware]' (tools/setup.sh does it)") \
            from None
    return build123d


def build_parts(m: Mechanics) -> dict[str, Part]:
    parts = [_slider(m), _holder_frame(m), *(_tray(m, ell) for ell in m.thicknesses), _panel_mount(m),
             _led_mount(m), _detector_tube(m)]
    return {p.name: p for p in parts}


def tray_name(ell: float) -> str:
    return f"sample_tray_l{ell:g}"


def _box(bd, x0, x1, y0, y1, z0, z1):
    """An axis-aligned box by its extents (so each dimension reads as what it is)."""
    return bd.Pos((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2) * bd.Box(x1 - x0, y1 - y0, z1 - z0)


def _cyl(bd, r, z0, z1, x=0.0, y=0.0):
    return bd.Pos(x, y, (z0 + z1) / 2) * bd.Cylinder(r, z1 - z0)


def _slider(m: Mechanics) -> Part:
    """The slider, posed with its first slot on the axis: the background pockets open towards +z, so a
    card's face is flush with the slider's face, background_gap_mm behind the stack."""
    bd = _bd()
    gap, wall = m.mm("device.background_gap_mm"), m.mm("mechanics.wall_mm")
    pitch, t = m.mm("mechanics.slider.slot_pitch_mm"), m.mm("mechanics.slider.thickness_mm")
    half, margin = m.pocket_mm / 2, m.mm("mechanics.slider.end_margin_mm")
    rail_x = m.mm("mechanics.slider.rail_offset_mm")
    hole_dx, hole_dy = m.mm_list("mechanics.slider.carriage_hole_spacing_mm", 2)
    order = m.slot_order()
    ys = [-k * pitch for k in range(len(order))]          # the slider moves +y to bring the next slot in
    face = -gap
    x_end = rail_x + hole_dx / 2 + 2 * wall
    body = _box(bd, -half - wall, x_end, ys[-1] - half - margin, half + margin, face - t, face)
    for name, y in zip(order, ys, strict=True):
        if name == "open":
            body -= _cyl(bd, m.mm("mechanics.slider.open_window_diameter_mm") / 2, face - t - 1, face + 1, y=y)
            continue
        depth = m.mm(f"mechanics.slider.{name}_{'card' if name == 'black' else 'block'}_thickness_mm")
        if depth >= t:
            raise HardwareError(f"{GEOMETRY.name}: the {name} background ({depth} mm) does not fit the slider ({t} mm)")
        body -= _box(bd, -half, half, y - half, y + half, face - depth, face + 1)
    y_mid = ys[-1] / 2
    for sx in (-1, 1):
        for sy in (-1, 1):
            body -= _cyl(bd, m.mm("mechanics.screw_hole_mm") / 2, face - t - 1, face + 1,
                         x=rail_x + sx * hole_dx / 2, y=y_mid + sy * hole_dy / 2)
    return Part("slider", "slider: black and white background pockets and the open window", body, True)


def _holder_frame(m: Mechanics) -> Part:
    """The fixed frame: a channel the trays slide into along +x, its face flush with the stack's back
    face (z = 0); the window under the sample leaves the panels' light free."""
    bd = _bd()
    clear, base = m.mm("mechanics.fit_clearance_mm"), m.mm("mechanics.wall_mm")
    length, width = m.mm("mechanics.holder.frame_length_mm"), m.mm("mechanics.holder.frame_width_mm")
    tray_w = m.mm("mechanics.holder.tray_width_mm")
    depth = m.tray_mm + base
    body = _box(bd, -length / 2, length / 2, -width / 2, width / 2, 0, depth)
    stop_x = -m.mm("device.sample_width_mm") / 2 - m.mm("mechanics.holder.lip_width_mm") - 2 * base
    body -= _box(bd, stop_x - clear, length / 2 + 1, -tray_w / 2 - clear, tray_w / 2 + clear, -1, m.tray_mm)
    # 45° clearance from the sample's rim through the whole frame
    window = m.mm("device.sample_width_mm") / 2 + depth / math.tan(math.radians(m.mm("device.panels.elevation_deg")))
    body -= _box(bd, -window, window, -window, window, -1, depth + 1)
    for sx in (-1, 1):
        for sy in (-1, 1):
            body -= _cyl(bd, m.mm("mechanics.mount_hole_mm") / 2, -1, depth + 1,
                         x=sx * (length / 2 - 8), y=sy * (width / 2 - 8))
    return Part("holder_frame", "sample holder frame: the channel the trays slide into", body, True)


def _tray(m: Mechanics, ell: float) -> Part:
    """A tray for one sample thickness: a pocket for the stack, from the back, on a lip of the front."""
    bd = _bd()
    clear = m.mm("mechanics.fit_clearance_mm")
    side, lip = m.mm("device.sample_width_mm"), m.mm("mechanics.holder.lip_width_mm")
    width, length = m.mm("mechanics.holder.tray_width_mm"), m.mm("mechanics.holder.tray_length_mm")
    x0 = -side / 2 - lip - 2 * m.mm("mechanics.wall_mm")
    body = _box(bd, x0, x0 + length, -width / 2, width / 2, 0, m.tray_mm)
    body -= _box(bd, -side / 2 - clear, side / 2 + clear, -side / 2 - clear, side / 2 + clear, -1, m.stack_mm(ell))
    body -= _box(bd, -side / 2 + lip, side / 2 - lip, -side / 2 + lip, side / 2 - lip, -1, m.tray_mm + 1)
    body -= _cyl(bd, 8.0, -1, m.tray_mm + 1, x=x0 + length - 14)           # finger hole of the handle
    return Part(tray_name(ell), f"sample tray for a {ell:g} mm sample between cover slides", body, True)


def _panel_mount(m: Mechanics) -> Part:
    """A wedge holding an LED panel's back plate at the panels' elevation from the sample plane."""
    bd = _bd()
    length, width = m.mm_list("mechanics.panel_mount.base_mm", 2)
    t = m.mm("mechanics.panel_mount.thickness_mm")
    elev = math.radians(m.mm("device.panels.elevation_deg"))
    if not 5 <= math.degrees(elev) <= 80:
        raise HardwareError(f"{GEOMETRY.name}: a printed wedge needs device.panels.elevation_deg in 5..80")
    height = length * math.tan(elev)
    with bd.BuildPart() as wedge:
        with bd.BuildSketch(bd.Plane.XZ):
            bd.Polygon((0, 0), (length, 0), (0, height), align=None)
        bd.extrude(amount=width / 2, both=True)
    body = wedge.part
    # M5 through the base at the foot, two M3 into the inclined face for the panel's back plate
    foot_x = length - t - 4
    body -= _cyl(bd, m.mm("mechanics.mount_hole_mm") / 2, -1, (length - foot_x) * math.tan(elev) + 1, x=foot_x)
    for f in (0.35, 0.65):
        point = (length * (1 - f), 0.0, height * f)
        hole = bd.Cylinder(m.mm("mechanics.screw_hole_mm") / 2, 30)
        body -= bd.Location(point, (0, math.degrees(elev), 0)) * hole     # along the face's normal
    return Part("panel_mount", "LED panel mount: a wedge at the panels' elevation", body, False)


def _led_mount(m: Mechanics) -> Part:
    """The collimated LED behind the slider: the LED star, then two pinholes of the beam's diameter."""
    bd = _bd()
    beam_r = m.mm("device.collimated.beam_diameter_mm") / 2
    length = m.mm("mechanics.led_mount.collimator_length_mm")
    body_r = m.mm("mechanics.led_mount.body_diameter_mm") / 2
    star_r = m.mm("mechanics.led_mount.led_star_diameter_mm") / 2 + m.mm("mechanics.fit_clearance_mm")
    wall = m.mm("mechanics.wall_mm")
    front = -m.mm("device.background_gap_mm") - m.mm("mechanics.slider.thickness_mm") - wall  # clear of the slider
    plate = 1.5
    pinholes = (front - plate, front - plate - length)
    back = pinholes[1] - plate - 6.0
    body = _cyl(bd, body_r, back, front)
    body += _cyl(bd, m.mm("mechanics.led_mount.flange_diameter_mm") / 2, back, back + 4)
    body -= _cyl(bd, 3.0, pinholes[1], pinholes[0])                         # the collimator's bore
    body -= _cyl(bd, beam_r, pinholes[0] - 1, front + 1)                     # exit pinhole
    body -= _cyl(bd, beam_r, pinholes[1] - plate - 1, pinholes[1] + 1)       # entrance pinhole
    body -= _cyl(bd, star_r, back - 1, pinholes[1] - plate)                  # LED star pocket
    for k in range(3):
        a = math.radians(90 + 120 * k)
        r = (m.mm("mechanics.led_mount.flange_diameter_mm") / 2 + body_r) / 2
        body -= _cyl(bd, m.mm("mechanics.screw_hole_mm") / 2, back - 1, back + 5, x=r * math.cos(a), y=r * math.sin(a))
    return Part("led_mount", "collimated LED mount: two pinholes of the beam's diameter", body, True)


def _detector_tube(m: Mechanics) -> Part:
    """The detector tube on the axis: its aperture (aperture_diameter_mm) at aperture_distance_mm from
    the stack's front face, a pocket for the sensor board behind it, a flange to mount it by."""
    bd = _bd()
    bore_r = m.mm("mechanics.detector_tube.bore_mm") / 2
    r_out = bore_r + m.mm("mechanics.detector_tube.wall_mm")
    plate = m.mm("mechanics.detector_tube.aperture_plate_mm")
    px, py, pz = m.mm_list("mechanics.detector_tube.sensor_pocket_mm", 3)
    flange_r = m.mm("mechanics.detector_tube.flange_diameter_mm") / 2
    if math.hypot(px, py) / 2 + 1 > flange_r:
        raise HardwareError(f"{GEOMETRY.name}: the sensor pocket does not fit the detector tube's flange")
    near, z_ap = m.tube_near_z, m.aperture_z
    far = z_ap + plate + pz
    body = _cyl(bd, r_out, near, z_ap) + _cyl(bd, flange_r, z_ap - 4, far)
    body -= _cyl(bd, bore_r, near - 1, z_ap)
    body -= _cyl(bd, m.mm("device.collimated.aperture_diameter_mm") / 2, z_ap - 1, z_ap + plate + 1)
    body -= _box(bd, -px / 2, px / 2, -py / 2, py / 2, z_ap + plate, far + 1)
    for k in range(3):
        a = math.radians(120 * k + 30)
        r = flange_r - 4
        body -= _cyl(bd, m.mm("mechanics.screw_hole_mm") / 2, z_ap - 5, far + 1, x=r * math.cos(a), y=r * math.sin(a))
    return Part("detector_tube", "detector tube: the aperture and the sensor pocket", body, True)


def write_stls(parts: dict[str, Part], out_dir: Path) -> list[Path]:
    bd = _bd()
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for part in parts.values():
        path = out_dir / f"{part.name}.stl"
        if not bd.export_stl(part.shape, str(path), tolerance=STL_TOLERANCE_MM,
                             angular_tolerance=STL_ANGULAR_TOLERANCE):
            raise HardwareError(f"build123d could not write {path}")
        paths.append(path)
    return paths
