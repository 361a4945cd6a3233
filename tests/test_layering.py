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
