"""`trimeter fit --table FILE`: a fit from a device table alone, in a directory holding nothing else and
with every map file out of reach: by default the instrument's own fit (native.TableFitter) with its stds from
the same table (trimeter.inversion.table_std);
`--refine` the lut fit on the table's refined model, with `--polish N` (0: the table's raw guess); bad
tables and option combinations are one clear error line and exit code 2."""

from __future__ import annotations

import csv
import shutil
import struct
import zlib

import numpy as np
import pytest

from trimeter.cli import main
from trimeter.formats.appearance import AppearanceMap
from trimeter.formats.device_table import DeviceTable
from trimeter.inversion.table_model import DeviceTableModel
from trimeter.paths import MAPS_DIR

NAME = "device-n1.5-l0.4"


@pytest.fixture(scope="module")
def measured_materials():
    """Rendered from the shipped map (its in-scattering included), materials inside its range."""
    amap = AppearanceMap.load(MAPS_DIR / f"{NAME}.tmap")
    rng = np.random.default_rng(3)
    n = 32
    alpha, sigma_t, g = rng.uniform(0.7, 0.98, n), rng.uniform(2.0, 20.0, n), rng.uniform(0.2, 0.7, n)
    rho_b, rho_w = amap.reference_rhos
    I_b, I_w, _ = amap.query(alpha, sigma_t, g, rho_b, rho_w)
    I_c = amap.collimated_measured(alpha, sigma_t, g)
    return np.linspace(400, 700, n), I_b, I_w, I_c, (alpha, sigma_t, g)


@pytest.fixture
def alone(tmp_path, monkeypatch, measured_materials):
    """A directory holding the table and the CSV only, as the working directory; map files out of reach."""
    from trimeter.formats import container

    work = tmp_path / "alone"
    work.mkdir()
    shutil.copy(MAPS_DIR / f"{NAME}.tlut", work / "t.tlut")
    wl, I_b, I_w, I_c, _ = measured_materials
    with open(work / "meas.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["wavelength_nm", "I_b", "I_w", "I_c"])
        writer.writerows(zip(wl, I_b, I_w, I_c, strict=True))
    monkeypatch.chdir(work)

    def no_map_file(*args, **kwargs):
        raise AssertionError("a map file was read")

    monkeypatch.setattr(AppearanceMap, "load", no_map_file)
    monkeypatch.setattr(container, "read_container", no_map_file)
    return work


def _read(path) -> dict:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def test_fit_from_the_table_alone(alone, measured_materials, capsys):
    from trimeter.inversion import native
    from trimeter.inversion.api import fit

    if not native.available():
        pytest.skip(native.status())
    assert main(["fit", "--table", "t.tlut", "--input", "meas.csv", "-o", "out.csv"]) == 0
    err = capsys.readouterr().err
    table = DeviceTable.load(alone / "t.tlut")
    assert f"table {NAME} (sha256 {table.sha256[:12]}…) with the instrument's fit" in err
    assert "thickness: 0.4 mm" in err
    got = _read(alone / "out.csv")
    alpha, sigma_t, g = measured_materials[4]
    assert np.all(got["thickness_mm"] == 0.4)
    assert np.median(np.abs(got["alpha"] - alpha)) < 0.01 and np.median(np.abs(got["g"] - g)) < 0.05
    assert np.median(np.abs(got["sigma_t"] / sigma_t - 1)) < 0.01
    # the instrument's fit on the file's bytes, to the digit printed, its stds from the same table
    from trimeter.inversion.table_std import TableStds

    _, I_b, I_w, I_c, _ = measured_materials
    want = native.TableFitter(table.to_bytes()).fit(I_b, I_w, I_c)
    for column, value in zip(("alpha", "sigma_t", "g"), want[:3], strict=True):
        np.testing.assert_allclose(got[column], value, rtol=1e-8)
    rhos = [np.full(len(I_b), r) for r in table.reference_rhos]
    stds = TableStds(table).result(want, I_b, I_w, I_c, *rhos)
    np.testing.assert_array_equal(got["flags"], stds.flags)
    for column in ("alpha_std", "sigma_t_std", "g_std"):
        assert np.isfinite(got[column]).all()
        np.testing.assert_allclose(got[column], getattr(stds, column), rtol=1e-8)
    # --refine: the lut fit on the table's refined model, stds included
    # about the stds of the lut fit on the same table
    assert main(["fit", "--table", "t.tlut", "--refine", "--input", "meas.csv", "-o", "refined.csv"]) == 0
    assert "refined at load" in capsys.readouterr().err
    refined = _read(alone / "refined.csv")
    lut = fit(DeviceTableModel(table), I_b, I_w, I_c, method="lut")
    np.testing.assert_allclose(refined["alpha"], lut.alpha, rtol=1e-8)
    assert np.isfinite(refined["alpha_std"]).all()
    assert 0.9 < np.median(got["alpha_std"] / refined["alpha_std"]) < 1.1
    assert 0.9 < np.median(got["g_std"] / refined["g_std"]) < 1.1
    # --polish 0: the table's raw guess, which the default polish then moves
    assert main(["fit", "--table", "t.tlut", "--refine", "--input", "meas.csv", "--polish", "0", "-o",
                 "raw.csv"]) == 0
    raw = _read(alone / "raw.csv")
    guess = fit(DeviceTableModel(table), I_b, I_w, I_c, method="lut", polish=0)
    np.testing.assert_allclose(raw["alpha"], guess.alpha, rtol=1e-8)
    assert np.max(np.abs(raw["alpha"] - refined["alpha"])) > 1e-4
    capsys.readouterr()
    assert main(["fit", "--table", "t.tlut", "--input", "meas.csv", "--json"]) == 0
    doc = __import__("json").loads(capsys.readouterr().out)
    assert doc["table"]["sha256"] == table.sha256 and doc["table"]["parent_map_sha256"] == table.parent_sha256
    assert "computed on the host from this table" in doc["table"]["stds"]
    np.testing.assert_allclose(doc["columns"]["alpha_std"], got["alpha_std"], rtol=1e-8)


def test_without_the_compiled_kernel_the_instruments_fit_is_a_clear_error(alone, monkeypatch, capsys):
    from trimeter.inversion import native

    monkeypatch.setattr(native, "_LIB", None)
    monkeypatch.setattr(native, "_STATUS", "not built (make native)")
    assert main(["fit", "--table", "t.tlut", "--input", "meas.csv"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: the table fit needs the compiled kernel: not built")
    assert "Traceback" not in err


@pytest.mark.parametrize("json_output", [False, True])
def test_std_columns_set_the_table_fits_stds(alone, capsys, json_output):
    """The readings' stds and the sample thickness's std, given as columns, are propagated (CSV, streamed, and
    JSON alike); the fitted values stay the instrument's fit's."""
    import json

    def run(name: str) -> dict:
        capsys.readouterr()
        argv = ["fit", "--table", "t.tlut", "--input", name]
        if json_output:
            assert main([*argv, "--json"]) == 0
            return {k: np.array([np.nan if v is None else v for v in vs], dtype=float)
                    for k, vs in json.loads(capsys.readouterr().out)["columns"].items()}
        assert main([*argv, "-o", "out.csv"]) == 0
        return _read(alone / "out.csv")

    plain = run("meas.csv")
    rows = (alone / "meas.csv").read_text().splitlines()
    (alone / "noisy.csv").write_text("\n".join([rows[0] + ",I_b_std,I_w_std,I_c_std,thickness_std_mm",
                                                *(r + ",0.02,0.02,0.001,0.02" for r in rows[1:])]) + "\n")
    noisy = run("noisy.csv")
    assert "not used" not in capsys.readouterr().err
    np.testing.assert_array_equal(noisy["alpha"], plain["alpha"])
    assert np.all(noisy["alpha_std"] > plain["alpha_std"]) and np.all(noisy["sigma_t_std"] > plain["sigma_t_std"])


def _damaged(data: bytes, offset: int, value: bytes, fix_crc: bool = True) -> bytes:
    out = bytearray(data)
    out[offset:offset + len(value)] = value
    if fix_crc:
        out[-4:] = struct.pack("<I", zlib.crc32(bytes(out[:-4])))
    return bytes(out)


@pytest.mark.parametrize("argv, message", [
    (["--map", NAME], "not allowed with argument"),
    (["--thickness", "0.8"], "--thickness 0.8: table device-n1.5-l0.4 is for ℓ = 0.4 mm"),
    (["--method", "paper"], "--method paper: a device table fits with method lut"),
    (["--polish", "-1"], "is not a number of Newton steps"),
    (["--polish", "many"], "is not a number of Newton steps"),
    (["--polish", "2"], "--polish: the instrument's fit has its own polish (add --refine"),
    (["--port", "/dev/null"], "--port: only with --on-device"),
])
def test_option_errors(alone, argv, message, capsys):
    try:
        code = main(["fit", "--table", "t.tlut", "--input", "meas.csv", *argv])
    except SystemExit as exc:  # argparse's own checks
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("damage, message", [
    (lambda d: _damaged(d, 8, struct.pack("<H", 1), fix_crc=False), "format_version: 1, this reader reads 2 "
                                                                     "(format 1 is retired"),
    (lambda d: _damaged(d, 2000, b"\xff\xff", fix_crc=False), "crc32: mismatch: the table is corrupt"),
    (lambda d: d[:5000], "total_size"),
    (lambda d: b"wavelength_nm,I_b\n" * 20, "magic: not a trimeter map table"),
])
def test_bad_table_files(alone, damage, message, capsys):
    (alone / "t.tlut").write_bytes(damage((alone / "t.tlut").read_bytes()))
    assert main(["fit", "--table", "t.tlut", "--input", "meas.csv"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: t.tlut: ") and message in err and "Traceback" not in err


def test_polish_with_a_map_and_on_device_without_a_port(alone, monkeypatch, capsys):
    monkeypatch.undo()  # the map is wanted here
    monkeypatch.chdir(alone)
    assert main(["fit", "--map", NAME, "--input", "meas.csv", "--polish", "0", "-o", "p0.csv"]) == 0
    assert main(["fit", "--map", NAME, "--input", "meas.csv", "-o", "p.csv"]) == 0
    assert np.max(np.abs(_read(alone / "p0.csv")["alpha"] - _read(alone / "p.csv")["alpha"])) > 1e-4
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(alone / "config"))
    capsys.readouterr()
    assert main(["fit", "--on-device", "--input", "meas.csv"]) == 2
    assert "port: no instrument port given" in capsys.readouterr().err
    assert main(["fit", "--on-device", "--port", "x", "--input", "meas.csv", "--polish", "2"]) == 2
    assert "--polish: the instrument fits with its own polish" in capsys.readouterr().err
    assert main(["fit", "--map", NAME, "--input", "meas.csv", "--refine"]) == 2
    assert "--refine: only with --table" in capsys.readouterr().err
