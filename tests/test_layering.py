"""Layering: the product (host/) and the tools (tools/) never reach into tests/, by import or by editing sys.path.
Anything both need lives in the package (or maps/), so a product or tool runs from any checkout or install."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# `tests`, `conftest`, and the helper modules tests import by bare name (tests/conftest.py puts tests/ on the path)
TEST_MODULES = {"tests", "conftest"} | {p.stem for p in (ROOT / "tests").rglob("*.py")
                                         if not p.stem.startswith("test_")}


def _is_sys_path(node: ast.AST) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name)
            and node.value.id == "sys")


def layering_problems(source: str, filename: str = "<source>") -> list[str]:
    """Each import of a test module and each change to sys.path in `source`, as 'file:line: what'."""
    problems = []
    for node in ast.walk(ast.parse(source, filename)):
        where = f"{filename}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Import):
            problems += [f"{where}: imports {a.name}" for a in node.names if a.name.split(".")[0] in TEST_MODULES]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0 and node.module and node.module.split(".")[0] in TEST_MODULES:
                problems.append(f"{where}: imports from {node.module}")
            if node.module == "sys" and any(a.name == "path" for a in node.names):
                problems.append(f"{where}: imports sys.path (to change it)")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and _is_sys_path(node.func.value):
            problems.append(f"{where}: calls sys.path.{node.func.attr}")
        elif isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Delete)):
            targets = node.targets if isinstance(node, (ast.Assign, ast.Delete)) else [node.target]
            for t in targets:
                if _is_sys_path(t) or (isinstance(t, ast.Subscript) and _is_sys_path(t.value)):
                    problems.append(f"{where}: assigns to sys.path")
    return problems


def _sources():
    return sorted(p for top in ("host", "tools") for p in (ROOT / top).rglob("*.py"))


def test_no_product_or_tool_imports_tests_or_edits_sys_path():
    sources = _sources()
    assert len(sources) > 50  # the walk found the package, not an empty folder
    problems = [msg for p in sources for msg in layering_problems(p.read_text(), str(p.relative_to(ROOT)))]
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("snippet", [
    "import tests.fakes",
    "from tests.inversion import ideal_map",
    "from conftest import ROOT",
    "import hil_support",
    "from ideal_map import ideal_abc",
    "import sys\nsys.path.insert(0, 'tests')",
    "import sys\nsys.path.append('x')",
    "import sys\nsys.path += ['x']",
    "import sys\nsys.path = ['x']",
    "import sys\nsys.path[:0] = ['x']",
    "from sys import path\npath.insert(0, 'x')",
])
def test_the_check_catches(snippet):
    assert layering_problems(snippet)


@pytest.mark.parametrize("snippet", [
    "import sys\nprint(sys.path)",
    "from trimeter.forward.adding_doubling import ideal_abc",
    "from . import fakes_helper",
    "import os.path\nos.path.join('a', 'b')",
])
def test_the_check_passes(snippet):
    assert not layering_problems(snippet)


# The package's layers, lowest first. A module may import only from lower layers (its own subpackage aside); two
# subpackages on one layer are independent of each other. Imports inside functions count: deferring an import
# hides a cycle from Python, not from a reader.
LAYERS = (
    {"__version__", "errors", "crc"},
    {"validation", "paths", "atomic", "toml_text"},
    {"geometry", "registers", "tables"},
    {"domain"},                         # plain data: captures, calibrations, reflectances, measurements, parameters
    {"model"},                          # the forward model: what the instrument reads for a material and a set-up
    {"forward", "inversion"},           # simulating the physics / solving the inverse, both on the model
    {"device"},                         # the instrument, over Modbus
    {"spectrometer"},                   # its detector (the mcu backend reads the firmware's over the device's link)
    {"maps"},                           # files and artifacts (a table is read from a device)
    {"results"},
    {"twin"},                           # its virtual samples and mixtures are results' spectral materials
    {"sequences", "prediction", "library"},
    {"web", "bench"},
    {"cli", "<package>"},
    {"__main__"},
)
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}
PACKAGE = ROOT / "host" / "trimeter"


def _unit(path: Path) -> str:
    """The subpackage (or top-level module) a source file belongs to."""
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return "<package>" if parts == ("__init__",) else parts[0]


def import_edges(source: str, path: Path) -> set[tuple[str, str]]:
    """(importing unit, imported unit) for every `trimeter` import in `source`, relative ones resolved."""
    unit = _unit(path)
    package = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if package[-1] == "__init__":
        package.append("")
    edges = set()
    for node in ast.walk(ast.parse(source, str(path))):
        if isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            modules = [module] if node.module or node.level == 0 else [f"{module}.{a.name}" for a in node.names]
        else:
            continue
        for module in modules:
            parts = module.split(".")
            if parts[0] == "trimeter" and len(parts) > 1 and parts[1] != unit:
                edges.add((unit, parts[1]))
    return edges


def _package_edges() -> set[tuple[str, str]]:
    return {e for p in PACKAGE.rglob("*.py") for e in import_edges(p.read_text(encoding="utf-8"), p)}


def test_every_unit_has_a_layer():
    units = {_unit(p) for p in PACKAGE.rglob("*.py")}
    assert units - RANK.keys() == set(), "add new subpackages to LAYERS"


def test_imports_only_go_down():
    upward = sorted(f"{a} -> {b}" for a, b in _package_edges() if RANK.get(b, -1) >= RANK.get(a, -1))
    assert upward == [], f"imports that go sideways or up the layers: {upward}"


@pytest.mark.parametrize(("source", "edge"), [
    ("from trimeter.maps import container", ("inversion", "maps")),
    ("def f():\n    import trimeter.maps.artifacts", ("inversion", "maps")),
    ("from ..maps import container", ("inversion", "maps")),
    ("from .. import maps", ("inversion", "maps")),
])
def test_the_edge_finder_sees(source, edge):
    assert edge in import_edges(source, PACKAGE / "inversion" / "api.py")
    assert RANK[edge[1]] >= RANK[edge[0]]  # each of these is an upward import the layer test would refuse
