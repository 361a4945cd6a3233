"""The tracer's `polarisation` option (s and p tracked at the interfaces, trimeter.forward.transport.walk.Walk):
closed forms of clear slabs per polarisation, the control variates' expectations against the walk, and the
shift polarised − unpolarised against Mitsuba's polarised renders (maps/polarisation.json). Each test
fails if the option is ignored: with it off the traces are the unpolarised ones, bit for bit."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from trimeter.bench.polarisation import (MAPS, MATERIALS, SLAB_N, SLAB_RHO, SLAB_THICKNESS_MM, clear_slab_over,
                                         slab_diffuse_from, slab_diffuse_reflectance)
from trimeter.forward.transport import Stack, k_max_for
from trimeter.forward.transport import trace_column as trace
from trimeter.geometry import load_geometry
from trimeter.model.fresnel import NUMPY, fresnel_polarised, normal_incidence_reflectance

BENCH = Path(__file__).resolve().parents[2] / "maps" / "polarisation.json"
NO_SCATTERING = np.array([0.0])   # α = 0: only light that never scattered counts


@pytest.fixture(scope="module")
def ideal():
    return Stack.from_recipe("ideal", load_geometry("ideal"), SLAB_N, SLAB_THICKNESS_MM)


def response(tally, alpha, rho):
    A, B, C = tally.abc(alpha)
    return A + B * rho / (1 - C * rho)


def absorbing_slab(n: float, optical_depth: float, rho: float, polarised: bool) -> float:
    """I along the normal of a clear slab (absorbing: σt·ℓ = optical_depth) over a Lambertian ρ under
    uniform light: the slab's normal reflectance and transmittance (s and p alike there), and its diffuse
    reflectance C and transmittance T_d from below, per polarisation then averaged (polarised: the
    background depolarises between passes) or from the averaged Fresnel (unpolarised)."""
    r = float(normal_incidence_reflectance(1.0, n))
    t = math.exp(-optical_depth)
    R0, T0 = r + (1 - r) ** 2 * r * t * t / (1 - r * r * t * t), (1 - r) ** 2 * t / (1 - r * r * t * t)
    x, w = np.polynomial.legendre.leggauss(96)
    mu, w = (x + 1) / 2, w / 2
    R_s, R_p, cos_in = fresnel_polarised(NUMPY, mu, n)
    t_mu = np.exp(-optical_depth / cos_in)
    faces = (R_s, R_p) if polarised else ((R_s + R_p) / 2,)
    C = np.mean([np.sum(w * 2 * mu * (f + (1 - f) ** 2 * f * t_mu**2 / (1 - f * f * t_mu**2))) for f in faces])
    T_d = np.mean([np.sum(w * 2 * mu * (1 - f) ** 2 * t_mu / (1 - f * f * t_mu**2)) for f in faces])
    return float(R0 + T0 * T_d * rho / (1 - C * rho))


def test_the_absorbing_slabs_closed_form_is_the_benchs_when_lossless():
    for polarised, R_d in zip((False, True), slab_diffuse_reflectance(SLAB_N), strict=True):
        assert absorbing_slab(SLAB_N, 0.0, SLAB_RHO, polarised) == pytest.approx(
            clear_slab_over(SLAB_RHO, SLAB_N, R_d), abs=1e-12)


@pytest.mark.parametrize("factorise", [True, False])
def test_a_clear_lossless_slab_reflects_as_the_polarised_closed_form(ideal, factorise):
    """The bench's clear-slab check, traced: R_d from I over ρ 0.5 (α = 0, no absorption to speak of)
    is the polarised closed form with the option on and the unpolarised one with it off (same paths).
    Factorised: the walk alone (background paths for C and UTU); unfactorised: the next-event estimate
    and the control variates' expectations too."""
    closed = dict(zip((False, True), slab_diffuse_reflectance(SLAB_N), strict=True))
    assert closed[False] - closed[True] > 0.006
    for polarisation in (False, True):
        tally = trace(ideal, 1e-6, 0.0, 1 << 21, 5, 4, factorise=factorise, polarisation=polarisation,
                      below_fraction=1.0)
        I, se = response(tally, NO_SCATTERING, SLAB_RHO), tally.stderr(NO_SCATTERING, SLAB_RHO)
        R_d = slab_diffuse_from(I, SLAB_RHO, SLAB_N)[0]
        R_d_se = abs(slab_diffuse_from(I + se, SLAB_RHO, SLAB_N)[0] - R_d)
        assert abs(R_d - closed[polarisation]) < 4 * R_d_se, (polarisation, R_d, R_d_se, closed)
        assert R_d_se < 0.1 * (closed[False] - closed[True])


@pytest.mark.parametrize("factorise", [True, False])
def test_an_absorbing_clear_slab_gives_its_closed_form_per_polarisation(ideal, factorise):
    """Light that never scattered (α = 0) through a slab with σt·ℓ = 0.1, over both reference backgrounds:
    the closed form with s and p apart (Beer-Lambert along each way through the slab)."""
    sigma_t = 0.2
    tally = trace(ideal, sigma_t, 0.0, 1 << 21, 6, 30, factorise=factorise, polarisation=True)
    for rho in (0.02, 0.5, 0.9):
        I, se = response(tally, NO_SCATTERING, rho)[0], tally.stderr(NO_SCATTERING, rho)[0]
        expected = absorbing_slab(SLAB_N, sigma_t * SLAB_THICKNESS_MM, rho, polarised=True)
        assert abs(I - expected) < 4 * se, (rho, I, se, expected)
    unpolarised = absorbing_slab(SLAB_N, sigma_t * SLAB_THICKNESS_MM, 0.5, polarised=False)
    assert abs(expected - unpolarised) > 10 * se


@pytest.mark.parametrize("geometry, ell", [("ideal", 0.5), ("device", 0.4)])
def test_plain_returns_with_polarisation_happen_as_often_as_their_expectation_says(geometry, ell, monkeypatch):
    """The background paths' control variate with polarisation: the share of paths that come straight back
    (counted: the trace's expectation set to 0) equals plain_return's integral per polarisation (and, for a
    clear sample, not the unpolarised one)."""
    from trimeter.forward.transport import trace as trace_module
    from trimeter.forward.transport.estimators import plain_return

    monkeypatch.setattr(trace_module, "plain_return", lambda *args: (plain_return(*args)[0], 0.0))
    stack = Stack.from_recipe(geometry, load_geometry(geometry), SLAB_N, ell)
    n = 1 << 20
    for sigma_t in (0.05, 3.0):
        plain = trace_module.trace(stack, sigma_t, 0.5, n, 21, 30, from_below=True, control_variates=False,
                                   polarisation=True)
        varied = trace_module.trace(stack, sigma_t, 0.5, n, 21, 30, from_below=True, polarisation=True)
        _, expected = plain_return(stack, sigma_t, polarisation=True)
        _, unpolarised = plain_return(stack, sigma_t)
        share = (plain.counts[0, 0] - varied.counts[0, 0]) / n
        error = math.sqrt(expected * (1 - expected) / n)
        assert abs(share - expected) < 4 * error, (sigma_t, share, expected)
        if sigma_t < 1:   # (dense: one reflection off the bottom face, the same for unpolarised light)
            assert abs(unpolarised - expected) > 8 * error, (sigma_t, unpolarised, expected)


def test_a_bounce_series_returns_control_variate_predicts_the_polarised_returns(monkeypatch):
    """A bounce series with polarisation: the paths that came back from their first bounce by one
    Fresnel reflection are as many as series.single_reflection_returns' polarised probabilities say
    (within Poisson noise), and not as many as its unpolarised ones."""
    from trimeter.forward.transport import series as series_module

    seen = {}
    real = series_module.returns_control_variate

    def spy(dr, B, stack, sigma_t, seed, straight_through, final, second_bounce, at, value, polarisation=False):
        bounced, returned = np.flatnonzero(final["m"] >= 1), at[final["reflections"][at] == 1]
        x1, y1 = final["bounce_x"].astype(float), final["bounce_y"].astype(float)
        rng = np.random.default_rng(1)
        totals = {False: 0.0, True: 0.0}
        for _ in range(4):
            u1, u2 = rng.random((2, len(bounced)))
            r, phi = np.sqrt(u1), 2 * math.pi * u2
            start = [B.Float(v) for v in (x1[bounced], y1[bounced], r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1))]
            for pol in totals:
                P, _ = series_module.single_reflection_returns(dr, stack, sigma_t, *start, pol)
                totals[pol] += sum(float(np.sum(np.asarray(p))) for p in P) / 4
        seen.update(returned=len(returned), expected=totals[True], unpolarised=totals[False], option=polarisation)
        return real(dr, B, stack, sigma_t, seed, straight_through, final, second_bounce, at, value, polarisation)

    monkeypatch.setattr(series_module, "returns_control_variate", spy)
    device = Stack.from_recipe("device", load_geometry("device"), SLAB_N, 0.8)
    trace(device, 0.05, 0.0, 1 << 20, 7, 30, background_orders=3, polarisation=True)
    assert seen["option"] is True
    noise = math.sqrt(seen["expected"])
    assert abs(seen["returned"] - seen["expected"]) < 4 * noise, seen
    assert abs(seen["unpolarised"] - seen["expected"]) > 6 * noise, seen


@pytest.mark.parametrize("geometry, label", [("device", "clear"), ("ideal", "thin")])
def test_the_polarisation_shift_matches_mitsubas_polarised_renders(geometry, label):
    """The tracer's I shift polarised − unpolarised (same paths on and off, in 4 batches for its own error)
    against the bench's: Mitsuba's polarised variant with the depolarising phase function (the tracer's
    model) − its unpolarised one, on white, within their combined errors. Off, the two traces are identical
    and the shift 0."""
    bench = json.loads(BENCH.read_text())
    row = next(r for g in bench["geometries"] if g["geometry"] == geometry for r in g["rows"]
               if r["material"] == label and r["background"] == "white")
    _, alpha, sigma_t, g = next(m for m in MATERIALS if m[0] == label)
    from trimeter.formats.appearance import AppearanceMap, find_map

    amap = AppearanceMap.load(find_map(MAPS[geometry]))
    stack = Stack.from_recipe(geometry, amap.recipe["geometry_params"], amap.n, amap.thickness_mm)
    a, k_max = np.array([alpha]), k_max_for(alpha, 1e-9)
    shifts = [np.subtract(*(response(trace(stack, sigma_t, g, 1 << 18, 13 + batch, k_max, polarisation=pol), a,
                                     row["rho"])[0] for pol in (True, False))) for batch in range(4)]
    shift, own_error = np.mean(shifts), np.std(shifts, ddof=1) / 2
    render, error = row["delta_depolarising"], row["stderr_delta_depolarising"]
    assert abs(render) > 4 * error
    assert abs(shift - render) < 3 * math.hypot(error, own_error), (shift, own_error, render, error)


def test_a_map_built_with_polarisation_records_it_and_differs_from_the_unpolarised_one(tiny_data, tmp_path):
    """A recipe with `polarisation = true` builds a map whose stored recipe says so (and loads: the file
    schema knows the flag), with another C (close to it) than the same recipe without it, from the same paths; a
    stored flag that is not true/false is refused."""
    from trimeter.errors import MapFileError
    from trimeter.formats.appearance import MAP_KIND, AppearanceMap
    from trimeter.formats.container import read_container, write_container
    from trimeter.maps.builder import build_map
    from trimeter.maps.recipe import parse_recipe

    maps = {}
    for polarisation in (False, True):
        data = tiny_data()
        data["polarisation"] = polarisation
        maps[polarisation] = build_map(parse_recipe(data), tmp_path / f"{polarisation}.tmap", progress=False)
    assert AppearanceMap.load(tmp_path / "True.tmap").recipe["polarisation"] is True
    assert "polarisation" not in maps[False].recipe
    assert not np.array_equal(maps[True].C, maps[False].C)
    np.testing.assert_allclose(maps[True].C, maps[False].C, atol=0.02)
    meta, arrays, _ = read_container(tmp_path / "True.tmap", MAP_KIND)
    meta["recipe"]["polarisation"] = "yes"
    write_container(tmp_path / "bad.tmap", MAP_KIND, meta, arrays)
    with pytest.raises(MapFileError, match="polarisation"):
        AppearanceMap.load(tmp_path / "bad.tmap")
