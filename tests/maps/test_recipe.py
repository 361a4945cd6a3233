"""Recipes: valid ones parse (the shipped ones included); impossible values name their field."""

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.maps.recipe import load_recipe, parse_recipe
from trimeter.paths import MAPS_DIR


def test_shipped_recipes_parse_with_the_documented_axes():
    paths = sorted((MAPS_DIR / "recipes").glob("*.toml"))
    assert len(paths) >= 3
    for path in paths:
        r = load_recipe(path)
        assert r.alpha[0] == 0 and r.alpha[-1] == pytest.approx(0.999)
        assert np.all(np.diff(np.diff(r.alpha)) < 0)        # denser near α = 1
        assert r.sigma_t[0] == pytest.approx(0.05) and r.sigma_t[-1] == pytest.approx(50)
        assert r.g[0] == 0 and r.g[-1] == pytest.approx(0.9)
        assert r.to_dict()["geometry_params"]["cover_slides"] == (r.geometry == "device")


@pytest.mark.parametrize("change, field", [
    ({"n": 0.9}, "n"),
    ({"thickness_mm": 0.0}, "thickness_mm"),
    ({"thickness_mm": "thick"}, "thickness_mm"),
    ({"reference_rho_w": -0.1}, "reference_rho_w"),
    ({"reference_rho_b": 1.5}, "reference_rho_b"),
    ({"geometry": "lab"}, "geometry"),
    ({"colour": "red"}, "colour"),
    ({"grid": {"alpha": {"max": 1.0, "count": 5}, "sigma_t": [1, 2], "g": [0, 0.5]}}, "grid.alpha"),
    ({"grid": {"alpha": [0.0, 1.2], "sigma_t": [1, 2], "g": [0, 0.5]}}, "grid.alpha"),
    ({"grid": {"alpha": [0.0, 0.5], "sigma_t": [-1, 2], "g": [0, 0.5]}}, "grid.sigma_t"),
    ({"grid": {"alpha": [0.0, 0.5], "sigma_t": [2, 1], "g": [0, 0.5]}}, "grid.sigma_t"),
    ({"grid": {"alpha": [0.0, 0.5], "sigma_t": [1, 2], "g": [0, 1.0]}}, "grid.g"),
    ({"grid": {"alpha": [0.0, 0.5], "sigma_t": [1, 2], "g": [float("nan"), 0.5]}}, "grid.g"),
    ({"grid": {"alpha": [0.0, 0.5], "sigma_t": {"min": 1, "max": 2, "count": 1}, "g": [0, 0.5]}}, "grid.sigma_t.count"),
    ({"sampling": {"target_stderr": 0}}, "sampling.target_stderr"),
    ({"sampling": {"min_paths": 65536, "max_paths": 4096}}, "sampling.max_paths"),
    ({"sampling": {"truncation": 2}}, "sampling.truncation"),
    ({"name": "a\0b"}, "name"), ({"name": "a\nb"}, "name"), ({"name": "a\\b"}, "name"), ({"name": ".."}, "name"),
    ({"name": "x" * 201}, "name"), ({"name": 5}, "name"), ({"polarisation": "yes"}, "polarisation"),
    ({"polarisation": 1}, "polarisation"),
])
def test_impossible_values_are_refused_naming_the_field(change, field, tiny_data):
    data = tiny_data()
    data.update(change)
    with pytest.raises(InputError, match=field.replace(".", r"\.")):
        parse_recipe(data)


def test_unreadable_recipe_file_is_an_input_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("n = [unclosed\n")
    with pytest.raises(InputError, match="not valid TOML"):
        load_recipe(bad)
    with pytest.raises(InputError, match="cannot read"):
        load_recipe(tmp_path / "missing.toml")


def test_g_axis_log_spacing_in_one_minus_g(tiny_data):
    data = tiny_data()
    data["grid"] = {**data["grid"], "g": {"min": 0.0, "max": 0.9, "count": 4, "spacing": "log1m"}}
    np.testing.assert_allclose(parse_recipe(data).g, [0.0, 1 - 10 ** (-1 / 3), 1 - 10 ** (-2 / 3), 0.9])
    data["grid"]["g"]["spacing"] = "cubic"
    with pytest.raises(InputError, match=r"grid\.g\.spacing"):
        parse_recipe(data)


def test_the_fingerprint_ignores_last_bit_noise_in_generated_axes_but_not_a_real_change():
    """numpy releases generate geomspace axes that differ in the last bit; a map built with one must
    still count as current under the other, while any real change of the recipe makes it stale."""
    import copy

    import numpy as np

    from trimeter.maps.builder import recipe_fingerprint
    from trimeter.maps.recipe import load_recipe
    from trimeter.paths import MAPS_DIR

    stored = load_recipe(MAPS_DIR / "recipes" / "device-n1.5-l0.4.toml").to_dict()
    noisy = copy.deepcopy(stored)
    noisy["grid"]["alpha"] = [float(np.nextafter(a, 2.0)) for a in noisy["grid"]["alpha"]]
    assert noisy != stored and recipe_fingerprint(noisy) == recipe_fingerprint(stored)
    for change in (lambda d: d["grid"]["alpha"].__setitem__(5, d["grid"]["alpha"][5] + 1e-6),
                   lambda d: d["sampling"].__setitem__("max_paths", d["sampling"]["max_paths"] * 2),
                   lambda d: d.__setitem__("thickness_mm", 0.41)):
        changed = copy.deepcopy(stored)
        change(changed)
        assert recipe_fingerprint(changed) != recipe_fingerprint(stored)


def test_polarisation_is_off_unless_asked_and_only_then_in_the_stored_recipe(tiny_data):
    """The tracer's polarisation option: off by default, and then absent from the stored recipe (so every
    map built before it keeps its fingerprint); on, stored and part of the fingerprint."""
    from trimeter.maps.builder import recipe_fingerprint

    plain = parse_recipe(tiny_data())
    assert plain.polarisation is False and "polarisation" not in plain.to_dict()
    data = tiny_data()
    data["polarisation"] = True
    polarised = parse_recipe(data)
    assert polarised.polarisation is True and polarised.to_dict()["polarisation"] is True
    assert recipe_fingerprint(polarised) != recipe_fingerprint(plain)
    data["polarisation"] = False
    assert recipe_fingerprint(parse_recipe(data)) == recipe_fingerprint(plain)


@pytest.mark.parametrize("polarisation", [False, True])
def test_the_builder_passes_the_polarisation_option_to_the_tracer(tiny_data, polarisation):
    from trimeter.forward.transport import Stack
    from trimeter.forward.transport import trace_column as traced
    from trimeter.maps.builder import trace_column

    data = tiny_data()
    data["polarisation"] = polarisation
    recipe = parse_recipe(data)
    seen = []

    def tracer(stack, sigma_t, g, n_paths, seed, k_max, **options):
        seen.append(options)
        return traced(stack, sigma_t, g, n_paths, seed, k_max, **options)

    trace_column(recipe, Stack.from_recipe("ideal", recipe.geometry_params, recipe.n, recipe.thickness_mm), 0, 0,
                 tracer)
    assert seen and all(options == ({"polarisation": True} if polarisation else {}) for options in seen)
