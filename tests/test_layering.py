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
    {"version", "errors", "crc"},
    {"validation", "paths", "atomic", "toml_text"},
    {"geometry", "registers", "tables"},
    {"domain"},                         # plain data: captures, calibrations, reflectances, measurements, parameters
    {"model"},                          # the forward model: what the instrument reads for a material and a set-up
    {"formats"},                        # the files: appearance map, in-scattering table, device table, container
    {"forward", "inversion"},           # simulating the physics / solving the inverse, both on the model
    {"device"},                         # the instrument, over Modbus (and the table in its map slot)
    {"spectrometer"},                   # its detector (the mcu backend reads the firmware's over the device's link)
    {"maps"},                           # building maps and their children; the artifacts a fit loads
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
    ("def f():\n    import trimeter.maps.pipeline", ("inversion", "maps")),
    ("from ..maps import container", ("inversion", "maps")),
    ("from .. import maps", ("inversion", "maps")),
])
def test_the_edge_finder_sees(source, edge):
    assert edge in import_edges(source, PACKAGE / "inversion" / "api.py")
    assert RANK[edge[1]] >= RANK[edge[0]]  # each of these is an upward import the layer test would refuse


# ------------------------------------------------------------------ module level: no import cycles between files
def _module(path: Path, package: Path = PACKAGE) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports(source: str, path: Path, modules: set[str], root: Path = PACKAGE) -> set[str]:
    """The package's modules that `source` (the file at `path`) imports, relative imports resolved;
    `from package import name` counts as the submodule where `name` is one, else as the package. Imports
    inside functions and under TYPE_CHECKING count: each is a file that needs another."""
    me = _module(path, root)
    package = me.split(".") if path.name == "__init__.py" else me.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(source, str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            names = [f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module for a in node.names]
        else:
            continue
        for name in names:
            while name and name not in modules:     # trimeter.x.y.attribute → the module trimeter.x.y
                name = name.rpartition(".")[0]
            if name and name != me:
                found.add(name)
    return found


def module_graph(paths, root: Path = PACKAGE) -> dict[str, set[str]]:
    paths = list(paths)
    modules = {_module(p, root) for p in paths}
    return {_module(p, root): module_imports(p.read_text(encoding="utf-8"), p, modules, root) for p in paths}


def import_cycles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = set()
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in graph:
                    continue
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        cycles.add(frozenset(component))
    return cycles


# Cycles between modules still open, each to be broken where those files are being redesigned; any other
# cycle (or a module joining one of these) fails test_no_import_cycles_between_modules. Remove an entry
# when its cycle is broken (test_open_cycles_are_still_open says when). None is open.
OPEN_CYCLES: set[frozenset[str]] = set()


def _package_cycles() -> set[frozenset[str]]:
    return import_cycles(module_graph(PACKAGE.rglob("*.py")))


def test_no_import_cycles_between_modules():
    new = _package_cycles() - OPEN_CYCLES
    assert not new, "import cycles between modules: " + "; ".join(" <-> ".join(sorted(c)) for c in new)


def test_open_cycles_are_still_open():
    closed = OPEN_CYCLES - _package_cycles()
    assert not closed, "broken since, take them off OPEN_CYCLES: " + "; ".join(" <-> ".join(sorted(c)) for c in closed)


def test_the_cycle_finder_sees_imports_in_functions_and_submodules_by_name(tmp_path):
    package = tmp_path / "trimeter"
    (package / "sub").mkdir(parents=True)
    files = {"__init__.py": "", "sub/__init__.py": "",
             "sub/a.py": "from trimeter.sub import b\n",                      # a submodule named in a from-import
             "sub/b.py": "def f():\n    from .c import thing\n",            # relative, inside a function
             "sub/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import trimeter.sub.a\n",
             "sub/d.py": "from trimeter.sub.a import x\nfrom trimeter import sub\n"}   # d needs them, none needs d
    for name, text in files.items():
        (package / name).write_text(text)
    graph = module_graph(package.rglob("*.py"), package)
    assert graph["trimeter.sub.d"] == {"trimeter.sub.a", "trimeter.sub"}
    assert import_cycles(graph) == {frozenset({"trimeter.sub.a", "trimeter.sub.b", "trimeter.sub.c"})}
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == set()


# ------------------------------------------------------------------ the C: which directory may include which
# Each C directory with the directories its quoted includes may resolve into (its own first, then its
# include path). The inverse core (fit_core/) is shared by the firmware and the host's compiled kernel and
# includes neither; the firmware's core includes no port (a port fills a hal_t, firmware/core/hal.h); the
# host's kernel does not reach into the firmware.
C_INCLUDES = {
    "fit_core": ("fit_core",),
    "firmware/core": ("firmware/core", "fit_core"),
    "host/trimeter/inversion/native": ("host/trimeter/inversion/native", "fit_core"),
}


def c_include_problems(path: Path, source: str, allowed: tuple[str, ...], root: Path = ROOT) -> list[str]:
    """Each `#include "…"` in `source` (the file at `path`) that resolves, as the compiler would (the
    including file's directory, then the allowed ones), outside the allowed directories or nowhere."""
    problems = []
    dirs = [(root / d).resolve() for d in allowed]
    for number, line in enumerate(source.splitlines(), 1):
        name = line.split('#include "', 1)[1].split('"', 1)[0] if line.lstrip().startswith('#include "') else None
        if name is None:
            continue
        found = next((c.resolve() for c in [path.parent / name, *(d / name for d in dirs)] if c.is_file()), None)
        if found is None or not any(found.parent == d for d in dirs):
            problems.append(f"{path.relative_to(root)}:{number}: includes {name}"
                            f"{'' if found is None else ' (' + str(found.relative_to(root.resolve())) + ')'}")
    return problems


def test_c_includes_stay_in_their_layers():
    problems = [problem for directory, allowed in C_INCLUDES.items()
                for path in sorted((ROOT / directory).glob("*.[ch]"))
                for problem in c_include_problems(path, path.read_text(encoding="utf-8"), allowed)]
    assert problems == [], f"C includes outside their layer: {problems}"


@pytest.mark.parametrize("directory, line", [
    ("firmware/core", '#include "../ports/sim/plant.h"'),            # a port header, by a relative path
    ("firmware/core", '#include "ramfunc.h"'),                       # a port header no include path has
    ("fit_core", '#include "invert.h"'),                             # the host's boundary
    ("fit_core", '#include "../firmware/core/hal.h"'),               # the firmware's core
    ("host/trimeter/inversion/native", '#include "../../../../firmware/core/app.h"'),
])
def test_the_c_include_check_sees(directory, line):
    path = ROOT / directory / "anything.c"
    assert c_include_problems(path, f"#include <math.h>\n{line}\n", C_INCLUDES[directory]) != []
    assert c_include_problems(path, "#include <math.h>\n", C_INCLUDES[directory]) == []
