"""Combining repeats: inverse-variance mean, its std, the spread between repeats, the χ² flag, and two
thicknesses re-fitted jointly from the members' reflectances."""

from __future__ import annotations

import numpy as np
import pytest

import trimeter
from library_support import WL, capture, fit_result, write_member
from trimeter.errors import InputError
from trimeter.library.combine import DISAGREE_P, LibraryFlag, combine, weighted_mean


def test_inverse_variance_mean_std_spread_and_chi2():
    x = np.array([[1.0, 1.0], [2.0, 3.0]])
    s = np.array([[1.0, 0.1], [2.0, 0.1]])
    mean, std, spread, p, n, no_std = weighted_mean(x, s)
    # bin 0: weights 1 and 1/4
    assert mean[0] == pytest.approx((1 + 2 / 4) / 1.25)
    assert std[0] == pytest.approx(1 / np.sqrt(1.25))
    assert spread[0] == pytest.approx(np.sqrt(((1 - mean[0]) ** 2 + (2 - mean[0]) ** 2) / 1))
    # bin 1: 1 and 3 with stds 0.1: χ² = 200 on 1 dof
    assert mean[1] == pytest.approx(2.0) and p[1] < 1e-40
    assert p[0] > 0.5 and list(n) == [2, 2] and not no_std.any()


def test_missing_values_and_stds():
    x = np.array([[1.0, np.nan, 5.0], [3.0, 2.0, 7.0]])
    s = np.array([[np.nan, 1.0, 1.0], [1.0, 1.0, 1.0]])
    mean, std, spread, p, n, no_std = weighted_mean(x, s)
    assert mean[0] == pytest.approx(2.0) and np.isnan(std[0]) and no_std[0]   # plain mean, no std
    assert mean[1] == 2.0 and np.isnan(spread[1]) and n[1] == 1              # one member: no spread
    assert mean[2] == pytest.approx(6.0) and std[2] == pytest.approx(1 / np.sqrt(2))


def test_members_agreeing_and_disagreeing(tmp_path):
    a = write_member(tmp_path, fit_result(0.9, 2.0, 0.5))
    b = write_member(tmp_path, fit_result(0.9, 2.0, 0.5))
    c = write_member(tmp_path, fit_result(np.where(WL > 600, 0.7, 0.9), 2.0, 0.5))   # a bad repeat in the red
    agree = combine([trimeter.load(a), trimeter.load(b)])
    assert np.allclose(agree.values["alpha"], 0.9) and np.allclose(agree.stds["alpha"], 0.01 / np.sqrt(2))
    assert np.allclose(agree.spreads["alpha"], 0.0) and not agree.flags.any()
    three = combine([trimeter.load(p) for p in (a, b, c)])
    red = WL > 600
    assert np.all(three.flags[red] & LibraryFlag.REPEATS_DISAGREE)
    assert not np.any(three.flags[~red] & LibraryFlag.REPEATS_DISAGREE)
    assert np.all(three.chi2_p["alpha"][red] < DISAGREE_P)
    assert np.allclose(three.spreads["alpha"][red], np.std([0.9, 0.9, 0.7], ddof=1), atol=0.01)
    single = combine([trimeter.load(a)])
    assert np.all(single.flags & LibraryFlag.SINGLE_MEMBER) and np.isnan(single.spreads["alpha"]).all()


def test_members_over_other_wavelengths_are_refused(tmp_path):
    a = trimeter.load(write_member(tmp_path, fit_result(0.9, 2.0, 0.5)))
    b = trimeter.load(write_member(tmp_path, fit_result(0.9, 2.0, 0.5)))
    b.parameters.wavelengths_nm[:] += 1.0
    with pytest.raises(InputError, match="not over the wavelengths"):
        combine([a, b])


def test_two_thicknesses_are_refitted_jointly(tmp_path):
    """A member at 0.4 mm and one at 0.8 mm, each with the reflectances the shipped maps give for a known
    material: the joint re-fit recovers it, better in α and g than either member's parameters alone."""
    truth = (0.8, 3.0, 0.5)
    members = []
    for t in (0.4, 0.8):
        amap = trimeter.open_map(f"device-n1.5-l{t:g}")
        rho_b, rho_w = np.full(len(WL), 0.03), np.full(len(WL), 0.99)
        I_b, I_w, I_c = amap.query(*(np.full(len(WL), v) for v in truth), rho_b, rho_w)
        # the members' own parameters are off (as a one-thickness fit can be); their reflectances are right
        members.append(write_member(tmp_path, fit_result(0.75, 3.0, 0.4), thickness=t, map_name=amap.name,
                                    sample=(I_b, I_w, I_c)))
    loaded = [trimeter.load(p) for p in members]
    refl = loaded[0].reflectances[0]
    assert np.allclose(refl.rho_b, 0.03, atol=2e-3)   # the fake capture gives back what it was handed
    combined = combine(loaded)
    assert combined.method == "joint-refit" and combined.thicknesses_mm == [0.4, 0.8]
    assert np.nanmedian(np.abs(combined.values["alpha"] - truth[0])) < 0.01
    assert np.nanmedian(np.abs(combined.values["g"] - truth[2])) < 0.05
    assert np.isfinite(combined.stds["alpha"]).all()
    plain = combine(loaded, joint=False)
    assert plain.method == "inverse-variance" and np.allclose(plain.values["alpha"], 0.75)


def test_capture_helper_gives_back_its_sample():
    n = len(WL)
    _, _, refl = capture((np.full(n, 0.3), np.full(n, 0.6), np.full(n, 0.2)))
    assert np.allclose(refl.I_b, 0.3, rtol=1e-3) and np.allclose(refl.I_c, 0.2, rtol=1e-3)
