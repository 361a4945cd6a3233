"""Fixtures for the map tests: a tiny recipe cheap enough to build several times per run."""

import pytest

from trimeter.maps.recipe import parse_recipe


def tiny_recipe_dict(**sampling) -> dict:
    return {"name": "tiny", "geometry": "ideal", "n": 1.5, "thickness_mm": 0.5, "seed": 3,
            "grid": {"alpha": {"max": 0.99, "count": 6}, "sigma_t": [0.5, 5.0], "g": [0.0, 0.6]},
            "sampling": {"target_stderr": 1.0, "min_paths": 8192, "max_paths": 8192, **sampling}}


@pytest.fixture(scope="session")
def tiny_data():
    """A factory: the tiny recipe as a dict (tests change a field, then parse it)."""
    return tiny_recipe_dict


@pytest.fixture(scope="session")
def tiny_recipe():
    return parse_recipe(tiny_recipe_dict())
