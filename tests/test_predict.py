"""trimeter predict: a thick non-scattering slab against Beer-Lambert with Fresnel, mixtures (a material with
itself is the material; σa and σs add, g weighted by scattering), the checker's files, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

import trimeter.prediction as predict
from trimeter.cli import main
from trimeter.errors import InputError
from trimeter.forward.nonscattering import nonscattering_coefficients
from trimeter.results.medium import SpectralMaterial

pytest.importorskip("drjit")
NODES = np.array([450.0, 550.0, 650.0])


def test_thick_nonscattering_slab_is_beer_lambert_with_fresnel():
    sigma_t = np.array([0.05, 0.3, 1.0])                    # 3 mm: optical depths 0.15, 0.9, 3
    glass = SpectralMaterial(NODES, np.zeros(3), sigma_t, np.zeros(3))
    p = predict.predict_slab(glass, 3.0, rho_black=0.0, rho_white=0.8, paths=1 << 16, wavelengths_nm=NODES)
    A, B, C = nonscattering_coefficients("ideal", sigma_t, 3.0, 1.5)
    # Fresnel choices inside the slab are sampled: agreement within the tally's own standard error
    assert np.all(np.abs(p.on_black - A) <= 4 * p.stderr_black + 1e-4), (p.on_black, A)
    expected_white = A + B * 0.8 / (1 - C * 0.8)
    assert np.all(np.abs(p.on_white - expected_white) <= 4 * p.stderr_white + 2e-3), (p.on_white, expected_white)


def test_mixture_of_a_material_with_itself_is_the_material():
    m = SpectralMaterial(NODES, np.array([0.9, 0.5, 0.99]), np.array([2.0, 4.0, 1.0]), np.array([0.3, 0.6, 0.8]))
    mixed = predict.mixture([m, m], [0.3, 0.7])
    for k in ("alpha", "sigma_t", "g"):
        np.testing.assert_allclose(getattr(mixed, k), getattr(m, k), rtol=1e-12)
    a = predict.predict_slab(m, 1.0, paths=1 << 12, wavelengths_nm=NODES)
    b = predict.predict_slab(mixed, 1.0, paths=1 << 12, wavelengths_nm=NODES)
    np.testing.assert_allclose(b.on_white, a.on_white, rtol=1e-9)


def test_mixture_rule():
    a = SpectralMaterial.from_coefficients(NODES, [1.0, 0.0, 2.0], [1.0, 4.0, 0.0], [0.2, 0.5, 0.0])
    b = SpectralMaterial.from_coefficients(NODES, [0.0, 1.0, 0.0], [3.0, 0.0, 2.0], [0.6, 0.0, 0.9])
    m = SpectralMaterial.mixture([a, b], [1, 3])          # normalised: 1/4 and 3/4
    np.testing.assert_allclose(m.sigma_a, [0.25, 0.75, 0.5])
    np.testing.assert_allclose(m.sigma_s, [2.5, 1.0, 1.5])
    np.testing.assert_allclose(m.g, [(0.25 * 1 * 0.2 + 0.75 * 3 * 0.6) / 2.5, 0.5, 0.9])
    with pytest.raises(InputError, match="one volume fraction per material"):
        SpectralMaterial.mixture([a, b], [1])


def test_checker_writes_png_and_spectra(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(predict, "WAVELENGTHS_NM", NODES)
    rc = main(["predict", "--checker", "sample:cyan-ink", "sample:yellow-ink", "--thickness", "2", "--steps", "2",
               "--paths", "1024", "-o", str(tmp_path)])
    assert rc == 0
    assert (tmp_path / "checker.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = (tmp_path / "checker.csv").read_text().splitlines()
    assert lines[0].startswith("patch,background,srgb_hex,R_450nm") and len(lines) == 1 + 2 * 3
    assert "cyan-ink 0.5+yellow-ink 0.5" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["sample:cyan-ink", "--thickness", "0"], "--thickness"),
    (["sample:cyan-ink", "sample:milk", "--thickness", "1"], "need --fractions"),
    (["sample:cyan-ink", "--thickness", "1", "--fractions", "-1"], "--fractions"),
    (["sample:cyan-ink", "--thickness", "1", "--checker"], "-o DIR"),
    (["/no/such/result", "--thickness", "1"], "no such measurement"),
    (["sample:cyan-ink", "--thickness", "1", "--paths", "10"], "--paths"),
])
def test_bad_input_is_one_clear_error(argv, message, capsys):
    assert main(["predict", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error:") and message in err and "Traceback" not in err
