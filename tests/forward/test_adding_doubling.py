"""trimeter.forward.adding_doubling: the package's adding-doubling reproduces the committed ideal map it built."""

import sys
from pathlib import Path

import numpy as np
import pytest

from trimeter.errors import BuildError
from trimeter.forward.adding_doubling import ideal_abc
from trimeter.formats.appearance import AppearanceMap

IDEAL_MAP = Path(__file__).resolve().parents[1] / "inversion" / "data" / "ideal-l0.5.tmap"


def test_reproduces_the_committed_ideal_maps_nodes():
    pytest.importorskip("iadpython")
    amap = AppearanceMap.load(IDEAL_MAP)
    idx = np.random.default_rng(0).integers(0, amap.A.shape, size=(8, 3))
    i, j, k = idx.T
    abc = ideal_abc(amap.alpha[i], amap.sigma_t[j], amap.g[k], thickness_mm=amap.thickness_mm, n=amap.n)
    # the map stores float32: equal to its rounding
    np.testing.assert_allclose(abc, np.column_stack([amap.A[i, j, k], amap.B[i, j, k], amap.C[i, j, k]]), rtol=2e-7)


def test_without_iadpython_it_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "iadpython", None)
    with pytest.raises(BuildError, match="iadpython"):
        ideal_abc([0.9], [1.0], [0.5], thickness_mm=0.5, n=1.5)
