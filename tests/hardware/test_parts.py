"""The printable parts: generated once per session from hardware/geometry.toml, written as STL, read
back, and measured on the meshes: every one watertight, and the dimensions the optics assume (the
aperture, the beam's pinholes, distances along the axis, the backgrounds' pockets, the slot pitch and
the panels' elevation) equal to geometry.toml's, and the slot positions to the firmware's defaults."""

import math
import tomllib

import numpy as np
import pytest

from conftest import ROOT, hardware_parts

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("build123d")

TOL = 0.02   # mm: the STL's chord tolerance is 0.01
F32 = 1e-4   # mm: STL stores float32 coordinates


@pytest.fixture(scope="session")
def mech():
    return hardware_parts.load_mechanics()


@pytest.fixture(scope="session")
def meshes(mech, tmp_path_factory):
    parts = hardware_parts.build_parts(mech)
    paths = hardware_parts.write_stls(parts, tmp_path_factory.mktemp("stl"))
    return {p.stem: trimesh.load(p) for p in paths}


def hits(mesh, origin, direction) -> np.ndarray:
    """Sorted distances along a ray where it crosses the mesh's surface (Möller-Trumbore)."""
    o, d = np.asarray(origin, float), np.asarray(direction, float)
    tri = mesh.triangles
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
    s = o - tri[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    keep = ok & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > 0)
    return np.unique(np.round(t[keep], 6))   # an edge shared by two triangles counts once


def radius_at(mesh, z, direction=(1.0, 0.0)):
    """The hole's radius on the axis at height z: the first wall a ray from the axis meets."""
    return hits(mesh, (0, 0, z), (*direction, 0))[0]


def test_every_part_is_watertight_and_solid(meshes):
    assert set(meshes) >= {"slider", "holder_frame", "panel_mount", "led_mount", "detector_tube"}
    for name, mesh in meshes.items():
        assert mesh.is_watertight and mesh.is_winding_consistent, name
        assert mesh.volume > 0, name


def test_detector_aperture_diameter_and_distance(meshes, mech):
    tube = meshes["detector_tube"]
    z_front = mech.front_z(mech.reference_thickness)
    z_ap = z_front + mech.device["collimated"]["aperture_distance_mm"]
    plate = mech.mech["detector_tube"]["aperture_plate_mm"]
    for direction in ((1, 0), (0, 1), (math.sqrt(0.5), math.sqrt(0.5))):
        assert radius_at(tube, z_ap + plate / 2, direction) == pytest.approx(
            mech.device["collimated"]["aperture_diameter_mm"] / 2, abs=TOL)
    # along the axis, between the aperture's edge and the bore: the plate's near face is at z_ap
    r_mid = (mech.device["collimated"]["aperture_diameter_mm"] / 2 + mech.mech["detector_tube"]["bore_mm"] / 2) / 2
    walls = hits(tube, (r_mid, 0, z_front), (0, 0, 1))
    assert walls[0] + z_front == pytest.approx(z_ap, abs=F32)


def test_detector_tube_stays_out_of_the_panels_light(meshes, mech):
    """Rays from the panels (elevation_deg off the normal, azimuths along ±x) to every point of the
    detector spot pass the tube."""
    tube = meshes["detector_tube"]
    elev = math.radians(mech.device["panels"]["elevation_deg"])
    z_front = mech.front_z(mech.reference_thickness)
    r_spot = mech.device["detector"]["spot_diameter_mm"] / 2
    for x in np.linspace(-r_spot, r_spot, 5):
        for sign in (1, -1):
            assert len(hits(tube, (x, 0, z_front), (sign * math.sin(elev), 0, math.cos(elev)))) == 0


def test_collimator_pinholes_are_the_beam_diameter(meshes, mech):
    led = meshes["led_mount"]
    beam_r = mech.device["collimated"]["beam_diameter_mm"] / 2
    # both plates: along the axis the bore is the beam's radius only inside them
    z_top = led.bounds[1][2]
    radii = [radius_at(led, z) for z in np.linspace(z_top - 0.2, led.bounds[0][2] + 0.2, 400)]
    narrow = np.isclose(radii, beam_r, atol=TOL)
    runs = np.flatnonzero(np.diff(narrow.astype(int)) == 1).size + int(narrow[0])
    assert runs == 2, "two pinholes of the beam's diameter"
    # and the exit pinhole clears the slider at the open slot
    assert z_top < -mech.device["background_gap_mm"] - mech.mech["slider"]["thickness_mm"]


def test_slider_pockets_gap_and_pitch(meshes, mech):
    slider = meshes["slider"]
    gap = mech.device["background_gap_mm"]
    # the slider's face is background_gap_mm behind the stack's back face (z = 0)
    assert slider.bounds[1][2] == pytest.approx(-gap, abs=F32)
    # along y through the pockets, just inside the shallower (black) pocket's depth
    z = -gap - 0.5 * mech.mech["slider"]["black_card_thickness_mm"]
    start = slider.bounds[1][1] + 1
    walls = start - hits(slider, (0, start, z), (0, -1, 0))
    ends, inner = walls[[0, -1]], walls[1:-1].reshape(-1, 2)
    centres, widths = inner.mean(axis=1), -np.diff(inner, axis=1)[:, 0]
    pitch = mech.mech["slider"]["slot_pitch_mm"]
    np.testing.assert_allclose(-np.diff(centres), pitch, atol=TOL)
    pockets = [w for w, name in zip(widths, mech.mech["slider"]["slot_order"], strict=True) if name != "open"]
    np.testing.assert_allclose(pockets, mech.device["background_width_mm"] + 2 * mech.mech["fit_clearance_mm"],
                               atol=TOL)
    assert centres[0] == pytest.approx(0, abs=TOL), "posed with the first slot on the axis"
    assert len(ends) == 2
    # a background's depth: the card's face flush with the slider's face
    for name in ("black", "white"):
        y = centres[mech.mech["slider"]["slot_order"].index(name)]
        depth = hits(slider, (0, y, 1.0), (0, 0, -1))[0] - 1.0 - gap
        key = "black_card_thickness_mm" if name == "black" else "white_block_thickness_mm"
        assert depth == pytest.approx(mech.mech["slider"][key], abs=F32)


def test_firmware_default_slot_positions_match_the_slider(mech):
    with open(ROOT / "hardware" / "registers.toml", "rb") as fh:
        regs = {r["name"]: r for r in tomllib.load(fh)["holding_register"]}
    firmware = {name: regs[f"slot_{name}_mm"]["default"] for name in ("black", "white", "open")}
    assert firmware == pytest.approx(mech.slot_positions_mm())


def test_slot_pitch_leaves_room_for_the_backgrounds(mech):
    assert mech.mech["slider"]["slot_pitch_mm"] >= mech.pocket_mm + mech.mech["wall_mm"] / 2
    with open(ROOT / "hardware" / "registers.toml", "rb") as fh:
        regs = {r["name"]: r for r in tomllib.load(fh)["holding_register"]}
    for name, position in mech.slot_positions_mm().items():
        assert regs[f"slot_{name}_mm"]["min"] <= position <= regs[f"slot_{name}_mm"]["max"], name


def test_tray_holds_the_stack_flush_with_the_frame(meshes, mech):
    frame = meshes["holder_frame"]
    side = mech.device["sample_width_mm"]
    lip = mech.mech["holder"]["lip_width_mm"]
    clear = mech.mech["fit_clearance_mm"]
    for ell in mech.thicknesses:
        tray = meshes[hardware_parts.tray_name(ell)]
        assert tray.bounds[0][2] == pytest.approx(0) and tray.bounds[1][2] == pytest.approx(mech.tray_mm)
        # the pocket: the stack's depth from the back face, sample_width + clearance wide, then the lip
        x_in_pocket = side / 2 - lip / 2
        assert hits(tray, (x_in_pocket, 0, -1), (0, 0, 1))[0] - 1 == pytest.approx(mech.stack_mm(ell), abs=F32)
        walls = hits(tray, (0, 0, mech.stack_mm(ell) / 2), (1, 0, 0))
        assert walls[0] == pytest.approx(side / 2 + clear, abs=TOL)
        assert radius_at(tray, mech.stack_mm(ell) + 0.1) == pytest.approx(side / 2 - lip, abs=TOL)
    # the frame's channel is as deep as a tray: the stack's back face is flush with the frame's face
    y_in_channel = mech.mech["holder"]["tray_width_mm"] / 2 - 1
    x_beside_window = frame.bounds[1][0] - 12
    assert hits(frame, (x_beside_window, y_in_channel, -1), (0, 0, 1))[0] - 1 == pytest.approx(mech.tray_mm, abs=F32)


def test_panel_mount_face_is_at_the_panels_elevation(meshes, mech):
    mount = meshes["panel_mount"]
    normals, areas = mount.face_normals, mount.area_faces
    inclined = np.abs(normals[:, 0]) > 0.05
    area_by_angle = {}
    for n, a in zip(normals[inclined], areas[inclined], strict=True):
        angle = round(math.degrees(math.acos(np.clip(n[2], -1, 1))), 3)
        area_by_angle[angle] = area_by_angle.get(angle, 0) + a
    face_angle = max(area_by_angle, key=area_by_angle.get)
    assert face_angle == pytest.approx(mech.device["panels"]["elevation_deg"], abs=0.01)


def test_mechanics_never_enter_an_optical_preset():
    """The maps record load_geometry(preset): the mechanics table must not be part of it."""
    from trimeter.geometry import PRESETS, load_geometry

    for preset in PRESETS:
        assert "mechanics" not in load_geometry(preset)
        assert not any("mechanics" in str(k) for k in load_geometry(preset))


def test_a_bad_geometry_value_is_a_clear_error(tmp_path):
    text = (ROOT / "hardware" / "geometry.toml").read_text(encoding="utf-8")
    bad = tmp_path / "geometry.toml"
    bad.write_text(text.replace("slot_pitch_mm = 54.0", 'slot_pitch_mm = "wide"'), encoding="utf-8")
    with pytest.raises(hardware_parts.HardwareError, match="slot_pitch_mm"):
        hardware_parts.load_mechanics(bad).slot_positions_mm()
    bad.write_text("[device]\n", encoding="utf-8")
    with pytest.raises(hardware_parts.HardwareError, match=r"\[mechanics\]"):
        hardware_parts.load_mechanics(bad)


@pytest.mark.parametrize("old, new, named", [
    ("base_mm = [40.0, 20.0]", "base_mm = 40.0", "base_mm must list 2"),
    ("sensor_pocket_mm = [27.0, 20.0, 6.0]", "sensor_pocket_mm = [27.0, 20.0]", "sensor_pocket_mm must list 3"),
    ("carriage_hole_spacing_mm = [20.0, 20.0]", 'carriage_hole_spacing_mm = [20.0, "x"]', "carriage_hole_spacing"),
    ('slot_order = ["black", "white", "open"]', 'slot_order = ["black", 1, "open"]', "slot_order must name"),
])
def test_a_malformed_list_is_a_clear_error(tmp_path, old, new, named):
    """Pairs, triples and the slot order are checked before they are unpacked or sorted."""
    text = (ROOT / "hardware" / "geometry.toml").read_text(encoding="utf-8")
    assert old in text
    bad = tmp_path / "geometry.toml"
    bad.write_text(text.replace(old, new), encoding="utf-8")
    with pytest.raises(hardware_parts.HardwareError, match=named):
        hardware_parts.build_parts(hardware_parts.load_mechanics(bad))
