"""trimeter.load: a results directory written by the writer reads back whole (round trip), and every kind of
damaged, foreign or unsafe directory is one clear InputError."""

import json
import os

import numpy as np
import pytest

import trimeter
from trimeter.errors import InputError
from trimeter.results import write_measurement
from trimeter.results.reader import Measurement, load, read_record
from trimeter.tables import MAX_RESULT_FILE_BYTES


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory, measurement):
    return write_measurement(tmp_path_factory.mktemp("results"), measurement, label="ink", figure=False)


def test_round_trip(result_dir, measurement):
    m = trimeter.load(result_dir)
    assert isinstance(m, trimeter.Measurement) and m.name == result_dir.name
    p = measurement.parameters
    np.testing.assert_array_equal(m.wavelength_nm, p.wavelengths_nm)
    for name in ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "sigma_t_beer"):
        np.testing.assert_array_equal(getattr(m, name), getattr(p, name))  # JSON keeps every bit
    np.testing.assert_array_equal(m.flags, p.flags)
    assert np.isnan(m.alpha[3]) and m.flag_names[3] != "NONE" and m.flag_names[0] == "NONE"
    assert m.advice and "1 of 31 bins" in m.advice[0]
    assert m.thicknesses_mm == [0.4] and m.thickness_mm == 0.4 and m.per_thickness == []
    assert m.sample == "test ink" and m.label is None and m.method == "lut" and m.maps == ["test-map"]
    assert m.provenance.sample_name == "test ink" and m.written_utc
    refl, expected = m.reflectances[0], measurement.captures[0].reflectances
    np.testing.assert_allclose(refl.I_c, expected.I_c, rtol=1e-7)
    np.testing.assert_array_equal(refl.flags, expected.flags)
    raw, expected_raw = m.raw[0], measurement.captures[0].raw
    np.testing.assert_allclose(raw.white.signals, expected_raw.white.signals, rtol=1e-7)
    np.testing.assert_array_equal(raw.white.integration_times_us, expected_raw.white.integration_times_us)
    np.testing.assert_allclose(m.calibration.diffuse, measurement.calibration.diffuse, rtol=1e-7)
    assert m.parameters_document() == json.loads((result_dir / "parameters.json").read_text())
    assert "31 bins" in repr(m)


def test_export_from_the_loaded_measurement(result_dir, tmp_path):
    provenance = load(result_dir).export(to="pbrt", out_dir=tmp_path / "p", step_nm=0)
    assert provenance["source"]["measurement"] == result_dir.name and (tmp_path / "p" / "medium.pbrt").is_file()


@pytest.fixture
def copy(result_dir, tmp_path):
    """A fresh copy of the results directory to damage."""
    out = tmp_path / result_dir.name
    out.mkdir()
    for f in result_dir.iterdir():
        if f.is_file():
            (out / f.name).write_bytes(f.read_bytes())
    return out


def test_missing_and_foreign_directories(tmp_path, copy):
    with pytest.raises(InputError, match="no such results directory"):
        load(tmp_path / "nope")
    with pytest.raises(InputError, match="not a directory"):
        load(copy / "parameters.csv")
    (tmp_path / "foreign").mkdir()
    with pytest.raises(InputError, match="not a trimeter results directory"):
        load(tmp_path / "foreign")


@pytest.mark.parametrize("name, content, message", [
    ("measurement.json", "{not json", "not JSON"),
    ("measurement.json", "[1, 2]", "does not hold an object"),
    ("measurement.json", '{"thicknesses_mm": []}', "thicknesses_mm must be a list of positive numbers"),
    ("measurement.json", b"\xff\xfe{}", "not a UTF-8 text file"),
    ("parameters.json", '{"combined": {"wavelength_nm": [1]}}', "an estimate lacks alpha"),
    ("parameters.json", '{"combined": {"wavelength_nm": [1], "alpha": [1, 2], "sigma_t": [1], "g": [0]}}',
     "differ in length"),
    ("parameters.json", "{}", "expected an object with 'combined'"),
])
def test_corrupt_files(copy, name, content, message):
    target = copy / name
    target.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(InputError, match=message):
        load(copy)


def test_missing_parameters_and_damaged_capture_files(copy):
    m = load(copy)
    (copy / "reflectances.csv").write_text("wavelength_nm,I_b\n1,2\n")
    with pytest.raises(InputError, match="missing column"):
        m.reflectances
    (copy / "raw_white.csv").write_text("wavelength_nm,rate_counts_per_s,signal_10us\n1,2,x\n")
    with pytest.raises(InputError, match="line 2, column signal_10us: 'x' is not a number"):
        load(copy).raw
    (copy / "parameters.json").unlink()
    with pytest.raises(InputError, match="parameters.json: missing"):
        load(copy)


def test_symlinks_and_non_regular_files_are_refused(copy, tmp_path):
    (tmp_path / "elsewhere.json").write_bytes((copy / "measurement.json").read_bytes())
    (copy / "measurement.json").unlink()
    (copy / "measurement.json").symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(InputError, match="symbolic link"):
        load(copy)
    (copy / "measurement.json").unlink()
    os.mkfifo(copy / "measurement.json")
    with pytest.raises(InputError, match="not a regular file"):
        load(copy)  # and does not wait for a writer


def test_oversized_file_is_refused(copy):
    with open(copy / "parameters.json", "r+b") as f:
        f.truncate(MAX_RESULT_FILE_BYTES + 1)  # sparse: no real disk used
    with pytest.raises(InputError, match="more than the"):
        load(copy)


def test_read_record_is_the_measurement_json(result_dir):
    assert read_record(result_dir) == json.loads((result_dir / "measurement.json").read_text())
    assert Measurement(result_dir).record == read_record(result_dir)
