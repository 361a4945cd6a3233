"""The Python API at the package's top level: `trimeter.fit`, `load`, `Measurement`, `predict`, `open_map`,
each imported on first use; and `trimeter demo`'s default output outside the package and the repository."""

import subprocess
import sys

import numpy as np
import pytest

import trimeter
from trimeter.errors import InputError
from trimeter.paths import REPO_ROOT


def test_import_trimeter_stays_light():
    code = "import sys, trimeter; print(sorted(m for m in sys.modules if m.startswith('trimeter')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "['trimeter', 'trimeter.version']"   # the version: one line, no imports


def test_names_resolve_and_unknown_ones_do_not():
    from trimeter.inversion.artifacts import fit, open_map
    from trimeter.prediction import predict
    from trimeter.results.reader import Measurement, load

    assert (trimeter.fit, trimeter.open_map, trimeter.predict, trimeter.load, trimeter.Measurement) == \
        (fit, open_map, predict, load, Measurement)
    with pytest.raises(AttributeError):
        trimeter.no_such_thing  # noqa: B018
    # imported once: a resolved name is the module's own from then on (a fit in a loop does not import again)
    assert {"fit", "open_map", "predict", "load", "Measurement"} <= set(vars(trimeter))


def test_open_map_by_name_is_the_one_fit_uses():
    amap = trimeter.open_map("ideal-n1.5-l0.5")
    assert amap.name == "ideal-n1.5-l0.5" and amap.thickness_mm == 0.5
    assert trimeter.open_map("ideal-n1.5-l0.5") is amap  # the artifact cache: loaded once
    with pytest.raises(InputError, match="neither a file nor a shipped map"):
        trimeter.open_map("no-such-map")


def test_predict_takes_loaded_measurements_and_mixtures():
    from trimeter.prediction import mixture, predict_slab
    from trimeter.results.medium import SpectralMaterial

    lam = np.array([450.0, 550.0, 650.0])
    a = SpectralMaterial(lam, np.full(3, 0.9), np.full(3, 5.0), np.full(3, 0.3))
    b = SpectralMaterial(lam, np.full(3, 0.5), np.full(3, 2.0), np.full(3, 0.0))

    class Loaded:  # what trimeter.load returns, as far as predict looks at it
        def material(self):
            return b

    nodes = np.array([500.0, 600.0])
    got = trimeter.predict([a, Loaded()], 1.0, fractions=[0.5, 0.5], paths=1 << 11, wavelengths_nm=nodes)
    want = predict_slab(mixture([a, b], [0.5, 0.5]), 1.0, paths=1 << 11, wavelengths_nm=nodes)
    np.testing.assert_array_equal(got.on_white, want.on_white)
    with pytest.raises(InputError, match="not int"):
        trimeter.predict(3, 1.0)


def test_demo_writes_outside_the_package_and_the_repository(monkeypatch, tmp_path):
    from trimeter.cli.cmd_demo import demo_dir

    monkeypatch.delenv("TRIMETER_DATA_DIR", raising=False)
    default = demo_dir(None).resolve()
    assert REPO_ROOT not in default.parents and default.name == "demo"
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path))
    assert demo_dir(None) == tmp_path / "demo" and demo_dir("x") == type(tmp_path)("x")
