"""Fixtures: the iadpython `ideal` maps (exact for their geometry; see ideal_map.py), their map
table and MLP, all committed under tests/inversion/data so no test renders or trains."""

from __future__ import annotations

from pathlib import Path

import pytest

from trimeter.formats.appearance import AppearanceMap

from inversion_support import DATA


@pytest.fixture(scope="session")
def ideal_map() -> AppearanceMap:
    return AppearanceMap.load(DATA / "ideal-l0.5.tmap")


@pytest.fixture(scope="session")
def thick_map() -> AppearanceMap:
    return AppearanceMap.load(DATA / "ideal-l1.0.tmap")


@pytest.fixture(scope="session")
def ideal_model() -> Path:
    return DATA / "ideal-l0.5.onnx"
