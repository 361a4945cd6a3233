"""`trimeter fit` streams: read, fitted and written in chunks, with the same output bit for bit as one fit of
every row (each method, the instrument's table fit, std columns, missing cells); a large input must come in
wavelength order; FIFOs, devices and oversized inputs are refused before a row is read."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from trimeter.cli import fit_stream, main
from trimeter.maps import AppearanceMap
from trimeter.paths import MAPS_DIR

NAME = "device-n1.5-l0.4"
ROWS = 3001  # not a multiple of any vector width: the tails differ between the two runs


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """A sorted input of ROWS bins rendered from the shipped map, with std columns and a few missing cells."""
    amap = AppearanceMap.load(MAPS_DIR / f"{NAME}.tmap")
    rng = np.random.default_rng(5)
    alpha, sigma_t, g = rng.uniform(0.5, 0.99, ROWS), rng.uniform(1.0, 30.0, ROWS), rng.uniform(0.0, 0.8, ROWS)
    rho_b, rho_w = amap.reference_rhos
    I_b, I_w, _ = amap.query(alpha, sigma_t, g, rho_b, rho_w)
    I_c = amap.collimated_measured(alpha, sigma_t, g)
    wl = np.sort(rng.uniform(400, 700, ROWS))
    lines = ["wavelength_nm,I_b,I_w,I_c,I_b_std,I_w_std,I_c_std,thickness_std_mm"]
    for i in range(ROWS):
        cells = [f"{wl[i]:.17g}", f"{I_b[i]:.17g}", f"{I_w[i]:.17g}", f"{I_c[i]:.17g}", f"{0.002 * I_b[i]:.17g}",
                 f"{0.002 * I_w[i]:.17g}", f"{0.003 * I_c[i]:.17g}", "0.01"]
        if i % 401 == 7:
            cells[2] = ""        # a missing value: that bin flagged, the rest unaffected
        lines.append(",".join(cells))
    path = tmp_path_factory.mktemp("stream") / "meas.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def _fit(extra, inp, out, monkeypatch, streamed):
    if streamed:
        monkeypatch.setattr(fit_stream, "WHOLE_INPUT_BYTES", 0)   # streamed, in order, as a large input is
        monkeypatch.setattr(fit_stream, "CHUNK_ROWS", 256)
    else:
        monkeypatch.setattr(fit_stream, "CHUNK_ROWS", 1 << 20)  # one chunk: the unchunked fit
    assert main(["fit", *extra, "--input", str(inp), "-o", str(out)]) == 0
    monkeypatch.undo()
    return out.read_bytes()


@pytest.mark.parametrize("extra", [["--map", NAME], ["--map", NAME, "--method", "mlp"],
                                   ["--map", NAME, "--polish", "0"], ["--table", str(MAPS_DIR / f"{NAME}.tlut")],
                                   ["--table", str(MAPS_DIR / f"{NAME}.tlut"), "--refine"]],
                         ids=["lut", "mlp", "raw-guess", "table", "table-refined"])
def test_chunked_output_is_the_unchunked_one_bit_for_bit(measured, tmp_path, monkeypatch, capsys, extra):
    whole = _fit(extra, measured, tmp_path / "whole.csv", monkeypatch, streamed=False)
    whole_err = capsys.readouterr().err
    chunked = _fit(extra, measured, tmp_path / "chunked.csv", monkeypatch, streamed=True)
    assert whole.count(b"\n") == ROWS + 1 and b",nan," in whole   # every row, the missing cells flagged
    assert chunked == whole
    assert capsys.readouterr().err == whole_err.replace("whole.csv", "chunked.csv")  # the same advice counts


def test_paper_method_chunks_alike(measured, tmp_path, monkeypatch):
    head = tmp_path / "head.csv"
    head.write_text("".join(measured.read_text().splitlines(keepends=True)[:301]))
    extra = ["--map", NAME, "--method", "paper"]
    assert _fit(extra, head, tmp_path / "a.csv", monkeypatch, False) == \
        _fit(extra, head, tmp_path / "b.csv", monkeypatch, True)


def test_rows_in_any_order_are_sorted_when_read_whole(measured, tmp_path, monkeypatch):
    lines = measured.read_text().splitlines(keepends=True)
    shuffled = tmp_path / "shuffled.csv"
    shuffled.write_text(lines[0] + "".join(lines[1:][::-1]))
    assert _fit(["--map", NAME], shuffled, tmp_path / "a.csv", monkeypatch, False) == \
        _fit(["--map", NAME], measured, tmp_path / "b.csv", monkeypatch, False)


def test_a_streamed_input_out_of_order_is_refused_and_writes_nothing(measured, tmp_path, monkeypatch, capsys):
    lines = measured.read_text().splitlines(keepends=True)
    lines[2000], lines[2001] = lines[2001], lines[2000]
    swapped = tmp_path / "swapped.csv"
    swapped.write_text("".join(lines))
    monkeypatch.setattr(fit_stream, "WHOLE_INPUT_BYTES", 0)
    monkeypatch.setattr(fit_stream, "CHUNK_ROWS", 256)
    assert main(["fit", "--map", NAME, "--input", str(swapped), "-o", str(tmp_path / "out.csv")]) == 2
    assert "data row 2001 is out of wavelength order" in capsys.readouterr().err
    assert not (tmp_path / "out.csv").exists()


def test_a_streamed_thickness_std_must_be_one_value(measured, tmp_path, monkeypatch, capsys):
    lines = measured.read_text().splitlines(keepends=True)
    lines[2500] = lines[2500].rstrip("\n").rsplit(",", 1)[0] + ",0.02\n"
    changed = tmp_path / "changed.csv"
    changed.write_text("".join(lines))
    monkeypatch.setattr(fit_stream, "WHOLE_INPUT_BYTES", 0)
    assert main(["fit", "--map", NAME, "--input", str(changed), "-o", str(tmp_path / "out.csv")]) == 2
    assert "thickness_std_mm differs" in capsys.readouterr().err


def test_fifo_device_and_oversized_inputs_are_refused(measured, tmp_path, monkeypatch, capsys):
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    done = threading.Event()

    def fit_fifo():
        assert main(["fit", "--map", NAME, "--input", str(fifo)]) == 2
        done.set()

    worker = threading.Thread(target=fit_fifo, daemon=True)
    worker.start()
    worker.join(timeout=30)
    assert done.is_set(), "fit waited on a FIFO"
    assert "not a regular file" in capsys.readouterr().err
    assert main(["fit", "--map", NAME, "--input", "/dev/zero"]) == 2
    assert "not a regular file" in capsys.readouterr().err
    monkeypatch.setattr(fit_stream, "MAX_INPUT_BYTES", 1000)
    assert main(["fit", "--map", NAME, "--input", str(measured)]) == 2
    assert "more than the 1000 such a file may have" in capsys.readouterr().err


def test_whole_input_fits_are_bounded(measured, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(fit_stream, "WHOLE_FIT_BYTES", 1000)
    assert main(["fit", "--map", NAME, "--input", str(measured), "--json"]) == 2
    assert "reads its input whole, up to 1000 bytes" in capsys.readouterr().err


@pytest.fixture(scope="module")
def two_thicknesses(tmp_path_factory):
    """0.4 and 0.8 mm rows of the same materials, interleaved by wavelength (the 0.8 mm ones a hair longer, within
    the pairing's tolerance), with a thickness std per sample."""
    rng = np.random.default_rng(8)
    n = 1500
    alpha, sigma_t, g = rng.uniform(0.5, 0.99, n), rng.uniform(1.0, 20.0, n), rng.uniform(0.0, 0.8, n)
    wl = np.sort(rng.uniform(400, 700, n))
    lines = ["wavelength_nm,I_b,I_w,I_c,thickness_mm,thickness_std_mm"]
    rows = []
    for thickness, std, shift in ((0.4, 0.01, 0.0), (0.8, 0.02, 1e-4)):
        amap = AppearanceMap.load(MAPS_DIR / f"device-n1.5-l{thickness}.tmap")
        I_b, I_w, _ = amap.query(alpha, sigma_t, g, *amap.reference_rhos)
        I_c = amap.collimated_measured(alpha, sigma_t, g)
        rows += [(wl[i] + shift, f"{wl[i] + shift:.17g},{I_b[i]:.17g},{I_w[i]:.17g},{I_c[i]:.17g},{thickness},{std}")
                 for i in range(n)]
    lines += [text for _, text in sorted(rows, key=lambda r: r[0])]
    path = tmp_path_factory.mktemp("two") / "two.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("method", ["lut", "mlp"])
def test_two_thicknesses_stream_alike(two_thicknesses, tmp_path, monkeypatch, method):
    extra = ["--map", "device-n1.5-l0.4", "--map", "device-n1.5-l0.8", "--method", method]
    whole = _fit(extra, two_thicknesses, tmp_path / "whole.csv", monkeypatch, streamed=False)
    chunked = _fit(extra, two_thicknesses, tmp_path / "chunked.csv", monkeypatch, streamed=True)
    assert whole.count(b"\n") == 1501 and whole.splitlines()[1].endswith(b",0.4+0.8")
    assert chunked == whole


def test_two_thicknesses_must_pair_up(two_thicknesses, tmp_path, monkeypatch, capsys):
    lines = two_thicknesses.read_text().splitlines(keepends=True)
    extra = tmp_path / "extra.csv"
    extra.write_text("".join(lines) + "701,0.1,0.5,0.1,0.8,0.02\n")  # a 0.8 mm row without its 0.4 mm one
    monkeypatch.setattr(fit_stream, "WHOLE_INPUT_BYTES", 0)
    monkeypatch.setattr(fit_stream, "CHUNK_ROWS", 256)
    assert main(["fit", "--map", "device-n1.5-l0.4", "--map", "device-n1.5-l0.8", "--input", str(extra), "-o",
                 str(tmp_path / "out.csv")]) == 2
    assert not (tmp_path / "out.csv").exists()
    assert "thickness 0.8 mm has 1 more row(s) than another: the thicknesses must cover the same wavelengths" \
        in capsys.readouterr().err
