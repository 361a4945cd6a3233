"""The compact forward model (trimeter.model.compact): the continuous form of the map's refined model,
evaluated on the fly; checked against scipy's splines and against today's refined trilinear grid."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator, RegularGridInterpolator, make_interp_spline

from trimeter.model.compact import CompactForward


def smooth_map(na=12, ns=8, ng=5):
    """A, B, C shaped like a map's (B falling with σt·ℓ, C a reflectance) on log-spaced axes."""
    alpha = -np.expm1(-np.linspace(0.0, np.log(1000.0), na))
    log_s = np.linspace(np.log(0.05), np.log(50.0), ns)
    g = -np.expm1(-np.linspace(0.0, np.log(10.0), ng))
    a, s, gg = np.meshgrid(alpha, np.exp(log_s), g, indexing="ij")
    A = 0.5 * a * (1 - gg) * (1 - np.exp(-0.4 * s))
    B = 0.8 * np.exp(-0.4 * s * (1 - 0.6 * a))
    C = 0.1 + 0.6 * a * (1 - 0.5 * gg)
    return alpha, log_s, g, np.stack([A, B, C], axis=-1)


def scipy_reference(alpha, log_s, g, values, pa, ps, pg):
    """The definition: a not-a-knot cubic spline in α, then in ln σt, PCHIP in g, C clipped."""
    at = make_interp_spline(alpha, values, k=3, axis=0)(pa)                     # (N, ns, ng, 3)
    out = np.empty((len(pa), 3))
    for i in range(len(pa)):
        col = make_interp_spline(log_s, at[i], k=3, axis=0)(ps[i])               # (ng, 3)
        out[i] = PchipInterpolator(g, col, axis=0)(pg[i])
    out[:, 2] = np.clip(out[:, 2], 0.0, 0.999)
    return out.T


def random_points(alpha, log_s, g, n, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(alpha[0], alpha[-1], n), rng.uniform(log_s[0], log_s[-1], n), rng.uniform(g[0], g[-1], n))


@pytest.mark.parametrize("ng", [3, 4, 5, 8])  # g windows: the whole axis, and placed at its ends and inside
def test_it_is_the_tensor_spline_with_pchip_in_g_exactly(ng):
    alpha, log_s, g, values = smooth_map(ng=ng)
    model = CompactForward.from_nodes(alpha, log_s, g, values)
    pa, ps, pg = random_points(alpha, log_s, g, 300)
    value = model.evaluate(pa, ps, pg)[0]
    assert np.abs(value - scipy_reference(alpha, log_s, g, values, pa, ps, pg)).max() < 1e-12
    assert np.abs(model.nodes() - values).max() < 1e-12


def test_its_derivatives_are_those_of_its_values():
    alpha, log_s, g, values = smooth_map()
    model = CompactForward.from_nodes(alpha, log_s, g, values)
    pa, ps, pg = random_points(alpha, log_s, g, 500, seed=1)
    pa, pg = np.minimum(pa, alpha[-1] - 1e-5), np.minimum(pg, g[-1] - 1e-5)  # room for the forward difference
    value, d_a, d_s, d_g = model.evaluate(pa, ps, pg)
    h = 1e-7
    for d, moved in ((d_a, (pa + h, ps, pg)), (d_s, (pa, ps + h, pg)), (d_g, (pa, ps, pg + h))):
        numeric = (model.evaluate(*moved)[0] - value) / h
        assert np.abs(numeric - d).max() < 1e-4 * (1 + np.abs(d).max())


def test_it_clamps_points_to_the_box():
    alpha, log_s, g, values = smooth_map()
    model = CompactForward.from_nodes(alpha, log_s, g, values)
    inside = model.evaluate([alpha[-1]], [log_s[0]], [g[0]])[0]
    outside = model.evaluate([1.5], [log_s[0] - 3], [-0.5])[0]
    assert np.array_equal(inside, outside)


def test_it_refuses_coefficients_that_do_not_match_the_axes():
    alpha, log_s, g, values = smooth_map()
    with pytest.raises(ValueError, match="do not match"):
        CompactForward(alpha, log_s, g, np.zeros((len(g), len(alpha), len(log_s) + 1, 3)))


def refined_trilinear(alpha, log_s, g, values):
    """Today's model between the nodes (ForwardGrid.between_nodes): the axes refined (α ×2, ln σt to
    ~121 nodes, g ×2) by the same splines, then trilinear."""
    def refine(x, factor):
        return np.interp(np.linspace(0, len(x) - 1, (len(x) - 1) * factor + 1), np.arange(len(x)), x)

    ra, rs, rg = refine(alpha, 2), refine(log_s, max(1, round(120 / (len(log_s) - 1)))), refine(g, 2)
    v = make_interp_spline(alpha, values, k=3, axis=0)(ra)
    v = make_interp_spline(log_s, v, k=3, axis=1)(rs)
    v = PchipInterpolator(g, v, axis=2)(rg)
    v[..., 2] = np.clip(v[..., 2], 0.0, 0.999)
    return RegularGridInterpolator((ra, rs, rg), v)


def test_on_the_shipped_map_it_stays_within_the_refined_grids_own_error():
    """The compact model and today's refined trilinear grid differ by that grid's cell error only: the
    bounds are about twice their difference on device-n1.5-l0.4, which trilinear interpolation on the
    raw nodes (the device's model before this table) exceeds several times over."""
    from trimeter.formats.appearance import AppearanceMap, find_map

    amap = AppearanceMap.load(find_map("device-n1.5-l0.4"))
    # copies: a container's arrays can be unaligned, which scipy refuses
    alpha, log_s, g = np.array(amap.alpha, float), np.log(np.array(amap.sigma_t, float)), np.array(amap.g, float)
    values = np.stack([amap.A, amap.B, amap.C], axis=-1).astype(float)
    model = CompactForward.from_nodes(alpha, log_s, g, values)
    pa, ps, pg = random_points(alpha, log_s, g, 5000, seed=2)
    diff = np.abs(model.evaluate(pa, ps, pg)[0] - refined_trilinear(alpha, log_s, g, values)((pa, ps, pg)).T)
    assert np.percentile(diff, 95) < 1e-3
    assert diff.max() < 3e-3
