"""The α = 0 closed form (trimeter.forward.nonscattering), itself checked before it checks the renders."""

import numpy as np
import pytest

from trimeter.model.collimated import collimated_transmittance
from trimeter.forward.nonscattering import nonscattering_coefficients, stack_rt

iadpython = pytest.importorskip("iadpython")


@pytest.mark.parametrize("sigma_t", [0.05, 1.0, 5.0, 30.0])
def test_ideal_alpha0_coefficients_match_adding_doubling(sigma_t):
    A, B, C = nonscattering_coefficients("ideal", sigma_t, 0.5, 1.5)
    ur1, ut1, uru, utu = iadpython.Sample(a=0.0, b=sigma_t * 0.5, g=0.0, d=0.5, n=1.5, n_above=1.0, n_below=1.0,
                                          quad_pts=32).rt()
    assert pytest.approx(ur1, rel=1e-6) == A
    assert pytest.approx(ut1 * utu, rel=2e-3) == B
    assert pytest.approx(uru, rel=2e-3) == C


def test_normal_incidence_transmittance_is_the_collimated_model():
    for cover in (None, 1.52):
        indices = [1.0, 1.5, 1.0] if cover is None else [1.0, cover, 1.5, cover, 1.0]
        for s in (0.0, 0.7, 4.0):
            depths = [s * 0.8] if cover is None else [0.0, s * 0.8, 0.0]
            _, T = stack_rt(np.ones(1), indices, depths)
            assert T[0] == pytest.approx(float(collimated_transmittance(s, 0.8, 1.5, cover)), rel=1e-12)


def test_device_alpha0_has_no_specular_term_and_sane_coefficients():
    A, B, C = nonscattering_coefficients("device", np.array([0.05, 1.0, 10.0]), 0.4, 1.5)
    assert np.all(A == 0.0)
    assert np.all(np.diff(B) < 0) and 0 < B[0] < 1 and np.all(C > 0) and np.all(C < 0.5)
