"""trimeter.forward.adding_doubling: the package's adding-doubling reproduces the committed ideal map it built."""

import sys
from pathlib import Path

import numpy as np
import pytest

from trimeter.errors import BuildError
from trimeter.forward.adding_doubling import IAD_QUAD_POINTS, ideal_abc
from trimeter.formats.appearance import AppearanceMap

IDEAL_MAP = Path(__file__).resolve().parents[1] / "inversion" / "data" / "ideal-l0.5.tmap"


def test_reproduces_the_committed_ideal_maps_nodes():
    pytest.importorskip("iadpython")
    amap = AppearanceMap.load(IDEAL_MAP)
    idx = np.random.default_rng(0).integers(0, amap.A.shape, size=(8, 3))
    i, j, k = idx.T
    # built at 4 quadrature points (tests/inversion/ideal_map.py, FIXTURE_QUAD_POINTS: why)
    abc = ideal_abc(amap.alpha[i], amap.sigma_t[j], amap.g[k], thickness_mm=amap.thickness_mm, n=amap.n, quad_points=4)
    # the map stores float32: equal to its rounding
    np.testing.assert_allclose(abc, np.column_stack([amap.A[i, j, k], amap.B[i, j, k], amap.C[i, j, k]]), rtol=2e-7)


def test_the_default_quadrature_is_converged():
    """IAD_QUAD_POINTS against twice as many: a clear slab and a dark, turbid, forward-scattering one (where
    iadpython's own default of 4 points is 0.5 % and 4 % off) agree to 0.1 %; 4 points do not."""
    pytest.importorskip("iadpython")
    from trimeter.model.response import background_response

    materials = ([0.0104, 0.7055], [0.056, 20.7], [0.65, 0.86])

    def reflectances(quad_points):
        A, B, C = ideal_abc(*materials, thickness_mm=0.5, n=1.5, quad_points=quad_points).T
        return np.array([background_response(A, B, C, rho) for rho in (0.02, 0.9)])

    exact = reflectances(64)
    np.testing.assert_allclose(reflectances(IAD_QUAD_POINTS), exact, rtol=1e-3)
    assert np.max(np.abs(reflectances(4) / exact - 1)) > 0.02


def test_without_iadpython_it_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "iadpython", None)
    with pytest.raises(BuildError, match="iadpython"):
        ideal_abc([0.9], [1.0], [0.5], thickness_mm=0.5, n=1.5)
