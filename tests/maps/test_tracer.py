"""The (k, m)-tally tracer: the polynomial bookkeeping, physical limits, the independent
adding-doubling solution (ideal geometry), determinism, and direct Mitsuba renders (slow).

iadpython needs quad_pts ≥ 32 here: with its default quadrature URU/UTU (the diffuse terms B, C)
are off by ~3 % for n = 1.5 (checked against direct numerical integration of the α = 0 slab)."""

import dataclasses
import math

import numpy as np
import pytest

from trimeter.forward.validate import iad_reflectance

from trimeter.geometry import load_geometry
from trimeter.errors import InputError
from trimeter.forward.transport import ColumnTally, Stack, Tally, k_max_for, resolve_backend
from trimeter.forward.transport.tally import detector_sums
from trimeter.model.response import background_response
from trimeter.forward.transport import trace_column as trace

from maps_direct_render import render_black_panels

N, ELL = 1.5, 0.5
K_MAX = k_max_for(0.999, 1e-5)


@pytest.fixture(scope="module")
def ideal():
    return Stack.from_recipe("ideal", load_geometry("ideal"), N, ELL)


def adding_doubling(alpha, sigma_t, g, rho, n=N, ell=ELL):
    pytest.importorskip("iadpython")
    return iad_reflectance(alpha, sigma_t, g, n, ell, rho)


def test_polynomial_bookkeeping_equals_per_path_sums():
    """A = c0(α), B = c1(α), C = returned-from-below(α) and the std-error of I(ρ) equal the explicit
    per-path computation (each detector path contributes once; C's error propagated)."""
    rng = np.random.default_rng(1)
    n_paths, n_below = 500, 300
    k = rng.integers(0, 40, n_paths)
    m = rng.integers(0, 3, n_paths)          # m = 2: stopped at the 2nd background hit, contributes nothing
    hit = rng.random(n_paths) < 0.7
    sel = hit & (m < 2)
    counts = np.zeros((2, 40))
    np.add.at(counts, (m[sel], k[sel]), 1.0)
    kb = rng.integers(0, 30, n_below)
    back = rng.random(n_below) < 0.3
    below = Tally(counts=np.bincount(kb[back], minlength=1)[None, :].astype(float), n_paths=n_below, weight=1.0,
                  specular=0.0, truncated=0, k_max=100)
    tally = ColumnTally(Tally(counts=counts, n_paths=n_paths, weight=0.8, specular=0.04, truncated=0, k_max=100),
                        below)
    alpha, rho = np.array([0.0, 0.3, 0.95]), 0.7
    A, B, C = tally.abc(alpha)
    powers = alpha[None, :] ** k[:, None]
    np.testing.assert_allclose(A, 0.04 + 0.8 * np.mean(np.where((sel & (m == 0))[:, None], powers, 0), axis=0))
    np.testing.assert_allclose(B, 0.8 * np.mean(np.where((sel & (m == 1))[:, None], powers, 0), axis=0))
    per_below = np.where(back[:, None], alpha[None, :] ** kb[:, None], 0.0)
    np.testing.assert_allclose(C, per_below.mean(axis=0))
    q = rho / (1 - C * rho)
    per_path = 0.8 * np.where(sel[:, None], powers * np.where(m[:, None] == 0, 1.0, q[None, :]), 0.0)
    var = per_path.var(axis=0, ddof=1) / n_paths + (B * q * q) ** 2 * per_below.var(axis=0, ddof=1) / n_below
    np.testing.assert_allclose(tally.stderr(alpha, rho), np.sqrt(var), rtol=1e-10)


@pytest.mark.parametrize("averaged", [False, True])
def test_next_event_sums_equal_per_path_values(averaged):
    """A detector path's value is v·α^k₁·q (its next-event estimate at the first background bounce) +
    h·α^k·q^m (its own way to the light: 1/0, or the rotation average); traced on to a 3rd bounce, also
    + v₂·α^k₂·q² (the estimate at the 2nd). The tallies' mean and second moment at any (α, q) equal the
    explicit per-path ones."""
    rng = np.random.default_rng(7)
    n = 400
    nee_k = rng.integers(0, 12, n)
    nee_value = np.where(rng.random(n) < 0.6, rng.uniform(0.0, 2.0, n), 0.0)
    m = np.where(nee_value > 0, np.where(rng.random(n) < 0.5, 1, 2), rng.integers(0, 3, n))
    k = np.where(m >= 1, nee_k + rng.integers(0, 5, n), rng.integers(0, 12, n))
    hit = rng.random(n) < 0.5
    if averaged:  # a share of the paths seen from 1…32 of their turned copies
        hit = np.where(hit, rng.integers(1, 33, n) / 32, 0.0).astype(np.float32)
    alpha, q = np.array([0.0, 0.4, 0.97]), 0.8
    # a 2nd bounce's estimate: only paths that bounced twice, after at least their first's scatterings;
    # given as those paths only (a sparse term), and another sparse one on a few of every path (as the
    # returns' control variate adds), so that every kind of pair of terms is summed
    m3 = np.where((m == 2) & (rng.random(n) < 0.5), 3, m)
    twice = np.flatnonzero(m3 >= 2)
    k2, value2 = nee_k[twice] + rng.integers(0, 3, len(twice)), rng.uniform(0.0, 2.0, len(twice))
    few = np.flatnonzero(rng.random(n) < 0.1)
    every = np.arange(n)
    for orders, m_of, terms in ((2, m, [(every, nee_k, nee_value, 1)]),
                                (3, m3, [(every, nee_k, nee_value, 1), (twice, k2, value2, 2),
                                         (few, nee_k[few], rng.uniform(0.0, 1.0, len(few)), 2)])):
        own = (every, k, np.where(m_of < orders, hit, 0.0), m_of)
        counts, second = detector_sums(n, [own, *terms], orders)
        tally = Tally(counts=counts, n_paths=n, weight=0.7, specular=0.0, truncated=0, k_max=100, second=second)
        value = np.zeros((n, len(alpha)))
        for paths, kj, v, r in [own, *terms]:
            r = np.broadcast_to(r, np.shape(paths))
            value[paths] += 0.7 * np.asarray(v, dtype=float)[:, None] * alpha ** kj[:, None] * q ** r[:, None]
        first, second_moments = tally._moments(alpha)
        np.testing.assert_allclose(sum(first[r] * q**r for r in range(orders)), value.mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(sum(second_moments[p] * q**p for p in range(2 * orders - 1)),
                                   (value**2).mean(axis=0), rtol=1e-12)


def test_backend_llvm_runs_and_cuda_without_a_gpu_is_a_clear_error(ideal):
    import drjit as dr

    assert resolve_backend("llvm") == "llvm"
    tally = trace(ideal, 1.0, 0.5, 4096, 3, K_MAX, backend=resolve_backend("llvm"))
    assert tally.n_paths == 4096 and tally.above.counts.sum() > 0
    with pytest.raises(InputError, match="backend"):
        resolve_backend("gpu")
    if dr.has_backend(dr.JitBackend.CUDA):
        assert resolve_backend("auto") == "cuda"
    else:
        assert resolve_backend("auto") == "llvm"
        with pytest.raises(InputError, match="no CUDA device"):
            resolve_backend("cuda")


def test_alpha_zero_is_beer_lambert_with_fresnel_and_g_has_no_effect(ideal):
    """At α = 0 only unscattered light remains: A is the Fresnel slab's specular reflectance and
    B = T(normal)·∫2μ T(μ)dμ (Beer-Lambert along each slant path); paths with k = 0 never sample the
    phase function, so with the same seed every g gives the identical α = 0 tally (a fixed share of
    background paths: the default one depends on the error at α > 0, and so on g)."""
    sigma_t = 1.0
    t0 = trace(ideal, sigma_t, 0.0, 1 << 17, 5, K_MAX, below_fraction=1.0)
    t9 = trace(ideal, sigma_t, 0.9, 1 << 17, 5, K_MAX, below_fraction=1.0)
    np.testing.assert_array_equal(t0.above.orders([0.0]), t9.above.orders([0.0]))
    np.testing.assert_array_equal(t0.below.orders([0.0]), t9.below.orders([0.0]))

    def fresnel(mu, n):
        sin2 = (1 - mu * mu) / (n * n)
        ct = np.sqrt(np.clip(1 - sin2, 0, None))
        rs, rp = (mu - n * ct) / (mu + n * ct), (n * mu - ct) / (n * mu + ct)
        return np.where(sin2 >= 1, 1.0, 0.5 * (rs * rs + rp * rp)), ct

    mu = (np.arange(100000) + 0.5) / 100000
    r, mu_in = fresnel(mu, N)
    t = np.exp(-sigma_t * ELL / mu_in)
    slab_t = (1 - r) ** 2 * t / (1 - r * r * t * t)
    r0, t_n = r[-1], np.exp(-sigma_t * ELL)
    A_exact = r0 + (1 - r0) ** 2 * r0 * t_n**2 / (1 - r0**2 * t_n**2)
    B_exact = (1 - r0) ** 2 * t_n / (1 - r0**2 * t_n**2) * np.mean(2 * mu * slab_t)
    A, B, _ = t0.abc([0.0])
    sd = t0.stderr([0.0], 1.0)[0]
    assert abs(A[0] - A_exact) < 4 * sd + 1e-9
    assert abs(B[0] - B_exact) < 4 * sd


def test_same_seed_same_tally_other_seed_other_tally(ideal):
    a = trace(ideal, 3.0, 0.5, 1 << 15, 11, K_MAX)
    b = trace(ideal, 3.0, 0.5, 1 << 15, 11, K_MAX)
    c = trace(ideal, 3.0, 0.5, 1 << 15, 12, K_MAX)
    np.testing.assert_array_equal(a.above.counts, b.above.counts)
    np.testing.assert_array_equal(a.below.counts, b.below.counts)
    assert not np.array_equal(a.above.counts, c.above.counts)


@pytest.mark.parametrize("geometry, ell, from_below", [("device", 0.4, False), ("device", 0.4, True),
                                                      ("ideal", 0.5, False)])
def test_tally_does_not_depend_on_the_wave_length(geometry, ell, from_below):
    """Waves only decide when finished paths are dropped and their records copied out (the first
    wave copies every lane, later ones scatter the live lanes): one long wave, the default and
    three-iteration waves record the same paths."""
    from trimeter.forward.transport.trace import trace as trace_one

    stack = Stack.from_recipe(geometry, load_geometry(geometry), N, ell)
    tallies = [trace_one(stack, 5.0, 0.6, 4096, 3, K_MAX, wave=wave, from_below=from_below)
               for wave in (100_000, 48, 3)]
    for other in tallies[1:]:
        np.testing.assert_array_equal(other.counts, tallies[0].counts)
        np.testing.assert_array_equal(other.second, tallies[0].second)
        assert other.path_events == tallies[0].path_events


def test_large_traces_run_in_chunks_that_keep_small_traces_unchanged(ideal, monkeypatch):
    """Memory: a request above TRACE_CHUNK paths is traced chunk by chunk and summed; a request of
    at most one chunk is bit for bit what it was (the shipped maps' first batches), and the chunked
    sum agrees with one unchunked trace of the same size within the MC error."""
    from trimeter.forward.transport import column

    whole = trace(ideal, 3.0, 0.5, 3 * 8192 + 100, 11, K_MAX)
    small = trace(ideal, 3.0, 0.5, 8192, 11, K_MAX)
    monkeypatch.setattr(column, "TRACE_CHUNK", 8192)
    np.testing.assert_array_equal(trace(ideal, 3.0, 0.5, 8192, 11, K_MAX).above.counts, small.above.counts)
    chunked = trace(ideal, 3.0, 0.5, 3 * 8192 + 100, 11, K_MAX)
    assert chunked.n_paths == whole.n_paths == 3 * 8192 + 100
    assert not np.array_equal(chunked.above.counts, whole.above.counts)  # other seeds past chunk 0
    alpha = np.array([0.3, 0.9, 0.99])
    for rho in (0.02, 0.9):
        i_whole = whole.abc(alpha)[0] + whole.abc(alpha)[1] * rho / (1 - whole.abc(alpha)[2] * rho)
        i_chunk = chunked.abc(alpha)[0] + chunked.abc(alpha)[1] * rho / (1 - chunked.abc(alpha)[2] * rho)
        assert np.all(np.abs(i_whole - i_chunk) < 5 * np.hypot(whole.stderr(alpha, rho), chunked.stderr(alpha, rho)))


def test_one_trace_per_column_matches_adding_doubling_for_every_alpha_and_rho(ideal):
    """The issue's criterion (≥ 30 random materials, median < 0.5 %) — here 6 random (σt, g) columns ×
    5 α × 3 ρ = 90 materials, each column traced once, and every value within MC error."""
    rng = np.random.default_rng(2022)
    rel, zs = [], []
    for col in range(6):
        sigma_t = float(np.exp(rng.uniform(np.log(0.05), np.log(20))))
        g = float(rng.uniform(0, 0.9))
        tally = trace(ideal, sigma_t, g, 1 << 16, 100 + col, K_MAX)
        alphas = np.sort(np.concatenate([[0.0], 1 - 10 ** rng.uniform(-3, 0, 4)]))
        A, B, C = tally.abc(alphas)
        for rho in (0.02, 0.5, 0.9):
            I = A + B * rho / (1 - C * rho)
            sd = tally.stderr(alphas, rho)
            for a, i_mc, s in zip(alphas, I, sd, strict=True):
                ref = adding_doubling(a, sigma_t, g, rho)
                rel.append(abs(i_mc - ref) / ref)
                zs.append((i_mc - ref) / math.hypot(s, 2e-4))   # 2e-4: iadpython's own quadrature error
    print(f"\ntracer vs adding-doubling, {len(rel)} materials: relative error median {np.median(rel):.3%}, "
          f"max {np.max(rel):.3%}; max |z| {np.max(np.abs(zs)):.2f}")
    assert len(rel) >= 30
    assert np.median(rel) < 0.005, f"median relative error {np.median(rel):.4f}"
    assert np.max(np.abs(zs)) < 4.5, f"max |z| {np.max(np.abs(zs)):.2f}"


@pytest.mark.slow
@pytest.mark.parametrize("geometry, ell, sigma_t, g, alpha, rho", [
    ("ideal", 0.5, 0.3, 0.2, 0.97, 0.9),
    ("ideal", 0.5, 4.0, 0.7, 0.995, 0.02),
    ("device", 0.4, 0.5, 0.0, 0.0, 0.9),
    ("device", 0.8, 3.0, 0.6, 0.99, 0.5),     # ρ = 0.5: not a reference background (checks the ρ model)
])
def test_tracer_equals_direct_render_within_mc_error(geometry, ell, sigma_t, g, alpha, rho):
    stack = Stack.from_recipe(geometry, load_geometry(geometry), N, ell)
    tally = trace(stack, sigma_t, g, 1 << 19, 9, K_MAX)
    A, B, C = tally.abc([alpha])
    I = float(A[0] + B[0] * rho / (1 - C[0] * rho))
    s = float(tally.stderr([alpha], rho)[0])
    I_ref, s_ref = render_black_panels(geometry, alpha, sigma_t, g, N, ell, rho, spp=1 << 18)
    z = (I - I_ref) / math.hypot(s, s_ref)
    assert abs(z) < 4, f"tracer {I:.5f}±{s:.5f} vs volpath {I_ref:.5f}±{s_ref:.5f} (z = {z:.2f})"


def test_light_leaving_a_side_face_downward_reaches_the_backgrounds_rim():
    """Light trapped in a thin, weakly scattering device sample leaves through the stack's side faces;
    what heads down lands on the background's rim outside the stack's footprint and comes back. So a
    background wider than the stack must raise B and C over one exactly as wide (same seed: the same
    paths up to their side exit, so the difference is far above the MC noise)."""
    device = Stack.from_recipe("device", load_geometry("device"), N, 0.8)
    assert device.background_half_width > device.stack_half_width
    flush = dataclasses.replace(device, background_half_width=device.stack_half_width)
    A_rim, B_rim, C_rim = trace(device, 0.09, 0.66, 1 << 18, 3, K_MAX).abc([0.98])
    A_flush, B_flush, C_flush = trace(flush, 0.09, 0.66, 1 << 18, 3, K_MAX).abc([0.98])
    assert A_rim[0] == pytest.approx(A_flush[0], abs=1e-9)     # A never meets the background
    assert B_rim[0] - B_flush[0] > 0.003, (B_rim, B_flush)
    assert C_rim[0] - C_flush[0] > 0.005, (C_rim, C_flush)


def test_a_ray_rising_from_the_rim_meets_the_stacks_side_face_only_where_it_is():
    """The stack 40 mm wide and 1.1 mm tall, the rim 0.5 mm below its back face: a ray from the rim
    towards the far panel enters the near side face; one steep enough passes over the top, one flat
    enough passes under the back face (it meets the bottom face instead), one heading away or from
    under the footprint meets nothing; the y faces likewise; a corner is entered through one face."""
    from trimeter.forward.transport.backend import load_drjit
    from trimeter.forward.transport.scene import side_entry

    dr, B = load_drjit("llvm")
    W, bottom, top, z0 = 20.0, 0.0, 1.1, -0.5
    s2 = math.sqrt(0.5)
    rays = [  # (x, y, dx, dy, dz): expected (meets x, meets y, distance or None)
        ((21.0, 0.0, -s2, 0.0, s2), (True, False, 1.0 / s2)),          # 45° towards the stack: z = 0.5 at x = 20
        ((20.2, 0.0, -0.1, 0.0, math.sqrt(0.99)), (False, False, None)),  # steep: over the top (z 1.49 at x = 20)
        ((20.4, 0.0, -0.99, 0.0, math.sqrt(1 - 0.99**2)), (False, False, None)),  # flat: under the back face
        ((21.0, 0.0, s2, 0.0, s2), (False, False, None)),               # heading away
        ((10.0, 0.0, s2, 0.0, s2), (False, False, None)),               # from under the footprint
        ((5.0, -21.0, 0.0, s2, s2), (False, True, 1.0 / s2)),           # the −y face
        ((5.0, 22.0, 0.0, -s2, s2), (False, False, None)),              # −y heading, z 1.5 at y = 20: over the top
        ((21.0, 20.5, -0.6, -0.6, math.sqrt(0.28)), (True, False, 1 / 0.6)),  # corner: at x = 20, y = 19.5, z 0.38
    ]
    cols = list(zip(*[r for r, _ in rays], strict=True))
    px, py, dx, dy, dz = (B.Float(c) for c in cols)
    meets_x, meets_y, dist = side_entry(dr, W, bottom, top, px, py, B.Float([z0] * len(rays)), dx, dy, dz)
    meets_x, meets_y, dist = (np.asarray(v) for v in (meets_x, meets_y, dist))
    for i, (_, (ex, ey, ed)) in enumerate(rays):
        assert (bool(meets_x[i]), bool(meets_y[i])) == (ex, ey), (i, rays[i])
        if ed is not None:
            assert dist[i] == pytest.approx(ed, rel=1e-5), (i, dist[i])


@pytest.mark.parametrize("orders", [2, 4])
def test_next_event_estimate_and_a_paths_own_way_out_count_the_rims_light_once(orders):
    """A thick (6 mm), clear sample over a wide (120 mm) background: much of I comes from light that TIR
    carries to the side faces, down onto the rim, and back up past (or into) the stack. The next-event
    estimate at a bounce counts the straight ways to a panel and the path itself the others; tracing
    without the estimates (each path counting its own way out) must give the same A and B, and, traced
    on to 4 bounces (an estimate at each), the same bounce series. A way counted by both, or by neither,
    shows up here, e.g. a next-event estimate that lets rim rays through the side faces while the paths
    enter them (a thinner stack over a narrower rim is too weak to tell)."""
    from trimeter.forward.transport.tally import detector_path_variance
    from trimeter.forward.transport.trace import trace as trace_paths

    params = {**load_geometry("device"), "background_width_mm": 120.0}
    stack = Stack.from_recipe("device", params, N, 6.0)
    alpha, q = 0.99, (0.9 / (1 - 0.2 * 0.9) if orders == 2 else 0.9)
    values, variances = [], []
    for seed, next_event in ((11, True), (12, False)):
        tally = trace_paths(stack, 0.1, 0.0, 1 << 21, seed, K_MAX, control_variates=False, next_event=next_event,
                            background_orders=orders)
        c = tally.orders([alpha])
        assert len(c) == orders
        values.append(float(sum(c[r][0] * q**r for r in range(orders))))
        variances.append(float(detector_path_variance(tally, [alpha], q)[0]) / (tally.n_paths - 1))
    z = (values[0] - values[1]) / math.sqrt(sum(variances))
    assert abs(z) < 4, f"with next-event estimate {values[0]:.5f}, without {values[1]:.5f} (z = {z:.2f})"


def test_a_bounce_series_keeps_A_and_B_and_matches_C_at_the_white():
    """background_orders = 6: the detector paths' rows m = 0, 1 are what they are when the paths stop
    at their 2nd bounce, bit for bit, and no background paths are traced; C is the one that makes the
    model equal the series at the white it is matched at (0.9, or 0.99 when asked), with the series'
    std-error, and the model stays within a std-error of the series elsewhere (a clear 0.8 mm sample,
    where the single C of background paths is high on white). A column with two
    orders has no series; fewer than two orders, or more in a factorised column, are refused, and so
    are a white outside (0, 1] and sums of different kinds of column."""
    device = Stack.from_recipe("device", load_geometry("device"), N, 0.8)
    two = trace(device, 0.058, 0.5, 1 << 19, 3, K_MAX)
    six = trace(device, 0.058, 0.5, 1 << 19, 3, K_MAX, background_orders=6)
    width = two.above.counts.shape[1]
    assert six.above.counts.shape[0] == 6 and six.below is None
    assert np.array_equal(six.above.counts[:2, :width], two.above.counts)
    assert not six.above.counts[:2, width:].any()
    assert six.above.counts[2:].sum() > 0
    alpha = np.array([0.5, 0.97])
    for white, column in ((0.9, six), (0.99, trace(device, 0.058, 0.5, 1 << 19, 3, K_MAX, background_orders=6,
                                                   white_rho=0.99))):
        A, B, C = column.abc(alpha)
        for rho in (0.5, 0.9, 0.99):
            value, error = column.bounce_series(alpha, rho)
            model = background_response(A, B, C, rho)
            assert np.all(error > 0) and np.all(error < 0.005)
            np.testing.assert_array_equal(column.stderr(alpha, rho), error)
            if rho == white:
                np.testing.assert_allclose(model, value, rtol=1e-12)
            else:
                assert np.all(np.abs(model - value) < error), (white, rho, model, value)
    with pytest.raises(ValueError):
        two.bounce_series(alpha, 0.9)
    with pytest.raises(ValueError, match="different kinds"):
        six += two
    with pytest.raises(InputError):
        trace(device, 0.058, 0.5, 1 << 12, 3, K_MAX, background_orders=1)
    with pytest.raises(InputError, match="white_rho"):
        trace(device, 0.058, 0.5, 1 << 12, 3, K_MAX, background_orders=6, white_rho=0.0)
    with pytest.raises(InputError, match="below_fraction"):
        trace(device, 0.058, 0.5, 1 << 12, 3, K_MAX, background_orders=6, below_fraction=0.5)


def test_a_bounce_series_control_variate_predicts_the_returns_it_replaces(monkeypatch):
    """The bounce series' control variate replaces the next-event estimate at a path's second bounce,
    when the path came back from its first by one Fresnel reflection and nothing else, by its
    expectation given the first bounce's position: the probabilities and landing points of those returns
    (series.single_reflection_returns, over cosine-distributed directions there) must be those of the traced
    paths (their number within Poisson noise of Σ P, and as far from their first bounce on average as
    the P-weighted landings); and with the control variates the series agrees with the plain
    estimator's and is more precise on white."""
    from trimeter.forward.transport import series as series_module

    seen = {}
    real = series_module.returns_control_variate

    def spy(dr, B, stack, sigma_t, seed, straight_through, final, second_bounce, at, value, polarisation=False):
        bounced, returned = np.flatnonzero(final["m"] >= 1), at[final["reflections"][at] == 1]
        x1, y1 = final["bounce_x"].astype(float), final["bounce_y"].astype(float)
        rng = np.random.default_rng(1)
        total = moment = 0.0
        for _ in range(4):
            u1, u2 = rng.random((2, len(bounced)))
            r, phi = np.sqrt(u1), 2 * math.pi * u2
            P, landings = series_module.single_reflection_returns(dr, stack, sigma_t, *(B.Float(v) for v in (
                x1[bounced], y1[bounced], r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1))))
            P = np.array([np.asarray(p) for p in P])
            landed = np.array([[np.asarray(c) for c in xy] for xy in landings])
            total += P.sum() / 4
            moment += (P * np.hypot(landed[:, 0] - x1[bounced], landed[:, 1] - y1[bounced])).sum() / 4
        distance = np.hypot(second_bounce["x"][returned] - x1[returned], second_bounce["y"][returned] - y1[returned])
        seen.update(expected=total, returned=len(returned), predicted=moment / total, mean=distance.mean(),
                    sem=distance.std(ddof=1) / math.sqrt(len(returned)))
        return real(dr, B, stack, sigma_t, seed, straight_through, final, second_bounce, at, value, polarisation)

    monkeypatch.setattr(series_module, "returns_control_variate", spy)
    device = Stack.from_recipe("device", load_geometry("device"), N, 0.8)
    series = trace(device, 0.05, 0.0, 1 << 20, 7, K_MAX, background_orders=4)
    assert abs(seen["returned"] - seen["expected"]) < 4 * math.sqrt(seen["expected"]), seen
    assert abs(seen["mean"] - seen["predicted"]) < 4 * seen["sem"], seen
    plain = trace(device, 0.05, 0.0, 1 << 20, 8, K_MAX, background_orders=4, control_variates=False)
    alpha = np.array([0.5, 0.97])
    (value, error), (plain_value, plain_error) = series.bounce_series(alpha, 0.9), plain.bounce_series(alpha, 0.9)
    assert np.all(np.abs(value - plain_value) < 4 * np.hypot(error, plain_error)), (value, plain_value)
    assert np.all(error < 0.7 * plain_error), (error, plain_error)


def test_a_bounce_series_row_does_not_depend_on_how_far_the_paths_go_on(monkeypatch):
    """A bounce series traces the paths on past each bounce in a pass of their own, from where the last
    pass cut them, with their own random streams: row m of a trace to N orders is, bit for bit, the
    same for every N > m + 1 (roulette past the 2nd bounce off, so that every path goes on)."""
    from trimeter.forward.transport import series
    from trimeter.forward.transport.trace import trace as trace_paths

    monkeypatch.setattr(series, "CONTINUATION_PILOT", 1)
    device = Stack.from_recipe("device", load_geometry("device"), N, 0.4)
    rows = {orders: trace_paths(device, 0.3, 0.5, 1 << 17, 5, K_MAX, background_orders=orders).counts
            for orders in (3, 4, 6)}
    for orders in (4, 6):
        for m in range(3):
            width = rows[3].shape[1]
            np.testing.assert_array_equal(rows[orders][m, :width], rows[3][m])
            assert not rows[orders][m, width:].any()
    np.testing.assert_array_equal(rows[6][3, :rows[4].shape[1]], rows[4][3])
    assert rows[6][3:].sum() > 0


def test_russian_roulette_past_the_second_bounce_saves_work_and_changes_no_value(monkeypatch):
    """In a dense column few paths come back to the background twice, but those that do diffuse long:
    past the 2nd bounce only a share of them goes on (a pilot, then the others with a probability the
    pilot sets, weighted by its inverse). Same column, same seeds: the series with roulette and with
    every path going on agree within their errors, and the roulette did less work. A clear column,
    whose later bounces carry much of I on white, keeps every path."""
    from trimeter.forward.transport import series as series_module
    from trimeter.forward.transport.trace import trace as trace_paths

    device = Stack.from_recipe("device", load_geometry("device"), N, 0.4)
    alpha = np.array([0.9, 0.99, 0.999])

    def series(sigma_t, pilot):
        monkeypatch.setattr(series_module, "CONTINUATION_PILOT", pilot)
        tally = trace_paths(device, sigma_t, 0.5, 1 << 19, 9, K_MAX, background_orders=5)
        return tally, ColumnTally(tally, None).bounce_series(alpha, 0.9)

    (rouletted, (value, error)), (every, (value_all, error_all)) = series(20.0, 8), series(20.0, 1)
    assert rouletted.path_events < 0.97 * every.path_events
    np.testing.assert_array_equal(rouletted.counts[:2], every.counts[:2])    # before the 2nd bounce: the same
    assert np.all(np.abs(value - value_all) < 3 * np.hypot(error, error_all)), (value, value_all)
    clear, _ = series(0.1, 8)
    assert clear.path_events == series(0.1, 1)[0].path_events


def test_background_orders_are_refused_for_a_factorised_column(ideal):
    with pytest.raises(InputError):
        trace(ideal, 0.3, 0.5, 1 << 12, 3, K_MAX, background_orders=3)


@pytest.mark.slow
def test_thin_clear_device_sample_on_white_matches_a_direct_render():
    """The case that exposed the neglected rim: ℓ 0.8 mm, σt 0.09 /mm, g 0.66, α 0.9775 on ρ = 0.9 came
    out 1.4 % low. Enough paths and samples here (combined std-error ~0.2 %) to resolve that."""
    stack = Stack.from_recipe("device", load_geometry("device"), N, 0.8)
    alpha, rho = 0.9775, 0.9
    tally = trace(stack, 0.09, 0.66, 1 << 21, 11, K_MAX)
    A, B, C = tally.abc([alpha])
    I = float(A[0] + B[0] * rho / (1 - C[0] * rho))
    I_ref, s_ref = render_black_panels("device", alpha, 0.09, 0.66, N, 0.8, rho, spp=1 << 21)
    s = math.hypot(float(tally.stderr([alpha], rho)[0]), s_ref)
    assert abs(I - I_ref) < 4 * s, f"tracer {I:.5f} vs volpath {I_ref:.5f} ± {s:.5f}"


CRASHING_COLUMN = """
import tomllib
from trimeter.maps.recipe import parse_recipe
from trimeter.maps.builder import column_task
d = tomllib.load(open("maps/recipes/device-n1.5-l0.4.toml", "rb"))
d["grid"]["sigma_t"]["count"], d["grid"]["g"]["count"] = 4, 3
d["sampling"]["min_paths"] = d["sampling"]["max_paths"] = 1 << 23
col, _ = column_task(parse_recipe(d), "/nonexistent", 3, 2)
print("traced", col.n_paths)
"""


@pytest.mark.slow
def test_dense_device_column_survives_the_dask_nannys_malloc_trim_threshold():
    """σt = 50/mm, g = 0.9 at 8M paths segfaulted (inside Dr.Jit's kernels) in a process started with
    MALLOC_TRIM_THRESHOLD_=65536, the Dask nanny's default; the tracer overrides glibc's settings (see
    trimeter.forward.transport.backend._keep_freed_memory)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    run = subprocess.run([sys.executable, "-c", CRASHING_COLUMN], env=env, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[2], timeout=600)
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])
    assert "traced 8388608" in run.stdout


def test_added_constant_sums_equal_per_path_values():
    """A control variate adds its expectation c·q^r to every path's value: the tallies' mean and
    second moment at any (α, q) equal the explicit per-path ones."""
    from trimeter.forward.transport.tally import add_constant

    rng = np.random.default_rng(5)
    n = 300
    nee_k, k = rng.integers(0, 8, n), rng.integers(0, 10, n)
    m = rng.integers(0, 3, n)
    nee_value = np.where(m >= 1, rng.uniform(0.0, 2.0, n), 0.0)
    hit = rng.random(n) < 0.5
    every = np.arange(n)
    counts, second = detector_sums(n, [(every, k, np.where(m < 2, hit, 0.0), m), (every, nee_k, nee_value, 1)])
    counts, second = add_constant(counts, second, n, 0.37, row=1)
    tally = Tally(counts=counts, n_paths=n, weight=0.7, specular=0.0, truncated=0, k_max=100, second=second)
    alpha, q = np.array([0.0, 0.4, 0.97]), 0.8
    h = (hit & (m < 2))[:, None]
    value = 0.7 * (nee_value[:, None] * alpha**nee_k[:, None] * q + h * alpha**k[:, None] * q ** m[:, None] + 0.37 * q)
    first, second_moments = tally._moments(alpha)
    np.testing.assert_allclose(first[0] + q * first[1], value.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(sum(second_moments[p] * q**p for p in range(3)), (value**2).mean(axis=0), rtol=1e-12)


@pytest.mark.parametrize("geometry, ell", [("ideal", 0.5), ("device", 0.4)])
def test_plain_returns_happen_as_often_as_their_expectation_says(geometry, ell):
    """The background paths' control variate: the share of paths that come straight back (no
    scattering, within PLAIN_RETURN_ITERATIONS) equals _plain_return's integral within MC error. Both
    estimators on the same paths differ by exactly n·E − (plain returns)."""
    from trimeter.forward.transport.estimators import plain_return
    from trimeter.forward.transport.trace import trace as trace_one

    stack = Stack.from_recipe(geometry, load_geometry(geometry), N, ell)
    n = 1 << 20
    for sigma_t in (0.05, 3.0):
        plain = trace_one(stack, sigma_t, 0.5, n, 21, K_MAX, from_below=True, control_variates=False)
        varied = trace_one(stack, sigma_t, 0.5, n, 21, K_MAX, from_below=True)
        _, expected = plain_return(stack, sigma_t)
        share = (plain.counts[0, 0] - varied.counts[0, 0]) / n + expected
        assert 0.05 < expected < 0.2
        assert abs(share - expected) < 4 * math.sqrt(expected * (1 - expected) / n), (sigma_t, share, expected)


@pytest.mark.parametrize("geometry, ell", [("ideal", 0.5), ("device", 0.4)])
def test_control_variates_keep_the_values_and_cut_the_noise_of_clear_samples(geometry, ell):
    """The default estimator (control variates, background paths by below_share) against the plain
    one on the same seeds: the same I within the plain one's MC error, at every α and both
    backgrounds; on a clear sample on white its std-error is well below the plain one's. (Ideal
    geometry: with B unfactorised, the estimator that uses control variates there.)"""
    stack = Stack.from_recipe(geometry, load_geometry(geometry), N, ell)
    alpha = np.array([0.0, 0.5, 0.9, 0.99])
    unfactorised = {"factorise": False}
    for sigma_t, g in ((0.05, 0.0), (2.0, 0.8)):
        plain = trace(stack, sigma_t, g, 1 << 18, 31, K_MAX, below_fraction=1.0, control_variates=False,
                      **unfactorised)
        varied = trace(stack, sigma_t, g, 1 << 18, 31, K_MAX, **unfactorised)
        for rho in (0.02, 0.9):
            i_plain = background_response_of(plain, alpha, rho)
            i_varied = background_response_of(varied, alpha, rho)
            assert np.all(np.abs(i_varied - i_plain) < 4 * plain.stderr(alpha, rho)), (sigma_t, g, rho)
    clear_plain = trace(stack, 0.05, 0.0, 1 << 18, 32, K_MAX, below_fraction=1.0, control_variates=False,
                        **unfactorised)
    clear = trace(stack, 0.05, 0.0, 1 << 18, 32, K_MAX, **unfactorised)
    assert np.all(clear.stderr(alpha, 0.9) < 0.8 * clear_plain.stderr(alpha, 0.9))


def test_rotation_average_keeps_the_values_and_cuts_the_noise_of_the_devices_panels(monkeypatch):
    """Device: a detector path's own way to a panel, averaged over its copies turned about its start
    (trimeter.forward.transport.walk.ROTATIONS), against the 0/1 outcome on other seeds: the same I within the MC
    error at every α and both backgrounds, and a clearly smaller std-error where light that scattered in the
    sample reaches the panels itself (black background, or α near 1 on white)."""
    from trimeter.forward.transport import walk

    stack = Stack.from_recipe("device", load_geometry("device"), N, 0.4)
    alpha = np.array([0.0, 0.5, 0.9, 0.99])
    for sigma_t, g in ((0.05, 0.0), (2.0, 0.5), (50.0, 0.9)):
        averaged = trace(stack, sigma_t, g, 1 << 18, 41, K_MAX)
        monkeypatch.setattr(walk, "ROTATIONS", 1)
        single = trace(stack, sigma_t, g, 1 << 18, 42, K_MAX)
        monkeypatch.undo()
        for rho in (0.02, 0.9):
            both = np.hypot(averaged.stderr(alpha, rho), single.stderr(alpha, rho))
            difference = background_response_of(averaged, alpha, rho) - background_response_of(single, alpha, rho)
            assert np.all(np.abs(difference) <= 4 * both + 1e-12), (sigma_t, g, rho, difference / (both + 1e-300))
            assert averaged.stderr(alpha[2:], rho).max() < 0.85 * single.stderr(alpha[2:], rho).max(), (sigma_t, g, rho)


def background_response_of(tally, alpha, rho):
    A, B, C = tally.abc(alpha)
    return A + B * rho / (1 - C * rho)


def test_background_paths_follow_their_share_of_the_error():
    """below_share: few background paths where C hardly matters (it adds no variance), more where its
    variance matters, never fewer than the pilot's share nor more than one per detector path."""
    from trimeter.forward.transport.column import BELOW_PILOT, below_share

    above = Tally(counts=np.array([[100.0, 50.0], [300.0, 20.0]]), n_paths=1000, weight=1.0, specular=0.0,
                  truncated=0, k_max=10, path_events=20000)
    certain = Tally(counts=np.array([[1000.0]]), n_paths=1000, weight=1.0, specular=0.0, truncated=0, k_max=10,
                    path_events=10000)          # every path comes back: C = 1 exactly, no variance
    noisy = Tally(counts=np.array([[150.0, 20.0]]), n_paths=1000, weight=1.0, specular=0.0, truncated=0, k_max=10,
                  path_events=10000)
    assert below_share(above, certain) == 1 / BELOW_PILOT
    assert 1 / BELOW_PILOT < below_share(above, noisy) <= 1.0


def test_estimator_comparison_refuses_too_few_paths_with_a_clear_error(capsys):
    from trimeter.cli import main

    assert main(["bench", "mapbuild", "--device-columns", "maps/recipes/device-n1.5-l0.4.toml", "--paths", "10"]) == 2
    assert "trimeter: error: --paths must be ≥ 65536" in capsys.readouterr().err


def test_factorised_bookkeeping_equals_per_path_sums():
    """Factorised columns (B = UT1·UTU): A, B, C and the std-error of I(ρ) equal the explicit per-path
    computation — a detector path's value is its A term + q·UTU × its UT1 term; a background path
    moves I through C (× B·q²) and UTU (× UT1·q), its two outcomes exclusive; constants added to rows
    (as control variates add them) included."""
    from trimeter.forward.transport.tally import add_constant, background_sums

    rng = np.random.default_rng(3)
    n, nb = 600, 400
    k = rng.integers(0, 30, n)
    m = rng.integers(0, 2, n)
    hit = (m == 0) & (rng.random(n) < 0.6)
    nee_k = np.where(m == 1, k, 0)
    v = np.where((m == 1) & (rng.random(n) < 0.8), 1.0, 0.0)
    every = np.arange(n)
    counts, second = detector_sums(n, [(every, k, np.where(m < 2, hit, 0.0), m), (every, nee_k, v, 1)])
    counts, second = add_constant(counts, second, n, 0.15, row=1)
    kb = rng.integers(0, 25, nb)
    outcome = rng.random(nb)
    returned, escaped = outcome < 0.3, outcome > 0.5
    bc, bs = background_sums(kb, returned, escaped)
    bc, bs = add_constant(bc, bs, nb, 0.05, row=0)
    bc, bs = add_constant(bc, bs, nb, 0.2, row=1)
    above = Tally(counts=counts, n_paths=n, weight=0.9, specular=0.04, truncated=0, k_max=100, second=second)
    below = Tally(counts=bc, n_paths=nb, weight=1.0, specular=0.0, truncated=0, k_max=100, second=bs)
    tally = ColumnTally(above, below, factorised=True)
    alpha, rho = np.array([0.0, 0.4, 0.97]), 0.8
    a_term = 0.9 * np.where(hit[:, None], alpha[None, :] ** k[:, None], 0.0)
    ut1_term = 0.9 * (v[:, None] * alpha[None, :] ** nee_k[:, None] + 0.15)
    pb = alpha[None, :] ** kb[:, None]
    c_term = np.where(returned[:, None], pb, 0.0) + 0.05
    e_term = np.where(escaped[:, None], pb, 0.0) + 0.2
    A, UT1, C, UTU = 0.04 + a_term.mean(0), ut1_term.mean(0), c_term.mean(0), e_term.mean(0)
    got = tally.abc(alpha)
    for have, want in zip(got, (A, UT1 * UTU, C), strict=True):
        np.testing.assert_allclose(have, want, rtol=1e-12)
    q = rho / (1 - C * rho)
    per_above = a_term + q * UTU * ut1_term
    per_below = UT1 * UTU * q * q * c_term + UT1 * q * e_term
    var = per_above.var(0, ddof=1) / n + per_below.var(0, ddof=1) / nb
    np.testing.assert_allclose(tally.stderr(alpha, rho), np.sqrt(var), rtol=1e-9)


def test_factorisation_is_the_ideal_geometrys_default_and_refused_elsewhere(ideal):
    device = Stack.from_recipe("device", load_geometry("device"), N, 0.4)
    assert ideal.factorises and not device.factorises
    assert trace(ideal, 1.0, 0.5, 4096, 3, K_MAX).factorised
    assert not trace(ideal, 1.0, 0.5, 4096, 3, K_MAX, factorise=False).factorised
    assert not trace(device, 1.0, 0.5, 4096, 3, K_MAX).factorised
    with pytest.raises(InputError, match="factorises only"):
        trace(device, 1.0, 0.5, 4096, 3, K_MAX, factorise=True)
    with pytest.raises(ValueError, match="factorised"):
        trace(ideal, 1.0, 0.5, 4096, 3, K_MAX).__iadd__(trace(ideal, 1.0, 0.5, 4096, 4, K_MAX, factorise=False))


@pytest.mark.parametrize("sigma_t, g", [(0.05, 0.0), (2.0, 0.8), (20.0, 0.0)])
def test_factorised_columns_agree_with_adding_doubling_and_cut_the_white_backgrounds_noise_near_alpha_one(
        ideal, sigma_t, g):
    """B = UT1·UTU is unbiased (against adding-doubling, both backgrounds, within 4 std-errors), and
    the largest std-error over α on white — what sets a column's paths, at α near 1 — is well below
    the unfactorised estimator's on as many detector paths."""
    alpha = np.array([0.0, 0.5, 0.9, 0.99, 0.999])
    n = 1 << 17
    factorised = trace(ideal, sigma_t, g, n, 41, K_MAX)
    unfactorised = trace(ideal, sigma_t, g, n, 41, K_MAX, factorise=False)
    for rho in (0.02, 0.9):
        reference = np.array([adding_doubling(a, sigma_t, g, rho) for a in alpha])
        got = background_response_of(factorised, alpha, rho)
        assert np.all(np.abs(got - reference) < 4 * factorised.stderr(alpha, rho) + 2e-4), (rho, got - reference)
    worst, worst_before = factorised.stderr(alpha, 0.9).max(), unfactorised.stderr(alpha, 0.9).max()
    print(f"\nσt {sigma_t}, g {g}: largest std-error on white {worst:.2e}, unfactorised {worst_before:.2e}")
    assert worst < 0.75 * worst_before
