"""The mixing rule (trimeter.model.mixing), shared by measured materials and the twin's samples."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.model.mixing import mix_coefficients, parse_fractions
from trimeter.results.medium import SpectralMaterial


def test_coefficients_add_and_g_is_scattering_weighted():
    sa, ss, g = mix_coefficients([[1.0, 0.0], [0.0, 0.0]], [[2.0, 0.0], [6.0, 0.0]], [[0.2, 0.1], [0.6, 0.3]],
                                 [1.0, 3.0])   # normalised: 0.25, 0.75
    assert np.allclose(sa, [0.25, 0.0]) and np.allclose(ss, [5.0, 0.0])
    assert g[0] == pytest.approx((0.25 * 2 * 0.2 + 0.75 * 6 * 0.6) / 5.0)
    assert g[1] == pytest.approx(0.25 * 0.1 + 0.75 * 0.3)   # nothing scatters: the fractions' mean


def test_the_material_mixture_is_the_rule():
    lam = np.array([400.0, 500.0])
    a = SpectralMaterial(lam, np.array([0.5, 0.9]), np.array([2.0, 1.0]), np.array([0.1, 0.2]))
    b = SpectralMaterial(lam, np.array([0.8, 0.3]), np.array([4.0, 3.0]), np.array([0.7, 0.5]))
    m = SpectralMaterial.mixture([a, b], [0.3, 0.7])
    sa, ss, g = mix_coefficients([a.sigma_a, b.sigma_a], [a.sigma_s, b.sigma_s], [a.g, b.g], [0.3, 0.7])
    assert np.allclose(m.sigma_a, sa) and np.allclose(m.sigma_s, ss) and np.allclose(m.g, g)


@pytest.mark.parametrize("fractions,message", [([1.0], "one volume fraction per material"),
                                               ([0.0, 0.0], "not all 0"), ([np.nan, 1.0], "finite")])
def test_bad_fractions(fractions, message):
    with pytest.raises(InputError, match=message):
        mix_coefficients([[1.0], [1.0]], [[1.0], [1.0]], [[0.0], [0.0]], fractions)


def test_parse_fractions():
    assert parse_fractions("c:0.4+y:0.6") == [("c", 0.4), ("y", 0.6)]
    assert parse_fractions("a:b:1") == [("a:b", 1.0)]   # the last colon separates the fraction
    for bad in ("c:0.4+y:0.5", "c+y", "c:0.5+c:0.5", ":1", "c:-1+y:2"):
        with pytest.raises(InputError, match="mixture"):
            parse_fractions(bad)
