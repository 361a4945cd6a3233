"""The lead's analytic I_c (trimeter.model.collimated) against adding-doubling and its own inverse."""

import math

import numpy as np
import pytest

from trimeter.model.collimated import beer_lambert_sigma_t, collimated_transmittance

iadpython = pytest.importorskip("iadpython")

SIGMAS = np.array([0.0, 0.05, 0.3, 1.0, 4.0, 12.0, 40.0])


@pytest.mark.parametrize("n", [1.0, 1.33, 1.5, 1.7])
@pytest.mark.parametrize("thickness", [0.4, 0.8])
def test_matches_iadpython_unscattered_transmittance_in_air(n, thickness):
    ours = collimated_transmittance(SIGMAS, thickness, n)
    theirs = [float(iadpython.Sample(a=0.5, b=s * thickness, g=0.0, d=thickness, n=n, n_above=1.0,
                                     n_below=1.0).unscattered_rt()[1]) for s in SIGMAS]
    np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-300)


def test_cover_slides_agree_with_iadpython_glass_slides():
    # iadpython 0.5.3's _specular_rt sets the slab's inter-reflection denominator 1 − r_top·r_bot·e^(−2b)
    # to 1 for a scalar cosine (`if np.isscalar(denom): denom = 1`), i.e. drops the multiple
    # reflections between the two slide-covered faces (−0.16 % at b = 0.05). Restore that factor
    # from iadpython's own slide reflectance and the two must agree exactly.
    from iadpython.fresnel import absorbing_glass_RT

    r_face = float(absorbing_glass_RT(1.5, 1.52, 1.0, 1.0, 0.0)[0])
    for s in (0.0, 0.1, 2.0, 10.0):
        x = math.exp(-s * 0.5)
        ours = float(collimated_transmittance(s, 0.5, 1.5, 1.52))
        theirs = float(iadpython.Sample(a=0.5, b=s * 0.5, g=0.0, d=0.5, n=1.5, n_above=1.52,
                                        n_below=1.52).unscattered_rt()[1])
        assert ours == pytest.approx(theirs / (1.0 - r_face**2 * x * x), rel=1e-9)
    # A slide of a different index than the sample adds two reflecting interfaces: less light.
    assert collimated_transmittance(0.0, 0.5, 1.3, 1.52) < collimated_transmittance(0.0, 0.5, 1.3)


def test_no_extinction_is_the_fresnel_stack_alone():
    r = ((1.5 - 1) / (1.5 + 1)) ** 2
    assert float(collimated_transmittance(0.0, 0.5, 1.5)) == pytest.approx((1 - r) ** 2 / (1 - r * r), rel=1e-12)
    assert float(collimated_transmittance(0.0, 0.5, 1.0)) == 1.0


@pytest.mark.parametrize("cover", [None, 1.52])
@pytest.mark.parametrize("thickness", [0.4, 0.8])
def test_beer_lambert_inverse_round_trip(cover, thickness):
    ic = collimated_transmittance(SIGMAS, thickness, 1.5, cover)
    back = beer_lambert_sigma_t(ic, thickness, 1.5, cover)
    np.testing.assert_allclose(back, SIGMAS, rtol=1e-9, atol=1e-9)


def test_beer_lambert_inverse_refuses_impossible_intensities():
    t0 = float(collimated_transmittance(0.0, 0.5, 1.5))
    out = beer_lambert_sigma_t(np.array([0.0, -0.1, math.nan, t0 * 1.01, 1.5]), 0.5, 1.5)
    assert np.all(np.isnan(out))
