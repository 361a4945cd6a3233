"""The twin's physics: virtual samples traced by the maps' tracer (trimeter.twin.observables), close to but not
the map the host inverts, or for the ideal geometry computed by adding-doubling; stale data is refused; a set-up
without either says it fell back to the map, and the demo's "independent physics" line says what each source
can show."""

from __future__ import annotations

import dataclasses
import importlib.util
import json

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.geometry import load_geometry
from trimeter.formats.appearance import AppearanceMap
from trimeter.paths import REPO_ROOT
from trimeter.twin import observables
from trimeter.twin.optics import Optics, _catalogue, physics_line

DEVICE_MAP = REPO_ROOT / "maps" / "device-n1.5-l0.4.tmap"
IDEAL_MAP = REPO_ROOT / "maps" / "ideal-n1.5-l0.5.tmap"


@pytest.mark.skipif(not DEVICE_MAP.exists() or observables.setup_observables("device", 1.5, 0.4) is None,
                    reason="needs the shipped device map and its traced observables")
def test_traced_sample_agrees_with_the_map_but_is_not_it():
    amap = AppearanceMap.load(DEVICE_MAP)
    optics = Optics(amap)
    s = optics.insert_sample("magenta-ink", 0.4)
    assert s.physics == "traced" and optics.truth()["physics"] == "traced"
    I_b, I_w, I_c = amap.query(s.alpha, s.sigma_t, s.g, optics.rho_black, optics.rho_white)
    # the same forward model, traced independently: within the map's own error, never bit-identical
    assert np.nanmax(np.abs(s.I_w / I_w - 1)) < 0.02 and np.nanmax(np.abs(s.I_b / I_b - 1)) < 0.03
    assert np.nanmax(np.abs(s.I_w - I_w)) > 1e-5
    np.testing.assert_allclose(s.I_c, I_c, rtol=2e-3)  # both analytic Beer-Lambert × traced in-scattering


def test_unsetup_observables_falls_back_to_the_map_and_says_so(ideal_map):
    other = dataclasses.replace(ideal_map, recipe={**ideal_map.recipe, "thickness_mm": 0.37}, path=None)
    optics = Optics(other)
    s = optics.insert_sample("milk", 0.37)
    assert s.physics == "map"
    truth = optics.truth()
    assert truth["physics"] == "map" and other.name in truth["physics_source"]
    line = physics_line(truth["physics"], "milk", other.name)
    assert line.startswith("independent physics: none") and "NOT the map's own error" in line


@pytest.mark.skipif(observables.setup_observables("device", 1.5, 0.4) is None,
                    reason="needs the traced device observables")
def test_traced_truth_names_its_source_and_what_it_shares_with_the_maps():
    optics = Optics(AppearanceMap.load(DEVICE_MAP))
    optics.insert_sample("milk", 0.4)
    truth = optics.truth()
    assert truth["physics"] == "traced"
    assert truth["physics_source"].startswith("device-n1.5-l0.4.json (tool tools/make_twin_observables.py")
    line = physics_line("traced", "milk", "device-n1.5-l0.4")
    # honest: the same tracer and the same I(ρ) model as the maps, so not independent of them
    assert line.startswith("independent physics: partly") and "I(ρ) = A + Bρ/(1 − Cρ)" in line
    assert "NOT the tracer's or the I(ρ) model's own" in line
    with pytest.raises(InputError, match="physics must be one of traced, adding-doubling, map"):
        physics_line("mitsuba", "milk", "x")


@pytest.mark.skipif(not IDEAL_MAP.exists() or observables.setup_observables("ideal", 1.5, 0.5) is None,
                    reason="needs the shipped ideal map and its adding-doubling observables")
def test_the_shipped_ideal_maps_twin_is_adding_doubling_not_the_tracer():
    """The shipped ideal map was traced; its twin's samples are adding-doubling's (an integrator of their own),
    at every pixel what adding-doubling gives there (the spline between nodes included), near the map but never
    it, and the demo's line says the map's whole error shows."""
    pytest.importorskip("iadpython")
    from trimeter.forward.adding_doubling import ideal_abc
    from trimeter.model.response import background_response

    amap = AppearanceMap.load(IDEAL_MAP)
    optics = Optics(amap)
    s = optics.insert_sample("yellow-ink", 0.5)
    assert s.physics == "adding-doubling" and optics.truth()["physics"] == "adding-doubling"
    source = optics.truth()["physics_source"]
    assert source.startswith("ideal-n1.5-l0.5.json (tool tools/make_twin_observables.py, integrator adding-doubling")
    assert "quad_points 32" in source
    pixels = np.linspace(0, len(optics.wavelengths_nm) - 1, 7).astype(int)
    direct = ideal_abc(s.alpha[pixels], s.sigma_t[pixels], s.g[pixels], thickness_mm=0.5, n=1.5)
    for I, rho in ((s.I_b, optics.rho_black), (s.I_w, optics.rho_white)):
        np.testing.assert_allclose(I[pixels], background_response(*direct.T, rho[pixels]), atol=1e-4)
    I_b, I_w, _ = amap.query(s.alpha, s.sigma_t, s.g, optics.rho_black, optics.rho_white)
    assert np.nanmax(np.abs(s.I_w - I_w)) < 0.01 and np.nanmax(np.abs(s.I_b - I_b)) < 0.01
    assert np.nanmax(np.abs(s.I_w - I_w)) > 1e-5
    line = physics_line("adding-doubling", "yellow-ink", amap.name)
    assert line.startswith("independent physics: yes") and "whole of the map ideal-n1.5-l0.5's own error" in line


def _tool():
    spec = importlib.util.spec_from_file_location("make_twin_observables",
                                                  REPO_ROOT / "tools" / "make_twin_observables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_tool_output_loads_and_stale_data_is_refused(tmp_path, monkeypatch):
    pytest.importorskip("drjit")
    tool = _tool()
    monkeypatch.setattr(tool, "DATA_DIR", tmp_path)
    assert tool.main(["--setup", "ideal:0.3", "--material", "milk", "--paths", "4096", "--step-nm", "150",
                      "--range-nm", "340", "1000"]) == 0
    path = tmp_path / "ideal-n1.5-l0.3.json"
    setup = observables._load(path)
    lam = np.linspace(400, 900, 50)
    params = load_geometry("ideal")
    I_b, I_w, L, I_open = setup.observables("milk", _catalogue()["material"]["milk"], params, lam, 0.03, 0.99)
    assert np.all(I_w > I_b) and np.all(L == 0) and np.all((I_open > 0) & (I_open < I_b + 1e-12))
    assert setup.observables("cyan-ink", _catalogue()["material"]["cyan-ink"], params, lam, 0.03, 0.99) is None
    changed = {**_catalogue()["material"]["milk"], "g_at_500nm": 0.5}
    with pytest.raises(InputError, match="stale.*make_twin_observables"):
        setup.observables("milk", changed, params, lam, 0.03, 0.99)
    doc = json.loads(path.read_text())
    doc["materials"]["milk"]["A"] = doc["materials"]["milk"]["A"][:-1]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="A must be"):
        observables._load(bad)
    doc = json.loads(path.read_text())
    (bad := tmp_path / "bad-integrator.json").write_text(json.dumps({**doc, "integrator": "volpath"}))
    with pytest.raises(InputError, match="integrator must be one of tracer, adding-doubling"):
        observables._load(bad)


def test_tool_traces_with_the_polarisation_the_setups_recipe_has(tmp_path, monkeypatch):
    """By default a traced set-up follows its shipped map recipe (the device maps track polarisation, no
    recipe: unpolarised); the model is stamped in the file and its source, and a run with the other model
    keeps none of the first's entries."""
    pytest.importorskip("drjit")
    tool = _tool()
    assert tool.traced_polarisation("recipe", "device", 1.5, 0.4) is True
    assert tool.traced_polarisation("recipe", "ideal", 1.5, 0.4) is False
    assert tool.traced_polarisation("on", "ideal", 1.5, 0.4) is True
    monkeypatch.setattr(tool, "DATA_DIR", tmp_path)
    path = tmp_path / "ideal-n1.5-l0.3.json"
    args = ["--setup", "ideal:0.3", "--paths", "4096", "--step-nm", "150", "--range-nm", "340", "1000"]
    assert tool.main([*args, "--material", "milk"]) == 0
    unpolarised = observables._load(path)
    assert unpolarised.polarisation is False and "Fresnel unpolarised" in unpolarised.source()
    observables._load.cache_clear()
    assert tool.main([*args, "--material", "cyan-ink", "--polarisation", "on"]) == 0
    polarised = observables._load(path)
    assert polarised.polarisation is True and "Fresnel per polarisation" in polarised.source()
    assert list(polarised.materials) == ["cyan-ink"]
    observables._load.cache_clear()
    assert tool.main([*args, "--material", "milk", "--polarisation", "on"]) == 0
    same_seed = observables._load(path).materials["milk"]
    # the same paths, other odds at the faces: the coefficients move
    assert same_seed["A"] != unpolarised.materials["milk"]["A"]
    doc = json.loads(path.read_text())
    (bad := tmp_path / "bad-polarisation.json").write_text(json.dumps({**doc, "polarisation": "yes"}))
    with pytest.raises(InputError, match="polarisation must be true or false"):
        observables._load(bad)


def test_the_shipped_traced_observables_model_the_faces_as_their_set_ups_recipes_do():
    """A recipe that changes its Fresnel model leaves the twin's traced data of that set-up stale: this fails
    until tools/make_twin_observables.py has re-traced it (the device set-ups: polarised, as their maps)."""
    tool = _tool()
    traced = [s for s in map(_setup_of, observables.available_setups()) if s.integrator == "tracer"]
    assert {s.path.stem for s in traced} >= {"device-n1.5-l0.4", "device-n1.5-l0.8"}
    for s in traced:
        assert s.polarisation == tool.traced_polarisation("recipe", s.geometry, s.n, s.thickness_mm), s.path.name
    assert all(s.polarisation for s in traced if s.geometry == "device")


def _setup_of(stem: str) -> observables.SetupObservables:
    return observables._load(observables.DATA_DIR / f"{stem}.json")


def test_tool_computes_an_ideal_setup_by_adding_doubling(tmp_path, monkeypatch, capsys):
    """One integrator per file: a traced file re-made by adding-doubling keeps none of the traced entries; the
    integrator travels into the samples' physics; adding-doubling is refused for the device geometry."""
    pytest.importorskip("iadpython")
    tool = _tool()
    monkeypatch.setattr(tool, "DATA_DIR", tmp_path)
    path = tmp_path / "ideal-n1.5-l0.3.json"
    path.write_text(json.dumps({"materials": {"cyan-ink": {"traced": True}}, "integrator": "tracer"}))
    assert tool.main(["--setup", "ideal:0.3:adding-doubling", "--material", "milk", "--step-nm", "110"]) == 0
    assert "quadrature error black" in capsys.readouterr().out
    setup = observables._load(path)
    assert setup.integrator == "adding-doubling" and setup.physics == "adding-doubling"
    assert list(setup.materials) == ["milk"] and setup.provenance["step_nm"] == 110
    entry = setup.materials["milk"]
    assert entry["quad_points"] == 32 and entry["L"] == [0.0] * len(entry["wavelength_nm"])
    assert 0 < max(entry["quadrature_error_white"]) < 2e-3
    I_b, I_w, _, _ = setup.observables("milk", _catalogue()["material"]["milk"], load_geometry("ideal"),
                                       np.linspace(400, 900, 20), 0.03, 0.99)
    assert np.all((I_b > 0) & (I_w > I_b) & (I_w < 1))
    for bad, message in (("device:0.4:adding-doubling", "exact only for the ideal geometry"),
                         ("ideal:0.4:volpath", "integrator must be one of"), ("ideal:thin", "GEOMETRY:THICKNESS_MM")):
        with pytest.raises(InputError, match=message):
            tool.main(["--setup", bad, "--material", "milk"])
