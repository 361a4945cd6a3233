"""The results directory: complete or absent (temp dir + rename), readable CSV/JSON, a figure, and a
Mitsuba medium that Mitsuba itself loads with the measured spectra."""

import json

import numpy as np
import pytest

from trimeter.domain.parameters import FitResult
from trimeter.results import Parameters, write_measurement
from trimeter.results.medium import medium_dict

def test_writes_a_complete_directory(tmp_path, measurement):
    out = write_measurement(tmp_path, measurement, label="ink")
    names = {p.name for p in out.iterdir()}
    assert {"measurement.json", "calibration.json", "calibration.csv", "raw_black.csv", "raw_white.csv",
            "raw_collimated.csv", "reflectances.csv", "parameters.csv", "parameters.json", "figure.png",
            "medium.xml", "medium.json"} <= names
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".partial")]
    table = np.genfromtxt(out / "parameters.csv", delimiter=",", names=True)
    np.testing.assert_allclose(table["sigma_t"], np.linspace(1, 5, 31), rtol=1e-7)
    assert np.isnan(table["alpha"][3]) and table["flags"][3] == 1
    js = json.loads((out / "parameters.json").read_text())
    assert js["combined"]["alpha"][3] is None and js["combined"]["g"][0] == 0.4
    refl = np.genfromtxt(out / "reflectances.csv", delimiter=",", names=True)
    np.testing.assert_allclose(refl["I_c"], 0.1, rtol=1e-9)
    assert (out / "figure.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((out / "measurement.json").read_text())["sample"] == "test ink"


def test_the_declared_thickness_travels_with_the_capture_to_a_later_fit(tmp_path, measurement, capsys):
    """`trimeter fit --input <results>/reflectances.csv` checks its map against the thickness the sample was
    declared with when captured: a map of another thickness would scale σt by their ratio."""
    from trimeter.cli import main

    out = write_measurement(tmp_path, measurement)
    refl = np.genfromtxt(out / "reflectances.csv", delimiter=",", names=True)
    np.testing.assert_array_equal(refl["thickness_mm"], 0.4)
    assert main(["fit", "--map", "device-n1.5-l0.8", "--input", str(out / "reflectances.csv")]) == 2
    assert "thickness_mm has rows not matching the map's thickness 0.8 mm" in capsys.readouterr().err
    assert main(["fit", "--map", "device-n1.5-l0.4", "--input", str(out / "reflectances.csv"),
                 "-o", str(tmp_path / "p.csv")]) == 0


def test_writing_the_figure_leaves_the_process_s_plotting_backend_alone(tmp_path, measurement):
    """A notebook that measures in-process keeps its inline plots: the figure is drawn without pyplot."""
    import matplotlib

    before = matplotlib.get_backend()
    matplotlib.use("svg")  # any backend other than the Agg the figure is written with
    try:
        write_measurement(tmp_path, measurement)
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)


def test_failure_while_writing_leaves_nothing_that_looks_complete(tmp_path, measurement, monkeypatch):
    import trimeter.results.figure as figure

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(figure, "plot_parameters", boom)
    with pytest.raises(RuntimeError):
        write_measurement(tmp_path, measurement)
    assert list(tmp_path.iterdir()) == []


def test_medium_loads_in_mitsuba_with_the_measured_spectra(measurement):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_spectral")
    params = mi.traverse(mi.load_dict(medium_dict(measurement.parameters)))
    p = measurement.parameters
    valid = np.isfinite(p.alpha)
    wl = np.array(params["sigma_t.value.wavelengths"])
    np.testing.assert_allclose(np.array(params["sigma_t.value.values"]),
                               np.interp(wl, p.wavelengths_nm, p.sigma_t), rtol=1e-5)
    np.testing.assert_allclose(np.array(params["albedo.value.values"]),
                               np.interp(wl, p.wavelengths_nm[valid], p.alpha[valid]), rtol=1e-5)
    assert params["phase_function.g"] == pytest.approx(0.4, abs=1e-6)


def test_parameters_refuse_a_fit_over_other_bins():
    result = FitResult(*(np.zeros(3) for _ in range(7)), sigma_t_beer=np.zeros(3), method="lut")
    with pytest.raises(ValueError, match="3 fitted bins for 31 wavelengths"):
        Parameters.from_fit(np.linspace(400, 700, 31), result)
