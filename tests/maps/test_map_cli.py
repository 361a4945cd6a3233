"""`trimeter map build | list | info | query`: outputs checked, bad input → one clear line, exit 2."""

import json

import numpy as np
import pytest

from trimeter.cli import main
from trimeter.formats.appearance import AppearanceMap, shipped_maps
from trimeter.formats.container import write_container
from trimeter.paths import MAPS_DIR

from tiny_toml import tiny_toml

TINY_TOML = tiny_toml("cli-tiny")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    (d / "r.toml").write_text(TINY_TOML)
    assert main(["map", "build", str(d / "r.toml"), "--out", str(d / "m.tmap"), "--quiet"]) == 0
    return d / "m.tmap"


def test_build_prints_figures_and_info_describes(built, capsys):
    assert main(["map", "info", str(built), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["grid"] == {"alpha": 5, "sigma_t": 2, "g": 2, "points": 20}
    assert info["recipe"]["geometry"] == "ideal" and info["provenance"]["mitsuba_version"]
    assert main(["map", "info", str(built)]) == 0
    text = capsys.readouterr().out
    assert "MC stderr" in text and "Fresnel     unpolarised" in text
    assert main(["map", "info", str(MAPS_DIR / "device-n1.5-l0.4.tmap")]) == 0  # the shipped device maps track it
    assert "Fresnel     per polarisation" in capsys.readouterr().out


def test_query_returns_the_interpolated_observables(built, capsys):
    assert main(["map", "query", str(built), "--alpha", "0.7", "--sigma-t", "1.3", "--g", "0.2",
                 "--rho-b", "0.02", "--rho-w", "0.9", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    expected = AppearanceMap.load(built).query(0.7, 1.3, 0.2, 0.02, 0.9)
    assert set(out) == {"I_b", "I_w", "I_c"}
    np.testing.assert_allclose([out["I_b"], out["I_w"], out["I_c"]], [float(v) for v in expected])
    assert out["I_b"] < out["I_w"]


@pytest.mark.parametrize("args, field", [
    (["--alpha", "1.5", "--sigma-t", "1", "--g", "0.2"], "alpha"),
    (["--alpha", "0.5", "--sigma-t", "100", "--g", "0.2"], "sigma_t"),
    (["--alpha", "0.5", "--sigma-t", "1", "--g", "1.0"], "g"),
    (["--alpha", "0.5", "--sigma-t", "nan", "--g", "0.2"], "sigma_t"),
])
def test_query_bad_values_name_the_field(built, capsys, args, field):
    assert main(["map", "query", str(built), *args, "--rho-b", "0.02", "--rho-w", "0.9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error:") and field in err and len(err.strip().splitlines()) == 1


def test_query_negative_background_is_refused(built, capsys):
    assert main(["map", "query", str(built), "--alpha", "0.5", "--sigma-t", "1", "--g", "0.2",
                 "--rho-b", "-0.1", "--rho-w", "0.9"]) == 2
    assert "rho_b" in capsys.readouterr().err


def test_info_on_files_that_are_not_appearance_maps(tmp_path, capsys):
    junk = tmp_path / "junk.tmap"
    junk.write_bytes(b"not a map" * 20)
    assert main(["map", "info", str(junk)]) == 2
    assert "not a trimeter data file" in capsys.readouterr().err
    table = tmp_path / "table.bin"
    write_container(table, "map-table", {}, {"x": np.zeros(4)})
    assert main(["map", "info", str(table)]) == 2
    assert "is not an appearance map" in capsys.readouterr().err
    assert main(["map", "info", "no-such-map"]) == 2
    assert "neither a file nor a shipped map" in capsys.readouterr().err


def test_build_with_an_impossible_recipe_names_the_field(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY_TOML.replace("n = 1.5", "n = 0.8"))
    assert main(["map", "build", str(bad), "--out", str(tmp_path / "x.tmap"), "--quiet"]) == 2
    assert "n must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "x.tmap").exists()


def test_list_names_the_shipped_maps(capsys):
    assert main(["map", "list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["name"] for r in rows] == [p.stem for p in shipped_maps()]
    assert all("error" not in r for r in rows)


def test_map_inscatter_traces_a_device_maps_table_and_refuses_an_ideal_map(tmp_path, capsys, monkeypatch):
    """`trimeter map inscatter`: the table lands next to the map, where loading the map finds it; a map
    without the device's collimated set-up, or too few photons, is one clear error. (A 4 × 3 × 3 table:
    the full one takes 90 s; tests/forward/test_inscatter.py checks the tracing itself.)"""
    import shutil

    from trimeter.forward.transport import inscatter_tracer as inscatter
    from trimeter.paths import MAPS_DIR

    build = inscatter.build_inscatter_table
    monkeypatch.setattr(inscatter, "build_inscatter_table", lambda *a, **kw: build(*a, **{**kw, "shape": (4, 3, 3)}))

    shutil.copy(MAPS_DIR / "device-n1.5-l0.8.tmap", tmp_path / "d.tmap")
    assert main(["map", "inscatter", str(tmp_path / "d.tmap"), "--photons", "1000"]) == 0
    table = AppearanceMap.load(tmp_path / "d.tmap").inscatter
    assert table is not None and table.provenance["photons"] == 1000 and table.L.max() > 0
    assert main(["map", "inscatter", str(tmp_path / "d.tmap"), "--photons", "10"]) == 2
    assert "--photons" in capsys.readouterr().err
    assert main(["map", "inscatter", str(MAPS_DIR / "ideal-n1.5-l0.5.tmap")]) == 2
    assert "collimated set-up" in capsys.readouterr().err
