"""`trimeter bench gpu-check`: its skip, its output format, its verdict and its CUDA half's plumbing.

Dr.Jit cannot record a CUDA kernel without the driver (its CUDA arrays need jit_init(CUDA)), so on a
machine without a GPU the CUDA half is exercised up to the tracer call: the tracer is asked for the
"cuda" backend and (here) runs LLVM in its place.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from trimeter.bench import gpu_check
from trimeter.cli import main
from trimeter.paths import MAPS_DIR

IDEAL = str(MAPS_DIR / "recipes" / "ideal-n1.5-l0.5.toml")
TINY = ["--paths", "8192", "--columns", "2", "--recipes", IDEAL, "--tests", "none"]
HEADER = re.compile(r"^gpu-check v1 \| (cuda|llvm) vs llvm \| 8192 paths per column \| trimeter \S+ \| "
                    r"drjit \S+ \| .+$")
COLUMN = re.compile(r"^column \| ideal-n1\.5-l0\.5 \| j \d+ \| k \d+ \| sigma_t \S+ \| g \S+ \| (cuda|llvm) (\S+) s \| "
                    r"llvm (\S+) s \| speed-up \S+ \| max \|z\| (\S+)$")
AGREEMENT = re.compile(r"^agreement \| (cuda|llvm) vs llvm \| count 160 \| mean z \S+ \| p95 \|z\| \S+ \| "
                       r"max \|z\| \S+ \| (PASS|FAIL)$")


def test_without_a_cuda_device_it_says_skipped_and_why_and_exits_0(monkeypatch, capsys):
    import drjit as dr

    monkeypatch.setattr(dr, "has_backend", lambda backend: False)
    assert main(["bench", "gpu-check"]) == 0
    out = capsys.readouterr().out
    assert out == "SKIPPED: gpu-check needs a CUDA device: Dr.Jit finds no CUDA driver and device on this machine\n"


def test_llvm_against_llvm_runs_the_whole_check_in_its_stable_format(capsys):
    """The checked half on LLVM with other seeds: two independent traces, which agree within their errors."""
    assert main(["bench", "gpu-check", "--against", "llvm", *TINY]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert HEADER.match(lines[0]) and "llvm vs llvm" in lines[0]
    columns = [COLUMN.match(line) for line in lines[1:3]]
    assert all(columns), lines
    for m in columns:
        assert float(m.group(2)) > 0 and float(m.group(3)) > 0 and 0 < float(m.group(4)) < 6
    m = AGREEMENT.match(lines[3])
    assert m and m.group(2) == "PASS", lines[3]
    assert lines[4:] == ["inversion tests | NOT RUN (--tests none)", "RESULT | PASS"]


def test_the_cuda_half_asks_the_tracer_for_cuda(monkeypatch, capsys):
    from trimeter.forward import transport

    asked = []
    real = transport.trace_column

    def stand_in(*args, backend, **kwargs):
        asked.append(backend)
        return real(*args, backend="llvm", **kwargs)

    monkeypatch.setattr(gpu_check, "missing_backend", lambda backend: None)
    monkeypatch.setattr(gpu_check, "gpu_name", lambda: "stand-in")
    monkeypatch.setattr(transport, "trace_column", stand_in)
    assert main(["bench", "gpu-check", *TINY]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert HEADER.match(lines[0]) and lines[0].startswith("gpu-check v1 | cuda vs llvm")
    assert lines[0].endswith("| stand-in")
    assert all(COLUMN.match(line).group(1) == "cuda" for line in lines[1:3])
    assert set(asked) == {"cuda", "llvm"} and asked.count("cuda") == asked.count("llvm")
    # the same seeds on (here) the same backend: the same bits
    assert AGREEMENT.match(lines[3]) and "max |z| 0.000 | PASS" in lines[3]


def _column(shift: float = 0.0):
    alpha = np.linspace(0.0, 0.99, 40)
    return SimpleNamespace(A=0.1 * alpha + shift, B=0.5 * alpha, C=0.3 * alpha, std_b=np.full(40, 1e-3),
                           std_w=np.full(40, 1e-3))


def test_a_backend_several_std_errors_off_fails_the_agreement():
    recipe = SimpleNamespace(reference_rho_b=0.02, reference_rho_w=0.9)
    same = gpu_check.agreement(gpu_check.column_z(recipe, _column(), _column()))
    assert same["ok"] and same["max_abs"] == 0.0
    off = gpu_check.column_z(recipe, _column(shift=5e-3), _column())
    np.testing.assert_allclose(off, 5e-3 / np.sqrt(2e-6))
    assert not gpu_check.agreement(off)["ok"]


def test_failing_or_absent_inversion_tests_fail_the_check(tmp_path, capsys):
    (tmp_path / "test_fails.py").write_text("def test_fails():\n    assert False\n")
    assert gpu_check.run_inversion_tests(str(tmp_path)) is False
    assert "| FAIL (exit 1) |" in capsys.readouterr().out
    assert gpu_check.run_inversion_tests(str(tmp_path / "absent")) is False
    assert "NOT RUN" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "message"), [(["--paths", "10"], "--paths must be"),
                                               (["--columns", "0"], "--columns must be"),
                                               (["--recipes", "/nonexistent.toml"], "cannot read")])
def test_bad_options_are_clear_errors_before_any_work(argv, message, capsys):
    assert main(["bench", "gpu-check", *argv]) == 2
    assert message in capsys.readouterr().err


def test_spread_columns_run_from_the_grid_s_first_column_to_its_last():
    recipe = SimpleNamespace(shape=(40, 24, 10))
    assert gpu_check.spread_columns(recipe, 3) == [(0, 0), (12, 4), (23, 9)]
    assert gpu_check.spread_columns(recipe, 1) == [(12, 4)]
