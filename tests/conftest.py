"""Shared pytest options: the HIL suite runs against the twin unless --port/--spectrometer name a real
instrument; tests marked `hardware` need one and are skipped on the twin."""

import os
import sys
from pathlib import Path

import pytest

# tests/fakes.py and tests/hil_support.py are imported by name from several folders; make that work
# under any --import-mode (prepend adds this folder itself, importlib does not).
sys.path.insert(0, str(Path(__file__).resolve().parent))


def pytest_addoption(parser):
    group = parser.getgroup("trimeter hardware-in-the-loop")
    group.addoption("--port", default=None, help="serial port of a real trimeter (default: start the twin)")
    group.addoption("--spectrometer", default=None, help="spectrometer URL of the real instrument, e.g. seabreeze:")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--port"):
        return
    skip = pytest.mark.skip(reason="needs a real instrument: pass --port and --spectrometer")
    for item in items:
        # the marker, not the keyword: tests/hardware/ (the printed parts) puts "hardware" in every keyword set there
        if item.get_closest_marker("hardware"):
            item.add_marker(skip)


@pytest.fixture(scope="session", autouse=True)
def cache_dir_of_this_process():
    """TRIMETER_CACHE_DIR (the device tables read from instruments, the twin's seeded storage images) one
    directory per pytest process, kept between runs: under pytest-xdist each worker's twins then find (or
    miss) the tables their own tests cached, whatever the other worker ran before. A subdirectory of the
    cache directory in force (TRIMETER_CACHE_DIR or the user's), named by the worker (PYTEST_XDIST_WORKER;
    "main" without xdist); tests that need an empty cache still set their own."""
    import platformdirs

    base = os.environ.get("TRIMETER_CACHE_DIR") or platformdirs.user_cache_dir("trimeter")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TRIMETER_CACHE_DIR", str(Path(base) / "pytest" / os.environ.get("PYTEST_XDIST_WORKER", "main")))
        yield
