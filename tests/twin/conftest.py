"""Shared fixtures for the twin tests: a small exact `ideal` appearance map at the twin's default thickness."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.formats.appearance import AppearanceMap

THICKNESS_MM = 0.4
N = 1.5


def build_small_ideal_map(path, thickness_mm: float = THICKNESS_MM) -> AppearanceMap:
    """6×6×4 grid from iadpython (adding-doubling, exact at the grid points); a few seconds. Coarse on purpose:
    the twin only needs *a* consistent forward relation, not an accurate one."""
    from trimeter.forward.adding_doubling import ideal_abc

    alpha = 1.0 - (1.0 - np.linspace(0.0, 1.0, 6)) ** 2
    sigma_t = np.geomspace(0.5, 25.0, 6)
    g = np.linspace(0.0, 0.9, 4)
    aa, ss, gg = np.meshgrid(alpha, sigma_t, g, indexing="ij")
    abc = ideal_abc(aa.ravel(), ss.ravel(), gg.ravel(), thickness_mm=thickness_mm, n=N).reshape(*aa.shape, 3)
    A, B, C = abc[..., 0], abc[..., 1], abc[..., 2]
    recipe = {"name": f"ideal-test-l{thickness_mm:g}", "geometry": "ideal", "n": N, "thickness_mm": thickness_mm}
    amap = AppearanceMap(recipe=recipe, alpha=alpha, sigma_t=sigma_t, g=g, A=A, B=B, C=C,
                         std_b=np.zeros(A.shape), std_w=np.zeros(A.shape))
    amap.save(path)
    return AppearanceMap.load(path)


@pytest.fixture(scope="session")
def ideal_map(tmp_path_factory) -> AppearanceMap:
    return build_small_ideal_map(tmp_path_factory.mktemp("maps") / "ideal-test-l0.4.tmap")
