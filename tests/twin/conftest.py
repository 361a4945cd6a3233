"""Shared fixtures for the twin tests: a small exact `ideal` appearance map at the twin's default thickness."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.formats.appearance import AppearanceMap

THICKNESS_MM = 0.4
N = 1.5


def build_small_ideal_map(path, thickness_mm: float = THICKNESS_MM) -> AppearanceMap:
    """6×6×4 grid from iadpython (adding-doubling, exact at the grid points); ~2 s here. Coarse on purpose:
    the twin only needs *a* consistent forward relation, not an accurate one."""
    from iadpython import Sample

    alpha = 1.0 - (1.0 - np.linspace(0.0, 1.0, 6)) ** 2
    sigma_t = np.geomspace(0.5, 25.0, 6)
    g = np.linspace(0.0, 0.9, 4)
    A, B, C = (np.empty((6, 6, 4)) for _ in range(3))
    for i, a in enumerate(alpha):
        for j, s in enumerate(sigma_t):
            for k, gk in enumerate(g):
                ur1, ut1, uru, utu = Sample(a=float(a), b=float(s) * thickness_mm, g=float(gk), d=thickness_mm,
                                            n=N, n_above=1, n_below=1).rt()
                A[i, j, k], B[i, j, k], C[i, j, k] = ur1, ut1 * utu, uru
    recipe = {"name": f"ideal-test-l{thickness_mm:g}", "geometry": "ideal", "n": N, "thickness_mm": thickness_mm}
    amap = AppearanceMap(recipe=recipe, alpha=alpha, sigma_t=sigma_t, g=g, A=A, B=B, C=C,
                         std_b=np.zeros(A.shape), std_w=np.zeros(A.shape))
    amap.save(path)
    return AppearanceMap.load(path)


@pytest.fixture(scope="session")
def ideal_map(tmp_path_factory) -> AppearanceMap:
    return build_small_ideal_map(tmp_path_factory.mktemp("maps") / "ideal-test-l0.4.tmap")
