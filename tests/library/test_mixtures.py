"""The mixture check (paper Sec. 5.2): the twin's mixtures, ΔE2000 of predicted against measured mixtures
on the twin (≥ 8 mixtures of 3 inks, median ≤ 1), a check that notices a wrong prediction, and the same
check on results directories and library materials."""

from __future__ import annotations

import json

import numpy as np
import pytest

import trimeter
from library_support import WL, fit_result, write_member
from trimeter.cli import main
from trimeter.errors import InputError
from trimeter.library.mixtures import (MixtureObservation, default_twin_mixtures, mixture_label, on_twin,
                                       predict_square, write_outputs)
from trimeter.results.medium import SpectralMaterial
from trimeter.twin.optics import Optics, material_spectra


def test_the_twin_mixes_by_volume_fractions():
    lam = np.linspace(400, 700, 31)
    c, y = (SpectralMaterial(lam, **material_spectra(n, lam)) for n in ("cyan-ink", "yellow-ink"))
    mix = material_spectra("cyan-ink:0.25+yellow-ink:0.75", lam)
    sigma_s = 0.25 * c.sigma_s + 0.75 * y.sigma_s
    sigma_a = 0.25 * c.sigma_a + 0.75 * y.sigma_a
    assert np.allclose(mix["sigma_t"], sigma_s + sigma_a)
    assert np.allclose(mix["alpha"], sigma_s / (sigma_s + sigma_a))
    assert np.allclose(mix["g"], (0.25 * c.sigma_s * c.g + 0.75 * y.sigma_s * y.g) / sigma_s)


@pytest.mark.parametrize("name,message", [
    ("cyan-ink:0.5+yellow-ink:0.6", "summing to 1"),
    ("cyan-ink:0.5+teal-ink:0.5", "'teal-ink' is not a catalogue material"),
    ("cyan-ink:x+yellow-ink:0.5", "NAME:FRACTION"),
    ("cyan-ink:1.0+cyan-ink:0.0", "NAME:FRACTION"),
])
def test_bad_mixture_names(name, message):
    with pytest.raises(InputError, match=message):
        material_spectra(name, np.linspace(400, 700, 5))


def test_the_twin_traces_the_checks_mixtures_and_renders_others_with_the_map():
    optics = Optics(appearance_map=[trimeter.open_map("device-n1.5-l0.4").path])
    for fractions in default_twin_mixtures():
        assert optics.insert_sample(mixture_label(fractions), 0.4).physics == "traced"
    s = optics.insert_sample("cyan-ink:0.2+magenta-ink:0.8", 0.4)
    assert s.physics == "map" and np.all(np.isfinite(s.I_b)) and np.all(s.I_w > s.I_b)


def test_a_traced_mixture_is_stamped_with_its_components(tmp_path, monkeypatch):
    """The tool traces a mixture; a change of a component's recipe or of a fraction makes it stale."""
    pytest.importorskip("drjit")
    import importlib.util

    from trimeter.geometry import load_geometry
    from trimeter.paths import REPO_ROOT
    from trimeter.twin import observables
    from trimeter.twin.optics import catalogue_entry

    spec = importlib.util.spec_from_file_location("make_twin_observables",
                                                  REPO_ROOT / "tools" / "make_twin_observables.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    monkeypatch.setattr(tool, "DATA_DIR", tmp_path)
    name = "cyan-ink:0.5+yellow-ink:0.5"
    assert tool.main(["--setup", "ideal:0.3", "--material", name, "--paths", "4096", "--step-nm", "150"]) == 0
    setup = observables._load(tmp_path / "ideal-n1.5-l0.3.json")
    params, lam = load_geometry("ideal"), np.linspace(400, 900, 20)
    I_b, I_w, _, _ = setup.observables(name, catalogue_entry(name), params, lam, 0.03, 0.99)
    assert np.all(I_w > I_b)
    changed = catalogue_entry(name)
    changed["components"]["cyan-ink"]["scattering_at_500nm"] += 0.1
    with pytest.raises(InputError, match="stale"):
        setup.observables(name, changed, params, lam, 0.03, 0.99)
    assert setup.materials[name]["paths_per_node"] == 4096


def test_mixture_check_on_the_twin(tmp_path):
    """The issue's criterion: at least 8 mixtures of 3 inks, median ΔE2000 ≤ 1.0."""
    components, observed, info = on_twin()
    assert sorted(components) == ["cyan-ink", "magenta-ink", "yellow-ink"] and len(observed) >= 8
    assert all(o.source.endswith("rendered by traced") for o in observed)   # physics independent of the map
    squares = [predict_square(components, o) for o in observed]
    every = np.concatenate([s.delta_e for s in squares])
    assert np.median(every) <= 1.0
    summary = write_outputs(tmp_path, squares, info)
    assert (tmp_path / "checker.png").stat().st_size > 10_000
    assert len(json.loads((tmp_path / "mixtures.json").read_text())["mixtures"]) == len(observed)
    assert summary["median_delta_e2000"] == pytest.approx(np.median(every))


def test_the_check_notices_a_wrong_prediction():
    """Mixtures predicted with the wrong fractions (the labels swapped) are far off: the check can fail."""
    components, observed, _ = on_twin([[("cyan-ink", 0.25), ("yellow-ink", 0.75)]], noise_rel=0.0)
    right = predict_square(components, observed[0])
    o = observed[0]
    wrong = MixtureObservation("swapped", [("cyan-ink", 0.75), ("yellow-ink", 0.25)], o.wavelengths_nm, o.I_b,
                               o.I_w, o.rho_b, o.rho_w, o.forward, o.source)
    assert right.delta_e.max() < 0.5 and predict_square(components, wrong).delta_e.min() > 3.0


def test_default_mixtures():
    mixes = default_twin_mixtures()
    assert len(mixes) == 10 and all(abs(sum(f for _, f in m) - 1) < 1e-12 for m in mixes)


def test_taken_from_results_directories_and_the_library(tmp_path, monkeypatch, capsys):
    """Components as a library material and a results directory; the mixture as a results directory whose
    reflectances are the forward model's for the mixed truth: ΔE ≈ 0."""
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    amap = trimeter.open_map("device-n1.5-l0.4")
    truth = {n: SpectralMaterial(WL, **material_spectra(n, WL)) for n in ("cyan-ink", "yellow-ink")}
    dirs = {n: write_member(tmp_path / "r", fit_result(m.alpha, m.sigma_t, m.g)) for n, m in truth.items()}
    mixed = SpectralMaterial.mixture(list(truth.values()), [0.4, 0.6])
    rho_b, rho_w = np.full(len(WL), 0.03), np.full(len(WL), 0.99)
    I = amap.query(mixed.alpha, mixed.sigma_t, mixed.g, rho_b, rho_w)
    mix_dir = write_member(tmp_path / "r", fit_result(0.5, 1.0, 0.5), map_name=amap.name, sample=I)
    assert main(["library", "add", "cyan", dirs["cyan-ink"]]) == 0
    out = tmp_path / "check"
    assert main(["library", "mixtures", "--component", "c=library:cyan", "--component", f"y={dirs['yellow-ink']}",
                 "--mixture", f"c:0.4+y:0.6={mix_dir}", "-o", str(out)]) == 0
    summary = json.loads((out / "mixtures.json").read_text())
    assert summary["mixtures"][0]["delta_e2000_black"] < 0.05 and summary["median_delta_e2000"] < 0.05
    assert "median ΔE2000" in capsys.readouterr().out
    assert main(["library", "mixtures", "--component", "c=library:cyan", "--mixture",
                 f"c:0.4+z:0.6={mix_dir}", "-o", str(out)]) == 2
    assert "no component 'z'" in capsys.readouterr().err
    assert main(["library", "mixtures"]) == 2
