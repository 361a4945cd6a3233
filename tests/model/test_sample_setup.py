"""SampleSetup.matches_thickness: the one match of a declared thickness against a map's or table's ℓ."""

import numpy as np

from trimeter.domain.measurement import THICKNESS_TOLERANCE
from trimeter.model.sample_setup import SampleSetup


def test_a_thickness_matches_to_rounding_relative_to_the_map_above_one_mm():
    thick = SampleSetup(1.5, 4.0)
    assert thick.matches_thickness(4.0 + 3.9e-6)                  # within 1e-6 · ℓ
    assert not thick.matches_thickness(4.0 + 4.1e-6)
    thin = SampleSetup(1.5, 0.4)
    assert thin.matches_thickness(0.4 + 0.9 * THICKNESS_TOLERANCE)  # absolute below 1 mm
    assert not thin.matches_thickness(0.4 + 1.1 * THICKNESS_TOLERANCE)
    assert not thin.matches_thickness(0.5)


def test_a_column_of_thicknesses_is_matched_row_by_row_and_nan_matches_nothing():
    rows = SampleSetup(1.5, 0.4).matches_thickness(np.array([0.4, 0.5, np.nan, 0.4 + 5e-7]))
    assert rows.tolist() == [True, False, False, True]
