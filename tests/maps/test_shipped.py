"""The shipped maps: present, ≤ 5 MB, built from their recipe as it stands, physically sane, and their
interpolation error at off-grid points measured against independent references:
- ideal: Prahl's adding-doubling (iadpython, quad_pts = 32) at 40 random off-grid materials;
- device: direct volpath renders of the forward scene (black panels, see test_tracer) — slow.
Run with -s to see the figures."""

import math

import numpy as np
import pytest

from trimeter.formats.appearance import AppearanceMap, shipped_maps
from trimeter.maps.builder import recipe_fingerprint, validation_report
from trimeter.maps.recipe import load_recipe
from trimeter.paths import MAPS_DIR

from maps_direct_render import render_black_panels

SHIPPED = ("ideal-n1.5-l0.5", "device-n1.5-l0.4", "device-n1.5-l0.8")


def load(name):
    path = MAPS_DIR / f"{name}.tmap"
    if not path.exists():
        pytest.fail(f"shipped map {path} is missing: trimeter map build maps/recipes/{name}.toml --out {path}")
    return AppearanceMap.load(path)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_map_is_current_small_and_sane(name):
    amap = load(name)
    assert amap.path.stat().st_size <= 5e6
    recipe = load_recipe(MAPS_DIR / "recipes" / f"{name}.toml")
    # the recipe the map was built from (stored in it) against the recipe file and geometry as they are now
    assert recipe_fingerprint(amap.recipe) == recipe_fingerprint(recipe), "map is stale: rebuild it"
    report = validation_report(amap)
    assert report["energy_ok"] and report["I_b_le_I_w"] and report["g_no_effect_at_alpha0"], report
    assert amap.provenance["truncation"]["max_error_bound"] < 1e-4
    print(f"\n{name}: {amap.path.stat().st_size / 1e6:.2f} MB, trace {amap.provenance['trace_seconds']:.0f} s, "
          f"std-error median {amap.info()['mc_stderr']['median']:.1e} max {amap.info()['mc_stderr']['max']:.1e}")


@pytest.mark.parametrize("name", [n for n in SHIPPED if n.startswith("device")])
def test_device_maps_ship_their_inscattering_table(name):
    """Each device map has its in-scattering table (`trimeter map inscatter`), traced for its n, ℓ and
    the instrument's geometry as it stands (AppearanceMap.inscatter refuses one that is not), and
    sane: no light at α = 0 or σt = 0, more of it as α, σt and g grow."""
    amap = load(name)
    table = amap.inscatter
    assert table is not None, f"missing: trimeter map inscatter {name}"
    L = table.L
    assert np.all(L[0] == 0) and np.all(L[:, 0] == 0)
    assert np.all(np.diff(L[:, 1:], axis=0) >= 0) and np.all(np.diff(L[-1], axis=0) > 0)
    assert L[-1, -1, -1] > L[-1, -1, 0]
    assert amap.path.with_suffix(".tins").stat().st_size < 100_000


def test_map_list_names_the_shipped_maps():
    assert {p.stem for p in shipped_maps()} >= set(SHIPPED)


def off_grid_points(amap, count, seed):
    rng = np.random.default_rng(seed)
    pts = []
    while len(pts) < count:
        i, j, k = (int(rng.integers(len(ax) - 1)) for ax in (amap.alpha, amap.sigma_t, amap.g))
        t = rng.uniform(0.2, 0.8, 3)      # strictly inside a cell
        pts.append((amap.alpha[i] + t[0] * (amap.alpha[i + 1] - amap.alpha[i]),
                    math.exp(math.log(amap.sigma_t[j]) + t[1] * math.log(amap.sigma_t[j + 1] / amap.sigma_t[j])),
                    amap.g[k] + t[2] * (amap.g[k + 1] - amap.g[k])))
    return pts


def test_ideal_map_interpolation_error_against_adding_doubling():
    pytest.importorskip("iadpython")
    from trimeter.forward.validate import iad_reflectance

    amap = load("ideal-n1.5-l0.5")
    abs_err, rel_err = [], []
    for alpha, sigma_t, g in off_grid_points(amap, 40, 1):
        for rho in (0.02, 0.9):
            ref = float(iad_reflectance(alpha, sigma_t, g, 1.5, 0.5, rho))
            got = float(amap.diffuse(alpha, sigma_t, g, rho))
            abs_err.append(abs(got - ref))
            rel_err.append(abs(got - ref) / ref)
    print(f"\nideal map vs adding-doubling at 40 off-grid materials × 2 ρ: |ΔI| median {np.median(abs_err):.1e} "
          f"max {np.max(abs_err):.1e}; relative median {np.median(rel_err):.2%} max {np.max(rel_err):.2%}")
    assert np.median(rel_err) < 0.01
    assert np.max(abs_err) < 0.03


@pytest.mark.slow
@pytest.mark.parametrize("name, ell", [("device-n1.5-l0.4", 0.4), ("device-n1.5-l0.8", 0.8)])
def test_device_map_interpolation_error_against_direct_renders(name, ell):
    amap = load(name)
    for alpha, sigma_t, g in off_grid_points(amap, 2, 5):
        got = float(amap.diffuse(alpha, sigma_t, g, 0.9))
        ref, s = render_black_panels("device", alpha, sigma_t, g, 1.5, ell, 0.9, spp=1 << 18)
        print(f"\n{name} α={alpha:.4f} σt={sigma_t:.3g} g={g:.2f} ρ=0.9: map {got:.4f}, direct {ref:.4f} ± {s:.4f}")
        assert abs(got - ref) < 4 * s + 0.02 * ref


@pytest.mark.parametrize("path", sorted(MAPS_DIR.glob("*.onnx")), ids=lambda p: p.name)
def test_shipped_models_have_no_subnormal_weights(path):
    """Subnormal float32 weights put onnxruntime's CPU kernels on the processor's slow path (4× the time)."""
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    from trimeter.maps.mlp_training import flush_subnormals

    for init in onnx.load(str(path)).graph.initializer:
        weights = numpy_helper.to_array(init)
        np.testing.assert_array_equal(weights, flush_subnormals(weights), err_msg=f"{path.name}: {init.name}")


def _float32_ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How many float32 steps apart a and b are, element by element (across zero too)."""
    def ordered(x):
        i = np.float32(x).view(np.int32).astype(np.int64)
        return np.where(i < 0, -(i & 0x7FFFFFFF), i)
    return np.abs(ordered(a) - ordered(b))


# How far a re-trace may land from the stored column: on the CPU that traced the map, bit for bit; on
# another, numpy's and the JIT's SIMD code (chosen by CPU) may round a few sums differently (maps/README,
# "Deterministic", says by how much). A moved path moves a column by its Monte Carlo error, ~1e-4 of
# it: about a thousand steps.
RETRACE_ULPS = {"A": 8, "B": 8, "C": 8, "std_b": 64, "std_w": 64}


@pytest.mark.parametrize("name, j, k", [("ideal-n1.5-l0.5", 12, 5), ("ideal-n1.5-l0.5", 0, 9),
                                        ("device-n1.5-l0.4", 8, 3)])
def test_shipped_map_columns_re_trace_to_the_stored_values(name, j, k):
    """The tracer as it stands re-traces shipped columns of both geometries to the stored values (A, B, C
    and their std-errors, float32 as the map stores them; within RETRACE_ULPS steps, which only another
    CPU's rounding uses): a change that moves any path shows here."""
    from trimeter.maps.builder import trace_column
    from trimeter.forward.transport import Stack

    amap = load(name)
    recipe = load_recipe(MAPS_DIR / "recipes" / f"{name}.toml")
    stack = Stack.from_recipe(recipe.geometry, recipe.geometry_params, recipe.n, recipe.thickness_mm)
    col = trace_column(recipe, stack, j, k)
    for field, limit in RETRACE_ULPS.items():
        got, stored = getattr(col, field), getattr(amap, field)[:, j, k]
        ulps = _float32_ulps(got, stored)
        assert ulps.max() <= limit, (f"{name} column (σt index {j}, g index {k}): {field} is {ulps.max()} float32 "
                                     f"steps from the stored value at row {int(ulps.argmax())} "
                                     f"({float(np.float32(got[ulps.argmax()]))} against "
                                     f"{float(np.float32(stored[ulps.argmax()]))}; at most {limit})")


def test_float32_steps_count_across_zero():
    x = np.float32(1.0)
    assert _float32_ulps(np.array([x]), np.array([np.nextafter(x, np.float32(2))])).tolist() == [1]
    tiny = np.float32(1e-45)  # the smallest subnormal: one step either side of +0
    assert _float32_ulps(np.array([-tiny]), np.array([tiny])).tolist() == [2]
    assert _float32_ulps(np.array([0.5]), np.array([0.5 * (1 + 1e-4)]))[0] > 500  # a Monte Carlo-sized move
