"""`trimeter fit --bands WEIGHTS.csv --input CHANNELS.csv`: a multichannel sensor's readings fitted
band-aware from the command line (CSV and JSON out, one row per channel in input order, --grid rows
after them); every bad weights or channels file is one clear error line and exit code 2."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from trimeter.cli import main
from trimeter.maps.artifacts import load_artifacts
from trimeter.spectrometer.sensors import as7341_weights

MAP = "device-n1.5-l0.4"


def _write(path, header, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


@pytest.fixture(scope="module")
def sensor():
    """The AS7341 model's weights and the band readings of a smooth magenta-like spectrum (the map's
    forward model per wavelength, integrated over each band)."""
    weights = as7341_weights()
    lam = weights.wavelength_nm
    sigma_a = 0.01 + 2.1 * np.exp(-0.5 * ((lam - 545) / 40) ** 2)
    sigma_s = 3.3 * (lam / 500) ** -0.8
    alpha, sigma_t, g = sigma_s / (sigma_s + sigma_a), sigma_s + sigma_a, 0.6 - 0.02 * (lam - 500) / 100
    grid = load_artifacts(MAP).grid
    rho_b, rho_w = load_artifacts(MAP).reference_rhos
    I_b, I_w, I_c = grid.intensities(alpha, sigma_t, g, np.full(len(lam), rho_b), np.full(len(lam), rho_w))
    readings = np.stack([weights.diffuse @ I_b, weights.diffuse @ I_w, weights.collimated @ I_c])
    truth = [np.interp(weights.centre_nm, lam, v) for v in (alpha, sigma_t, g)]
    return weights, readings, truth


@pytest.fixture
def files(tmp_path, sensor):
    weights, readings, _ = sensor
    header = ["wavelength_nm", *(f"{c}_{k}" for c in weights.channels for k in ("diffuse", "collimated"))]
    rows = [[lam, *(v for i in range(len(weights.channels)) for v in (weights.diffuse[i, j], weights.collimated[i, j]))]
            for j, lam in enumerate(weights.wavelength_nm)]
    w = _write(tmp_path / "weights.csv", header, rows)
    order = [4, 0, 8, 1, 2, 3, 5, 6, 7]  # not in wavelength order: the output keeps the input's
    ch = _write(tmp_path / "channels.csv", ["channel", "I_b", "I_w", "I_c"],
                [[weights.channels[i], *readings[:, i]] for i in order])
    return w, ch, header, rows, order


def test_band_fit_from_files(files, sensor, tmp_path, capsys):
    w, ch, _, _, order = files
    weights, _, (alpha, sigma_t, g) = sensor
    out = tmp_path / "out.csv"
    argv = ["fit", "--map", MAP, "--bands", str(w), "--input", str(ch), "--grid", "500:600:50", "-o", str(out)]
    assert main(argv) == 0
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert [r["channel"] for r in rows[:9]] == [weights.channels[i] for i in order]
    assert [r["channel"] for r in rows[9:]] == ["", "", ""]
    assert [float(r["wavelength_nm"]) for r in rows[9:]] == [500.0, 550.0, 600.0]
    fitted = np.array([float(r["alpha"]) for r in rows[:9]])
    assert np.max(np.abs(fitted - alpha[order])) < 0.01
    s = np.array([float(r["sigma_t"]) for r in rows[:9]])
    assert np.max(np.abs(s / sigma_t[order] - 1)) < 0.02
    assert "band-aware fit of 9 channels" in capsys.readouterr().err


def test_built_in_weights_and_json(files, tmp_path, capsys):
    _, ch, _, _, _ = files
    assert main(["fit", "--map", MAP, "--bands", "as7341", "--input", str(ch), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["method"] == "bands" and len(doc["channels"]["alpha"]) == 9
    assert len(doc["channels"]["flag_names"]) == 9 and "grid" not in doc


def _error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("edit, message", [
    (lambda rows: rows[300].__setitem__(9, -0.5), "F5_diffuse has a negative weight"),
    (lambda rows: rows[300].__setitem__(10, "nan"), "F5_collimated has an empty or non-finite value"),
    (lambda rows: [r.__setitem__(3, 0.0) for r in rows], "F2_diffuse is zero everywhere"),
    (lambda rows: rows.__delitem__(slice(0, 100)), "F1_diffuse does not fall to zero at 450 nm"),
])
def test_bad_weights(files, tmp_path, capsys, edit, message):
    w, ch, header, rows, _ = files
    rows = [list(r) for r in rows]
    edit(rows)
    _write(w, header, rows)
    assert message in _error(capsys, ["fit", "--map", MAP, "--bands", str(w), "--input", str(ch)])


def test_channel_the_weights_lack(files, tmp_path, capsys):
    w, _, _, _, _ = files
    ch = _write(tmp_path / "c.csv", ["channel", "I_b", "I_w", "I_c"], [["F1", 0.1, 0.5, 0.3], ["F9", 0.1, 0.5, 0.3]])
    assert "F9 have no weights" in _error(capsys, ["fit", "--map", MAP, "--bands", str(w), "--input", str(ch)])


def test_one_channel_only(files, tmp_path, capsys):
    w, _, _, _, _ = files
    ch = _write(tmp_path / "c.csv", ["channel", "I_b", "I_w", "I_c"], [["F1", 0.1, 0.5, 0.3]])
    assert "one channel only" in _error(capsys, ["fit", "--map", MAP, "--bands", str(w), "--input", str(ch)])


@pytest.mark.parametrize("argv, message", [
    (["--grid", "500:400:5"], "--grid"),
    (["--method", "mlp"], "its own solver"),
])
def test_bad_options(files, capsys, argv, message):
    w, ch, _, _, _ = files
    assert message in _error(capsys, ["fit", "--map", MAP, "--bands", str(w), "--input", str(ch), *argv])


def test_grid_needs_bands(files, capsys):
    _, ch, _, _, _ = files
    assert "--grid: only with --bands" in _error(capsys, ["fit", "--map", MAP, "--input", str(ch), "--grid", "1:2:1"])


@pytest.mark.parametrize("header, rows, message", [
    (["name", "I_b", "I_w", "I_c"], [["F1", 0.1, 0.5, 0.3], ["F2", 0.1, 0.5, 0.3]], "missing column channel"),
    (["channel", "I_b", "I_w"], [["F1", 0.1, 0.5], ["F2", 0.1, 0.5]], "missing column(s) I_c"),
    (["channel", "I_b", "I_w", "I_c"], [["F1", 0.1, 0.5, 0.3], ["F1", 0.1, 0.5, 0.3]], "repeated: F1"),
    (["channel", "I_b", "I_w", "I_c"], [["F1", "dark", 0.5, 0.3], ["F2", 0.1, 0.5, 0.3]], "'dark' is not a number"),
])
def test_bad_channels_file(files, tmp_path, capsys, header, rows, message):
    w, _, _, _, _ = files
    ch = _write(tmp_path / "c.csv", header, rows)
    assert message in _error(capsys, ["fit", "--map", MAP, "--bands", str(w), "--input", str(ch)])
