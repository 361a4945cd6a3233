"""fit()'s checked settings, kept per distinct call (inversion.api._settings): a call with other
parameters or other models never gets another call's settings, and bad parameters are refused every time."""

from __future__ import annotations

import gc
from types import SimpleNamespace

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.inversion import api
from trimeter.inversion.artifacts import load_artifacts
from trimeter.inversion.methods import get_method
from trimeter.inversion.strategy import Method

from inversion_support import forward, well_conditioned


def _case(amap, n=64):
    a, s, g = well_conditioned(amap, n, np.random.default_rng(3))
    return forward(amap, a, s, g, 0.02, 0.99)


def _same(a, b):
    return all(np.array_equal(getattr(a, c), getattr(b, c), equal_nan=True) for c in a.COLUMNS)


def test_a_call_with_other_parameters_gets_its_own_settings(ideal_map):
    model, I = load_artifacts(ideal_map), _case(ideal_map)
    first = api.fit(model, *I, noise_rel=0.005)
    wider = api.fit(model, *I, noise_rel=0.02)
    assert np.all(wider.alpha_std[np.isfinite(first.alpha)] > first.alpha_std[np.isfinite(first.alpha)])
    assert _same(api.fit(model, *I, noise_rel=0.005), first)
    api._SETTINGS.clear()
    assert _same(api.fit(model, *I, noise_rel=0.005), first)  # kept settings are those checked afresh
    one_step = api.fit(model, *I, polish=1, polish_tol=0.0)
    assert not _same(one_step, first)
    thick = api.fit(model, *I, thickness_std_mm=np.array([0.05]))  # not hashable: checked each time
    assert np.all(thick.sigma_t_std[np.isfinite(first.alpha)] >= first.sigma_t_std[np.isfinite(first.alpha)])


@pytest.mark.parametrize("bad", [dict(noise_rel=-1.0), dict(ic_floor=0.0), dict(polish=-1), dict(first_row=-3),
                                 dict(noise_abs=float("nan")), dict(method="evil")])
def test_bad_parameters_are_refused_every_time(ideal_map, bad):
    model, I = load_artifacts(ideal_map), _case(ideal_map, 8)
    for _ in range(2):
        with pytest.raises(InputError):
            api.fit(model, *I, **bad)


class _StandIn:
    """Just what _check_settings reads of a model (weakly referable, as models are)"""

    def __init__(self, thickness_mm):
        self.setup = SimpleNamespace(thickness_mm=thickness_mm)
        self.reference_rhos = (0.0, 1.0)
        self.inverter = SimpleNamespace(grid=SimpleNamespace(mc_stderr=0.0, transmittance_limits=(0.9, 0.9)))


def test_a_model_gone_does_not_pass_its_settings_to_one_that_takes_its_id():
    """An id is a live object's only: a model that is gone may have passed its id on, and the kept settings
    of the old model must not serve the new one (staged here by keeping them under the new model's id)."""
    params = (None, 1e-6, 0.005, 2e-4, 1e-4, 0.02, 0.01, 250, 0.05, 0.1, 0)
    lut = get_method("lut")
    first, second = _StandIn(1.0), _StandIn(2.0)
    assert api._settings([first], lut, *params).thickness_rel == [0.1]
    kept = api._SETTINGS[(id(lut), (id(first),), params)]
    api._SETTINGS[(id(lut), (id(second),), params)] = kept
    del first
    gc.collect()
    assert api._settings([second], lut, *params).thickness_rel == [0.05]
    assert api._settings([second], lut, *params) is api._settings([second], lut, *params)


def test_a_method_registered_again_under_a_name_is_another(ideal_map):
    """Settings kept for a method are not those of a method registered later under the same name."""
    from trimeter.inversion import methods

    model, I = load_artifacts(ideal_map), _case(ideal_map, 8)
    temporary = Method("temporary", "lut under another name")
    methods.register(temporary)
    try:
        assert api.fit(model, *I, method="temporary").method == "temporary"
    finally:
        methods.unregister("temporary")
    with pytest.raises(InputError, match="method must be one of"):
        api.fit(model, *I, method="temporary")
