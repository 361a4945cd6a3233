"""`trimeter bench mapbuild`'s matched-error rule: what a direct render would cost at the map's own error."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.bench.mapbuild import matched_naive_seconds, stratified_mean
from trimeter.errors import InputError


def test_half_the_std_error_costs_four_times_the_sampling_and_the_overhead_once():
    seconds = np.array([3.0, 5.0, 2.0])
    naive_std = np.array([2e-4, 1e-4, 3e-4])
    map_std = np.array([1e-4, 1e-4, 6e-4])         # ×4, ×1 and ×¼ the samples
    got = matched_naive_seconds(seconds, 1.0, naive_std, map_std)
    np.testing.assert_allclose(got, [1.0 + 2.0 * 4, 1.0 + 4.0 * 1, 1.0 + 1.0 / 4])
    np.testing.assert_allclose(matched_naive_seconds(seconds, 0.0, naive_std, map_std), [12.0, 5.0, 0.5])


def test_an_overhead_above_the_fastest_render_is_held_to_it():
    """A render can never cost less than its fixed part: the overhead is capped at the fastest render."""
    got = matched_naive_seconds(np.array([2.0, 4.0]), 3.0, np.array([1e-4, 1e-4]), np.array([5e-5, 5e-5]))
    np.testing.assert_allclose(got, [2.0, 2.0 + 2.0 * 4])


def test_a_point_the_map_knows_exactly_cannot_be_matched():
    got = matched_naive_seconds(np.array([2.0, 4.0]), 0.5, np.array([1e-4, 1e-4]), np.array([0.0, 1e-4]))
    assert np.isinf(got[0]) and got[1] == pytest.approx(4.0)


@pytest.mark.parametrize("seconds, naive_std, map_std, overhead", [
    ([0.0], [1e-4], [1e-4], 0.1),                  # a render takes time
    ([1.0], [-1e-4], [1e-4], 0.1),
    ([1.0], [1e-4], [-1e-4], 0.1),
    ([1.0], [1e-4], [1e-4], -0.1),
    ([1.0, 2.0], [1e-4], [1e-4], 0.1),             # one std-error per point
    ([], [], [], 0.1),
])
def test_bad_input_is_a_clear_error(seconds, naive_std, map_std, overhead):
    with pytest.raises(InputError):
        matched_naive_seconds(np.array(seconds), overhead, np.array(naive_std), np.array(map_std))


@pytest.mark.parametrize("argv, message", [
    (["--naive-renders", "11"], "--naive-renders must be ≥ 12"),
    (["--spp", "100"], "--spp must be ≥ 4096"),
])
def test_bad_options_are_refused_before_any_render(capsys, argv, message):
    from trimeter.cli import main

    assert main(["bench", "mapbuild", *argv]) == 2
    assert f"trimeter: error: {message}" in capsys.readouterr().err


def test_the_stratified_mean_weighs_every_stratum_alike():
    """Stratum 0 is sampled three times as often as stratum 1: its values must not count three times."""
    values = np.array([1.0, 1.2, 0.8, 1.0, 1.2, 0.8, 10.0, 12.0])
    labels = np.array([0, 0, 0, 0, 0, 0, 1, 1])
    mean, err = stratified_mean(values, labels)
    assert mean == pytest.approx((1.0 + 11.0) / 2)
    within = np.sqrt(np.var([1.0, 1.2, 0.8] * 2, ddof=1) / 6 + np.var([10.0, 12.0], ddof=1) / 2) / 2
    assert err == pytest.approx(within)


def test_a_stratum_with_one_value_falls_back_to_the_unstratified_error():
    values, labels = np.array([1.0, 3.0, 10.0]), np.array([0, 0, 1])
    mean, err = stratified_mean(values, labels)
    assert mean == pytest.approx(6.0)
    assert err == pytest.approx(np.std(values, ddof=1) / np.sqrt(3))


def test_the_stratified_mean_refuses_mismatched_or_too_few_values():
    with pytest.raises(InputError):
        stratified_mean(np.array([1.0, 2.0]), np.array([0]))
    with pytest.raises(InputError):
        stratified_mean(np.array([1.0]), np.array([0]))
