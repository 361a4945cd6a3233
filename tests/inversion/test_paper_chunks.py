"""The paper method works through the bins in chunks (bounded memory): the chunk size changes nothing."""

import numpy as np

from trimeter.inversion.paper import paper_medians, paper_samples


def _inputs(amap, n, seed):
    rng = np.random.default_rng(seed)
    alpha, g = rng.uniform(0.3, 0.95, n), rng.uniform(0, 0.8, n)
    sigma_t = np.exp(rng.uniform(np.log(0.5), np.log(20), n))
    rho_b, rho_w = np.where(np.arange(n) % 2, 0.02, 0.05), np.where(np.arange(n) % 3, 0.99, 0.9)
    I_b, I_w, I_c = amap.query(alpha, sigma_t, g, rho_b, rho_w)
    I_b[5] = np.nan  # an unusable bin stays NaN and still takes its place in the ε-stream
    return I_b, I_w, I_c, rho_b, rho_w


def test_chunk_size_does_not_change_the_medians(ideal_map, thick_map):
    maps = [ideal_map, thick_map]
    inputs = [_inputs(m, 13, seed=1) for m in maps]  # 13 bins: chunks of 1, of 5 (5+5+3) and of 11 (11+2)
    whole = paper_medians(maps, inputs, samples=16, seed=4, chunk_points=10**9)
    for chunk_points in (1, 16 * 2 * 5, 16 * 2 * 11):  # one bin per chunk, 5 and 11 bins per chunk
        chunked = paper_medians(maps, inputs, samples=16, seed=4, chunk_points=chunk_points)
        np.testing.assert_array_equal(chunked[0], whole[0])
        for a, b in zip(chunked[1], whole[1], strict=True):
            np.testing.assert_array_equal(a, b)
    assert np.isnan(whole[1][0][5]).all() and np.isfinite(whole[0][:5]).all()


def test_a_bins_samples_do_not_depend_on_where_the_chunk_starts(ideal_map):
    I_b, I_w, I_c, rho_b, rho_w = _inputs(ideal_map, 20, seed=2)
    full = paper_samples(ideal_map, I_b, I_w, I_c, rho_b, rho_w, samples=8, seed=3)
    tail = paper_samples(ideal_map, I_b[12:], I_w[12:], I_c[12:], rho_b[12:], rho_w[12:], samples=8, seed=3,
                         first_row=12)
    np.testing.assert_array_equal(tail, full[12:])


def test_the_triangulation_cost_counts_each_distinct_background_pair_once():
    from types import SimpleNamespace

    from trimeter.inversion.paper import triangulated_nodes

    amap = SimpleNamespace(alpha=np.zeros(4), sigma_t=np.zeros(5), g=np.zeros(3))
    rho_b = np.array([0.03, 0.0301, 0.0312, 0.05, np.nan])  # the first two round to one pair; NaN: no pair
    rho_w = np.full(5, 0.99)
    assert triangulated_nodes(amap, rho_b, rho_w) == 3 * 60
