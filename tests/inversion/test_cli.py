"""`trimeter fit` end to end: CSV in, CSV/JSON out, values checked against the truth; bad files are
one clear error line and exit code 2."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from trimeter.cli import main

from inversion_support import DATA, forward, well_conditioned


def _write(path, rows, header):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


@pytest.fixture
def truth(ideal_map):
    rng = np.random.default_rng(11)
    a, s, g = well_conditioned(ideal_map, 40, rng)
    wl = np.linspace(400, 700, 40)
    rho_b, rho_w = np.linspace(0.02, 0.06, 40), np.linspace(0.97, 0.9, 40)
    return wl, a, s, g, rho_b, rho_w


def test_fit_csv_round_trip(ideal_map, truth, tmp_path, capsys):
    wl, a, s, g, rho_b, rho_w = truth
    I_b, I_w, I_c = forward(ideal_map, a, s, g, rho_b, rho_w)
    rows = list(zip(wl, I_b, I_w, I_c, rho_b, rho_w, strict=True))
    rows[3] = (wl[3], "nan", I_w[3], I_c[3], rho_b[3], rho_w[3])  # a missing value: flagged, nothing lost
    inp = _write(tmp_path / "meas.csv", rows[::-1], ["wavelength_nm", "I_b", "I_w", "I_c", "rho_b", "rho_w"])
    out = tmp_path / "params.csv"
    assert main(["fit", "--map", str(ideal_map.path), "--input", str(inp), "-o", str(out)]) == 0
    with open(out) as f:
        got = list(csv.DictReader(f))
    assert list(got[0]) == ["wavelength_nm", "alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "flags",
                            "sigma_t_beer", "thickness_mm"]
    assert {r["thickness_mm"] for r in got} == {"0.5"}  # the thickness the fit used, stated
    assert len(got) == 40
    col = lambda k: np.array([float(r[k]) for r in got])  # noqa: E731
    np.testing.assert_allclose(col("wavelength_nm"), wl, rtol=1e-6)  # sorted by wavelength
    ok = np.arange(40) != 3
    assert np.percentile(np.abs(col("alpha") - a)[ok], 95) < 3e-3
    np.testing.assert_allclose(col("sigma_t")[ok], s[ok], rtol=1e-4)
    assert np.isnan(col("alpha")[3]) and int(got[3]["flags"]) & 1
    assert capsys.readouterr().err.startswith("note: 1 of 40 bins are NaN, their input unusable (NaN, negative or "
                                              "above 1")


def test_fit_says_what_to_do_about_underdetermined_bins(ideal_map, tmp_path, capsys):
    """Optically thick, dark samples determine only a combination of α and g: the fit flags them and
    says, on stderr (stdout may be the CSV) and in the JSON, that a second thickness is the remedy."""
    a, s, g = np.array([0.2, 0.3, 0.9, 0.6]), np.array([12.0, 12.0, 2.0, 1.0]), np.array([0.5, 0.6, 0.3, 0.2])
    I_b, I_w, I_c = forward(ideal_map, a, s, g, 0.02, 0.99)
    inp = _write(tmp_path / "thick.csv", zip([500, 510, 520, 530], I_b, I_w, I_c, [0.02] * 4, [0.99] * 4, strict=True),
                 ["wavelength_nm", "I_b", "I_w", "I_c", "rho_b", "rho_w"])
    assert main(["fit", "--map", str(ideal_map.path), "--input", str(inp), "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    assert doc["flag_names"] == ["UNDERDETERMINED", "UNDERDETERMINED", "NONE", "NONE"]
    assert len(doc["advice"]) == 1 and doc["advice"][0].startswith("2 of 4 bins are UNDERDETERMINED")
    assert "second thickness" in doc["advice"][0]
    assert out.err == f"note: {doc['advice'][0]}\nthickness: 0.5 mm (not declared: the map's; map ideal-l0.5)\n"
    assert doc["thickness_mm"] == 0.5 and doc["thickness_declared"] is False


def test_fit_json_and_two_thicknesses(ideal_map, thick_map, truth, tmp_path, capsys):
    wl, a, s, g, rho_b, rho_w = truth
    rows = []
    for amap in (ideal_map, thick_map):
        I_b, I_w, I_c = forward(amap, a, s, g, 0.02, 0.99)
        rows += [(w, x, y, z, amap.thickness_mm) for w, x, y, z in zip(wl, I_b, I_w, I_c, strict=True)]
    inp = _write(tmp_path / "two.csv", rows, ["wavelength_nm", "I_b", "I_w", "I_c", "thickness_mm"])
    rc = main(["fit", "--map", str(ideal_map.path), "--map", str(thick_map.path), "--input", str(inp),
               "--method", "paper", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["method"] == "paper" and [m["thickness_mm"] for m in doc["maps"]] == [0.5, 1.0]
    alpha = np.array([np.nan if v is None else v for v in doc["columns"]["alpha"]])
    assert np.nanmedian(np.abs(alpha - a)) < 0.05
    assert len(doc["flag_names"]) == 40
    assert doc["thickness_mm"] == [0.5, 1.0]


def test_a_declared_thickness_other_than_the_maps_is_an_error(ideal_map, thick_map, truth, tmp_path, capsys):
    """0.5 mm data through a 1 mm map would give σt exactly −50 %: with the thickness declared it is refused;
    the matching map is accepted and says the thickness was declared."""
    wl, a, s, g, rho_b, rho_w = truth
    I_b, I_w, I_c = forward(ideal_map, a, s, g, 0.02, 0.99)
    inp = _write(tmp_path / "m.csv", zip(wl, I_b, I_w, I_c, strict=True), ["wavelength_nm", "I_b", "I_w", "I_c"])
    assert main(["fit", "--map", str(thick_map.path), "--input", str(inp), "--thickness", "0.5"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: --thickness 0.5: map ") and "is for ℓ = 1 mm" in err and "×0.5" in err
    assert main(["fit", "--map", str(ideal_map.path), "--input", str(inp), "--thickness", "0.5", "--thickness",
                 "1"]) == 2
    assert "give one per --map" in capsys.readouterr().err
    assert main(["fit", "--map", str(ideal_map.path), "--input", str(inp), "--thickness", "0.5"]) == 0
    assert "thickness: 0.5 mm (declared with --thickness; map ideal-l0.5)" in capsys.readouterr().err


@pytest.mark.parametrize("content, message", [
    ("wavelength_nm,I_b,I_w\n500,0.1,0.5\n", "missing column(s) I_c"),
    ("wavelength_nm,I_b,I_w,I_c\n500,0.1,abc,0.3\n", "line 2, column I_w: 'abc' is not a number"),
    ("wavelength_nm,I_b,I_w,I_c\n", "no data rows"),
    ("wavelength_nm,I_b,I_w,I_c\n,0.1,0.5,0.3\n", "wavelength_nm"),
    ("wavelength_nm,I_b,I_w,I_c,thickness_mm\n500,0.1,0.5,0.3,2.0\n", "thickness_mm"),
])
def test_bad_input_files_are_one_clear_error(ideal_map, tmp_path, capsys, content, message):
    inp = tmp_path / "bad.csv"
    inp.write_text(content)
    assert main(["fit", "--map", str(ideal_map.path), "--input", str(inp)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error:") and message in err and err.count("\n") == 1


def test_unknown_map_and_missing_file(tmp_path, capsys):
    assert main(["fit", "--map", "no-such-map", "--input", str(tmp_path / "x.csv")]) == 2
    assert "no-such-map" in capsys.readouterr().err
    assert main(["fit", "--map", str(DATA / "ideal-l0.5.tmap"), "--input", str(tmp_path / "x.csv")]) == 2
    assert "cannot read" in capsys.readouterr().err
