"""One Fresnel for the project (trimeter.model.fresnel): its numpy and Dr.Jit forms are the same
operations, bit for bit on a dense grid of angles and indices; its normal-incidence closed form agrees
with it; the physical limits hold."""

import numpy as np
import pytest

from trimeter.model.fresnel import NUMPY, fresnel, fresnel_polarised, normal_incidence_reflectance

COS = np.linspace(0.0, 1.0, 2001)
ETA = np.concatenate([np.linspace(1 / 1.8, 1.8, 157), [1.0, 1.5, 1 / 1.5, 1.33, 1 / 1.33]])


def _grid(dtype):
    cos, eta = np.meshgrid(COS.astype(dtype), ETA.astype(dtype))
    return cos.ravel(), eta.ravel()


def test_numpy_and_drjit_forms_agree_to_the_last_bit():
    """float32, as the map tracer's kernels compute it."""
    from trimeter.forward.transport.backend import load_drjit

    dr, B = load_drjit("llvm")
    cos, eta = _grid(np.float32)
    F_np, cos_t_np = fresnel(NUMPY, cos, eta)
    F_dr, cos_t_dr = fresnel(dr, B.Float(cos), B.Float(eta))
    assert F_np.dtype == np.float32
    np.testing.assert_array_equal(np.asarray(F_dr), F_np)
    np.testing.assert_array_equal(np.asarray(cos_t_dr), cos_t_np)


def test_normal_incidence_closed_form_agrees():
    n1, n2 = np.meshgrid(np.linspace(1.0, 2.0, 41), np.linspace(1.0, 2.0, 41))
    F, cos_t = fresnel(NUMPY, np.ones_like(n1), n2 / n1)
    np.testing.assert_allclose(normal_incidence_reflectance(n1, n2), F, rtol=1e-13, atol=1e-16)
    np.testing.assert_array_equal(cos_t, 1.0)


def test_limits():
    assert float(fresnel(NUMPY, 1.0, 1.5)[0]) == pytest.approx(0.04, rel=1e-12)
    assert float(fresnel(NUMPY, 0.0, 1.5)[0]) == pytest.approx(1.0)          # grazing
    assert float(fresnel(NUMPY, 0.5, 1 / 1.5)[0]) == 1.0                      # beyond the critical angle
    cos, eta = _grid(np.float64)
    F, cos_t = fresnel(NUMPY, cos, eta)
    assert np.all((F >= 0) & (F <= 1)) and np.all((cos_t >= 0) & (cos_t <= 1))
    # the same from either side of an interface at angles that refract (Stokes: R is symmetric)
    ok = cos_t > 0.05
    back, _ = fresnel(NUMPY, cos_t[ok], 1 / eta[ok])
    np.testing.assert_allclose(back, F[ok], rtol=1e-6, atol=1e-12)   # cancellation near the critical angle


def test_per_polarisation_it_averages_to_the_unpolarised_and_vanishes_for_p_at_brewster():
    cos, eta = _grid(np.float64)
    R_s, R_p, cos_t = fresnel_polarised(NUMPY, cos, eta)
    F, cos_t_unpolarised = fresnel(NUMPY, cos, eta)
    np.testing.assert_array_equal(cos_t, cos_t_unpolarised)
    np.testing.assert_allclose(0.5 * (R_s + R_p), F, rtol=1e-14, atol=1e-300)
    assert np.all(R_p <= R_s + 1e-15)  # s reflects at least as much as p at every angle
    assert float(fresnel_polarised(NUMPY, 1.0, 1.5)[0]) == pytest.approx(0.04)  # normal incidence: no plane,
    assert float(fresnel_polarised(NUMPY, 1.0, 1.5)[1]) == pytest.approx(0.04)  # both alike
    brewster = np.cos(np.arctan(1.5))
    assert float(fresnel_polarised(NUMPY, brewster, 1.5)[1]) == pytest.approx(0.0, abs=1e-15)
    assert float(fresnel_polarised(NUMPY, 0.5, 1 / 1.5)[1]) == 1.0  # beyond the critical angle
