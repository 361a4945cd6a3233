"""The compiled kernel's boundary: declared once in invert.h, the Python side generated from it, and a
library that does not match (another header, older sources, missing) named loudly, never a silent
switch to the slower numpy kernel."""

import importlib.util
import warnings
from pathlib import Path

import pytest

from trimeter.inversion import native
from trimeter.inversion.flags import FitFlag
from trimeter.inversion.native import invert_h

# tools/ is run as scripts (python -m tools.gen_native), not installed: load the generator from its file
_spec = importlib.util.spec_from_file_location(
    "gen_native", Path(__file__).resolve().parents[2] / "tools" / "gen_native.py")
gen_native = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gen_native)

HEADER_TEXT = gen_native.header_text()  # invert.h with fit_core/table_fit.h in place of its include


def test_the_generated_boundary_is_current():
    assert gen_native.stale() == [], "run `make gen` (python -m tools.gen_native)"


def test_the_header_declares_the_flag_bits_of_fitflag():
    assert {name: int(FitFlag[name]) for name in invert_h.FLAG_BITS} == invert_h.FLAG_BITS
    assert {flag.name for flag in FitFlag} == set(invert_h.FLAG_BITS)  # THICKNESS_DISAGREE too (tm_combine)


def test_the_abi_hash_follows_the_declarations_not_the_comments():
    base = gen_native.abi_hash(HEADER_TEXT)
    assert base == invert_h.ABI_HASH
    assert gen_native.abi_hash(HEADER_TEXT.replace("/* axes */", "/* the axes, reworded */  ")) == base
    assert gen_native.abi_hash(HEADER_TEXT.replace("double t_max;", "double t_max, t_spare;")) != base


def test_the_generator_reads_fields_declared_together_and_refuses_what_it_cannot_map():
    spec = gen_native.parse(HEADER_TEXT)
    fields = [name for _, name in spec["structs"]["tm_forward_grid"]]
    assert fields[:6] == ["na", "ns", "ng", "alpha", "log_sigma_t", "g"]
    assert [name for name, _ in native._ForwardGridC._fields_] == fields
    with pytest.raises(gen_native.HeaderError, match="unknown type"):
        gen_native.render_py(HEADER_TEXT.replace("double thickness_mm,", "long double thickness_mm,"))


def test_the_generator_reads_the_part_of_the_boundary_shared_with_the_firmware_from_fit_core():
    raw = gen_native.HEADER.read_text(encoding="utf-8")
    assert '#include "table_fit.h"' in raw and "TM_FLAG_" not in raw  # declared once, in table_fit.h
    spec = gen_native.parse(HEADER_TEXT)
    assert "tm_table_fit" in spec["functions"] and "TM_TABLE_FIT_POLISH" in spec["defines"]
    assert spec["enums"]["tm_flag"]["TM_FLAG_NONFINITE_INPUT"] == 1
    with pytest.raises(gen_native.HeaderError, match="not a header in"):
        gen_native.header_text(raw.replace('"table_fit.h"', '"no_such_header.h"'))
    system_include = raw.replace('"table_fit.h"', "<table_fit.h>")
    assert gen_native.header_text(system_include) == system_include  # <…> includes stay as they are


def test_gen_native_check_names_a_stale_file(tmp_path, monkeypatch, capsys):
    stale_copy = tmp_path / "invert_h.py"
    stale_copy.write_text("# edited by hand\n", encoding="utf-8")
    monkeypatch.setattr(gen_native, "OUT_PY", stale_copy)
    assert gen_native.main(["--check"]) == 1
    assert "invert_h.py is stale" in capsys.readouterr().err
    assert stale_copy.read_text(encoding="utf-8") == "# edited by hand\n"  # --check writes nothing


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_the_built_library_is_current():
    assert native._LIB.tm_abi_hash() == invert_h.ABI_HASH
    assert native._LIB.tm_source_hash() == native.source_hash()


def _reload(monkeypatch, kernel=None):
    """native._load() under TRIMETER_KERNEL=kernel, with the warnings it gave."""
    monkeypatch.delenv("TRIMETER_NATIVE", raising=False)
    if kernel is None:
        monkeypatch.delenv("TRIMETER_KERNEL", raising=False)
    else:
        monkeypatch.setenv("TRIMETER_KERNEL", kernel)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lib, status = native._load()
    return lib, status, [w for w in caught if issubclass(w.category, native.NativeKernelWarning)]


@pytest.mark.parametrize("fault, words", [("missing", "is not built"), ("header", "built for another invert.h"),
                                          ("sources", "older than the C sources")])
def test_a_missing_or_stale_library_is_named_and_numpy_runs_with_a_warning(monkeypatch, fault, words):
    if fault == "missing":
        monkeypatch.setattr(native, "LIBRARY", native.LIBRARY.with_name("no-such-library.so"))
    elif not native.LIBRARY.is_file():
        pytest.skip("the library is not built")
    elif fault == "header":
        monkeypatch.setattr(native, "ABI_HASH", native.ABI_HASH ^ 1)
    else:
        monkeypatch.setattr(native, "source_hash", lambda: 12345)
    lib, status, warned = _reload(monkeypatch)
    assert lib is None and words in status and "make native" in status
    assert len(warned) == 1 and words in str(warned[0].message) and "make native" in str(warned[0].message)
    with pytest.raises(native.NativeKernelError, match=f"{words}.*make native"):
        _reload(monkeypatch, "native")


def test_numpy_chosen_on_purpose_runs_without_a_warning(monkeypatch):
    lib, status, warned = _reload(monkeypatch, "numpy")
    assert lib is None and warned == [] and "TRIMETER_KERNEL=numpy" in status
    monkeypatch.setenv("TRIMETER_NATIVE", "0")  # the older spelling of the same choice
    assert native._load()[0] is None


def test_an_unknown_kernel_choice_is_an_error(monkeypatch):
    with pytest.raises(native.NativeKernelError, match="auto, native or numpy"):
        _reload(monkeypatch, "fortran")


@pytest.mark.skipif(not native.available(), reason=native.status())
def test_auto_and_native_load_the_current_library_without_a_warning(monkeypatch):
    for kernel in (None, "native"):
        lib, status, warned = _reload(monkeypatch, kernel)
        assert lib is not None and status.startswith("compiled") and warned == []
