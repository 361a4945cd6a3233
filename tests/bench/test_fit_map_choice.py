"""Which maps `trimeter bench fit` scores when given no --map: shipped ones only, never a test fixture."""

from __future__ import annotations

from pathlib import Path

import pytest

from trimeter.bench import fit as bench
from trimeter.paths import MAPS_DIR, REPO_ROOT


def test_the_fallback_map_is_shipped_not_a_test_fixture():
    assert bench.IDEAL_FALLBACK.is_file()
    assert bench.IDEAL_FALLBACK.parent == MAPS_DIR
    assert (REPO_ROOT / "tests") not in bench.IDEAL_FALLBACK.parents


def test_without_held_out_sets_the_shipped_ideal_map_is_scored(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    monkeypatch.setattr(bench, "HELDOUT_DIR", tmp_path)  # no shipped map has a held-out set here
    (amap,) = bench._maps(None)
    assert amap.path is not None and amap.path.resolve() == bench.IDEAL_FALLBACK.resolve()


def test_with_held_out_sets_every_such_shipped_map_is_scored():
    names = {amap.name for amap in bench._maps(None)}
    expected = {p.stem for p in (MAPS_DIR / "heldout").glob("*.held")} & {p.stem for p in MAPS_DIR.glob("*.tmap")}
    assert names == expected and expected
