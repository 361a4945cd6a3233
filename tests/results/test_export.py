"""trimeter export: each format parsed back gives the coefficients it was given (Mitsuba loads its medium
where installed), the RGB conversion agrees with colour-science's own computation and reference values,
provenance is written, and bad input is one clear error."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from trimeter.cli import main
from trimeter.errors import InputError
from trimeter.results.export import export, linear_srgb_coefficients, spectra_to_linear_srgb
from trimeter.results.reader import load_result
from trimeter.results.medium import SpectralMaterial

WL = np.arange(400.0, 701.0, 4.0)  # not the 5 nm default step: step 0 must keep these bins


def cyan() -> SpectralMaterial:
    sigma_s = 3.6 * (WL / 500) ** -0.8
    sigma_a = 0.01 + 2.4 * np.exp(-0.5 * ((WL - 630) / 55) ** 2)
    return SpectralMaterial.from_coefficients(WL, sigma_a, sigma_s, np.linspace(0.62, 0.56, len(WL)))


@pytest.fixture
def result_dir(tmp_path):
    m = cyan()
    d = tmp_path / "20260101T000000Z-cyan"
    d.mkdir()
    alpha = list(m.alpha)
    alpha[0] = None                      # an unusable bin: skipped, never exported as a number
    (d / "parameters.json").write_text(json.dumps({"combined": {
        "thickness_mm": None, "wavelength_nm": list(WL), "alpha": alpha, "sigma_t": list(m.sigma_t),
        "g": list(m.g)}, "per_thickness": []}))
    (d / "measurement.json").write_text(json.dumps({"sample": "cyan", "method": "lut",
                                                    "maps": ["device-n1.5-l0.4"], "thicknesses_mm": [0.4]}))
    return d


def test_mitsuba_round_trip_and_mitsuba_loads_it(result_dir, tmp_path):
    prov = export(load_result(result_dir), "mitsuba", tmp_path / "m", step_nm=0)
    m = cyan()
    xml = ET.parse(tmp_path / "m" / "medium.xml").getroot()
    spectra = {e.get("name"): e.get("value") for e in xml.iter("spectrum")}
    pairs = np.array([[float(x) for x in p.split(":")] for p in spectra["sigma_t"].split(",")])
    np.testing.assert_allclose(pairs[:, 0], WL[1:])
    np.testing.assert_allclose(pairs[:, 1], m.sigma_t[1:], rtol=1e-5)
    assert "_spectral" in (tmp_path / "m" / "medium.xml").read_text() and "spectral" in prov["spectral_variants"]
    assert prov["source"]["maps"] == ["device-n1.5-l0.4"] and prov["trimeter_version"]
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_spectral")
    params = mi.traverse(mi.load_dict(json.loads((tmp_path / "m" / "medium.json").read_text())))
    np.testing.assert_allclose(np.array(params["sigma_t.value.values"]), m.sigma_t[1:], rtol=1e-5)
    np.testing.assert_allclose(np.array(params["albedo.value.values"]), m.alpha[1:], rtol=1e-5)
    assert params["phase_function.g"] == pytest.approx(cyan().at(WL[1:]).g_mean(), abs=1e-5)


def read_spd(path):
    rows = [line.split() for line in path.read_text().splitlines() if line and not line.startswith("#")]
    return np.array(rows, dtype=float)


def test_pbrt_round_trip(result_dir, tmp_path):
    export(load_result(result_dir), "pbrt", tmp_path / "p", step_nm=0, scene_unit_mm=1000)
    m = cyan()
    a, s = read_spd(tmp_path / "p" / "sigma_a.spd"), read_spd(tmp_path / "p" / "sigma_s.spd")
    np.testing.assert_allclose(a[:, 0], WL[1:])
    np.testing.assert_allclose(a[:, 1], m.sigma_a[1:], rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(s[:, 1], m.sigma_s[1:], rtol=1e-5)
    text = (tmp_path / "p" / "medium.pbrt").read_text()
    assert 'MakeNamedMedium "trimeter_sample"' in text and '"string type" "homogeneous"' in text
    assert '"spectrum sigma_a" "sigma_a.spd"' in text and '"float scale" [ 1000 ]' in text
    json.loads((tmp_path / "p" / "provenance.json").read_text())


def test_resampling_averages_windows_and_keeps_flat_spectra():
    lam = np.arange(400.0, 500.0, 0.5)
    rng = np.random.default_rng(0)
    noisy = SpectralMaterial(lam, np.full(lam.size, 0.8), 2.0 + rng.normal(0, 0.2, lam.size), np.full(lam.size, 0.5))
    r = noisy.resampled(5.0)
    assert np.abs(r.sigma_t - 2.0).max() < 0.2  # ten bins per window: a third of the per-bin noise
    np.testing.assert_allclose(r.alpha, 0.8)
    np.testing.assert_allclose(r.g, 0.5)


def test_srgb_matches_colour_science():
    with np.printoptions():  # as they were after it: importing colour-science sets numpy's legacy printing
        colour = pytest.importorskip("colour")
    shape = colour.SpectralShape(360, 780, 1)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    checker = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    for illuminant in ("D65", "A"):
        light = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape)
        white = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"][illuminant]
        for name in ("dark skin", "blue", "yellow", "cyan", "white 9.5 (.05 D)"):
            sd = checker[name].copy().align(shape)
            reference = colour.XYZ_to_RGB(colour.sd_to_XYZ(sd, cmfs, light, method="Integration") / 100, "sRGB",
                                          illuminant=white, chromatic_adaptation_transform="CAT02")
            ours = spectra_to_linear_srgb(shape.wavelengths, sd.values, illuminant)
            np.testing.assert_allclose(ours, reference, atol=2e-4, err_msg=f"{name} under {illuminant}")
    # colour-science's reference chart values: the ColorChecker 1976 patches (xyY under illuminant C) against
    # ours from the Ohta spectra of the same patches under C: all 24 within 4 % + 0.01 (two measurements of one chart).
    chart = colour.CCS_COLOURCHECKERS["ColorChecker 1976"]
    for name, xyY in chart.data.items():
        expected = colour.XYZ_to_RGB(colour.xyY_to_XYZ(xyY), "sRGB", illuminant=chart.illuminant,
                                     chromatic_adaptation_transform="CAT02")
        ours = spectra_to_linear_srgb(shape.wavelengths, checker[name].copy().align(shape).values, "C")
        np.testing.assert_allclose(ours, expected, rtol=0.04, atol=0.01, err_msg=name)


def test_a_colour_export_leaves_numpy_s_printing_as_it_was():
    """colour-science sets numpy's 1.13 legacy printing on import (six digits in str() of a float32): in a fresh
    process, an export's colour conversion must not pass that on to what the process writes next."""
    code = ("import numpy as np; from trimeter.results.export import spectra_to_linear_srgb; "
            "spectra_to_linear_srgb([400.0, 700.0], [0.5, 0.5]); print(str(np.float32(1.15516505e-05)))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "1.15516505e-05"


def test_rgb_is_exact_for_flat_spectra_and_goes_through_transmittance():
    flat = SpectralMaterial.from_coefficients(WL, np.full(WL.size, 0.3), np.full(WL.size, 2.0), np.full(WL.size, 0.4))
    c = linear_srgb_coefficients(flat, 1.0)
    np.testing.assert_allclose(c["sigma_a"], 0.3, rtol=1e-6)
    np.testing.assert_allclose(c["sigma_s"], 2.0, rtol=1e-6)
    np.testing.assert_allclose(c["g"], 0.4, rtol=1e-6)
    # A narrow strong band: the transmitted colour, not the mean coefficient, is what is kept.
    band = SpectralMaterial.from_coefficients(WL, 20 * np.exp(-0.5 * ((WL - 550) / 8) ** 2), np.full(WL.size, 1.0),
                                              np.zeros(WL.size))
    c = linear_srgb_coefficients(band, 1.0)
    T = np.exp(-band.sigma_t * 1.0)
    target = spectra_to_linear_srgb(WL, T) / spectra_to_linear_srgb(WL, np.ones_like(T))
    np.testing.assert_allclose(np.exp(-c["sigma_t"]), target, rtol=1e-6)
    assert c["sigma_a"][1] < 20 * 0.5  # far below the band's peak: light passes around it
    assert all(math.isfinite(v) for v in c["sigma_s"])


def test_rgb_and_blender_round_trip(result_dir, tmp_path):
    prov = export(load_result(result_dir), "rgb", tmp_path / "r", reference_thickness_mm=0.4)
    c = linear_srgb_coefficients(load_result(result_dir).material, 0.4)
    doc = json.loads((tmp_path / "r" / "rgb.json").read_text())
    np.testing.assert_allclose(doc["sigma_a"], c["sigma_a"], rtol=1e-5)
    table = np.genfromtxt(tmp_path / "r" / "rgb.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    np.testing.assert_allclose(table["sigma_s_per_mm"], c["sigma_s"], rtol=1e-5)
    assert prov["reference_thickness_mm"] == 0.4 and prov["illuminant"] == "D65"
    export(load_result(result_dir), "blender", tmp_path / "b", reference_thickness_mm=0.4)
    doc = json.loads((tmp_path / "b" / "blender.json").read_text())
    np.testing.assert_allclose(doc["sigma_s_per_blender_unit"], 1000 * c["sigma_s"], rtol=1e-5)
    script = (tmp_path / "b" / "blender_volume.py").read_text()
    compile(script, "blender_volume.py", "exec")
    assert "ShaderNodeVolumeScatter" in script and str(doc["g"]) in script


def test_csv_parameters_file(tmp_path):
    m = cyan()
    path = tmp_path / "params.csv"
    rows = ["wavelength_nm,alpha,sigma_t,g,flags"] + [f"{w},{a},{s},{g},0" for w, a, s, g in
                                                      zip(WL, m.alpha, m.sigma_t, m.g, strict=True)]
    path.write_text("\n".join(rows) + "\n")
    assert main(["export", str(path), "--to", "pbrt", "--step-nm", "0"]) == 0
    np.testing.assert_allclose(read_spd(tmp_path / "params-pbrt" / "sigma_s.spd")[:, 1], m.sigma_s, rtol=1e-5)


@pytest.mark.parametrize("content, message", [
    ("wavelength_nm,alpha\n1,2\n3,4\n", "no sigma_t, g column"),
    ("wavelength_nm,alpha,sigma_t,g\n400,x,1,0\n500,0.5,1,0\n", "line 2, column alpha: 'x' is not a number"),
    ("wavelength_nm,alpha,sigma_t,g\n400,nan,1,0\n500,0.5,1,0\n", "fewer than two wavelengths"),
    ("wavelength_nm,alpha,sigma_t,g\n400,0.5,1,0\n500,0.5,1,1.5\n", "g at 500 nm is 1.5: outside"),
])
def test_bad_parameters_are_one_clear_error(tmp_path, capsys, content, message):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    assert main(["export", str(path), "--to", "rgb"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error:") and message in err and "Traceback" not in err


def test_bad_options_are_clear_errors(result_dir, capsys):
    assert main(["export", str(result_dir), "--to", "rgb", "--illuminant", "sunset"]) == 2
    assert "illuminant" in capsys.readouterr().err
    assert main(["export", str(result_dir), "--to", "rgb", "--reference-thickness", "-1"]) == 2
    assert main(["export", str(result_dir / "nope"), "--to", "rgb"]) == 2
    with pytest.raises(InputError):
        SpectralMaterial.mixture([cyan()], [-1.0])


@pytest.mark.parametrize("fmt", ["rgb", "blender"])
def test_a_material_opaque_at_the_reference_thickness_is_refused_not_made_an_absorber(tmp_path, capsys, fmt):
    path = tmp_path / "dense.csv"
    path.write_text("wavelength_nm,alpha,sigma_t,g\n400,0.99,1e300,0\n500,0.99,1e300,0\n600,0.99,1e300,0\n")
    assert main(["export", str(path), "--to", fmt, "-o", str(tmp_path / fmt)]) == 2
    err = capsys.readouterr().err
    assert "opaque in σt" in err and "Traceback" not in err
    assert not (tmp_path / fmt / f"{fmt}.json").exists()
    dense = SpectralMaterial.from_coefficients(WL, np.full(WL.size, 0.1), np.full(WL.size, 50.0), np.zeros(WL.size))
    with pytest.raises(InputError, match="at most 0.27"):   # −ln(1e-6)/50.1 mm
        linear_srgb_coefficients(dense, 1.0)
    assert linear_srgb_coefficients(dense, 0.2)["sigma_s"].min() > 40   # thin enough: its scattering kept


@pytest.mark.parametrize("step", ["1e-9", "0.01", "-1", "nan", "101"])
def test_a_resampling_step_too_fine_or_impossible_is_refused(result_dir, capsys, step):
    assert main(["export", str(result_dir), "--to", "mitsuba", "--step-nm", step, "-o", "/nonexistent/x"]) == 2
    err = capsys.readouterr().err
    assert "step" in err and "Traceback" not in err
