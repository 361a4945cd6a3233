"""The band-aware fit (trimeter.inversion.bands): AS7341-like band readings of the twin's traced inks
(independent of the map) fitted band-aware come within the band targets where the per-channel fit of
the same readings does not; the weights' validation; the spline bases."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.inversion.bands import _basis, band_weights, fit_bands
from trimeter.inversion.flags import FitFlag
from trimeter.inversion.artifacts import load_artifacts
from trimeter.spectrometer.sensors import as7341_weights

INKS = ("cyan-ink", "magenta-ink", "yellow-ink", "black-ink")


@pytest.fixture(scope="module")
def inks():
    from trimeter.twin.optics import Optics

    optics = Optics()
    lam = optics.wavelengths_nm
    inside = (lam >= 350) & (lam <= 995)
    weights = as7341_weights(lam[inside])
    out = {}
    for name in INKS:
        s = optics.insert_sample(name, 0.4)
        readings = (weights.diffuse @ s.I_b[inside], weights.diffuse @ s.I_w[inside],
                    weights.collimated @ s.I_c[inside], weights.diffuse @ optics.rho_black[inside],
                    weights.diffuse @ optics.rho_white[inside])
        truth = [np.interp(weights.centre_nm, lam, v) for v in (s.alpha, s.sigma_t, s.g)]
        out[name] = readings, truth
    return load_artifacts("device-n1.5-l0.4"), weights, out


def test_band_fit_meets_the_targets_the_per_channel_fit_misses(inks):
    model, weights, materials = inks
    errors = {"band": [], "per_channel": []}
    flagged = 0
    for readings, (alpha, sigma_t, g) in materials.values():
        fit = fit_bands(model, weights, *readings)
        for key, r in (("band", fit.at_centres), ("per_channel", fit.per_channel)):
            errors[key].append(np.stack([np.abs(r.alpha - alpha), np.abs(r.sigma_t / sigma_t - 1), np.abs(r.g - g)]))
        flagged += np.count_nonzero(fit.at_centres.flags & int(FitFlag.BAND_UNRESOLVED))
        assert not np.any(fit.per_channel.flags & int(FitFlag.BAND_UNRESOLVED))
    band = np.percentile(np.concatenate(errors["band"], axis=1), 95, axis=1)
    per_channel = np.percentile(np.concatenate(errors["per_channel"], axis=1), 95, axis=1)
    assert band[0] < 0.01 and band[1] < 0.02 and band[2] < 0.03, band
    assert per_channel[0] > 2 * band[0] and per_channel[1] > 2 * band[1]   # the bands' bias, removed
    assert flagged <= 6  # of 36 channels


def test_the_unresolved_flag_marks_the_worst_channels(inks):
    """The channels whose band-aware σt is off most are the flagged ones."""
    model, weights, materials = inks
    readings, (_, sigma_t, _) = materials["cyan-ink"]
    fit = fit_bands(model, weights, *readings).at_centres
    worst = np.argmax(np.abs(fit.sigma_t / sigma_t - 1))
    assert fit.flags[worst] & int(FitFlag.BAND_UNRESOLVED)


def test_grid_output_and_stds(inks):
    model, weights, materials = inks
    readings, _ = materials["magenta-ink"]
    fit = fit_bands(model, weights, *readings, grid_nm=np.array([380.0, 500.0, 555.0, 950.0]))
    assert fit.on_grid is not None
    # inside the channels' span the grid agrees with the centres' spline; beyond it, flagged
    at = fit.on_grid
    assert at.flags[0] & int(FitFlag.BAND_UNRESOLVED) and at.flags[3] & int(FitFlag.BAND_UNRESOLVED)
    assert not at.flags[1] & int(FitFlag.BAND_UNRESOLVED)
    c = fit.at_centres
    assert np.all(np.isfinite(c.alpha_std)) and np.all(c.alpha_std > 0) and np.all(c.sigma_t_std > 0)
    # a reading's std 10x larger widens the stds
    wide = fit_bands(model, weights, *readings, I_b_std=np.full(9, 0.05), check_resolved=False).at_centres
    assert np.all(wide.alpha_std > c.alpha_std)


def test_noisy_readings_scatter_within_the_stds(inks):
    model, weights, materials = inks
    readings, (alpha, _, _) = materials["black-ink"]
    rng = np.random.default_rng(1)
    z = []
    for _ in range(6):
        noisy = [r * (1 + 0.005 * rng.standard_normal(9)) + 2e-4 * rng.standard_normal(9) for r in readings[:3]]
        fit = fit_bands(model, weights, *noisy, *readings[3:], check_resolved=False).at_centres
        z.append((fit.alpha - alpha) / fit.alpha_std)
    assert np.percentile(np.abs(z), 95) < 3.5


def test_unusable_channel_is_nan_and_flagged(inks):
    model, weights, materials = inks
    (I_b, I_w, I_c, rb, rw), _ = materials["black-ink"]
    I_b = I_b.copy()
    I_b[3] = np.nan
    fit = fit_bands(model, weights, I_b, I_w, I_c, rb, rw).at_centres
    assert np.isnan(fit.alpha[3]) and fit.flags[3] & int(FitFlag.NONFINITE_INPUT)
    assert np.all(np.isfinite(np.delete(fit.alpha, 3)))


def _weights(**change):
    lam = np.arange(400.0, 701.0)
    d = np.stack([np.exp(-0.5 * ((lam - c) / 15) ** 2) for c in (500.0, 600.0)])
    args = dict(wavelength_nm=lam, channels=("A", "B"), diffuse=d, collimated=d.copy())
    args.update(change)
    return args


@pytest.mark.parametrize("edit, message", [
    (lambda a: a["diffuse"].__setitem__((0, 10), -0.1), "A_diffuse has a negative weight"),
    (lambda a: a["collimated"].__setitem__((1, 10), np.nan), "B_collimated has an empty or non-finite"),
    (lambda a: a["diffuse"].__setitem__(1, 0.0), "B_diffuse is zero everywhere"),
    (lambda a: a.update(wavelength_nm=a["wavelength_nm"][80:], diffuse=a["diffuse"][:, 80:],
                        collimated=a["collimated"][:, 80:]), "A_diffuse does not fall to zero at 480 nm"),
    (lambda a: a.update(channels=("A", "A")), "more than once"),
])
def test_bad_weights_are_one_clear_error(edit, message):
    args = _weights()
    edit(args)
    with pytest.raises(InputError, match=message):
        band_weights(**args)


def test_weights_select_and_one_channel(inks):
    model, weights, materials = inks
    with pytest.raises(InputError, match="F9 have no weights"):
        weights.select(["F1", "F9"])
    one = weights.select(["F5"])
    (I_b, I_w, I_c, rb, rw), _ = materials["black-ink"]
    with pytest.raises(InputError, match="at least 2 channels"):
        fit_bands(model, one, I_b[4:5], I_w[4:5], I_c[4:5])


@pytest.mark.parametrize("kind", ["cubic", "not-a-knot", "linear"])
def test_bases_interpolate_the_knots_in_any_order(kind):
    knots = np.array([500.0, 420.0, 610.0, 700.0, 560.0])
    values = np.array([0.3, -1.0, 2.0, 0.5, 1.2])
    B = _basis(knots, knots, kind)
    assert np.allclose(B @ values, values)
    lam = np.linspace(380, 760, 50)
    assert np.allclose(_basis(knots, lam, kind).sum(axis=1), 1.0)  # constants are reproduced


def test_readings_no_spectrum_explains_are_flagged_not_converged(inks):
    model, weights, materials = inks
    (I_b, I_w, I_c, rb, rw), _ = materials["black-ink"]
    I_w = I_w.copy()
    I_w[4] = min(0.99, I_w[4] * 3)  # far more light over white than a sample this dark can pass
    fit = fit_bands(model, weights, I_b, I_w, I_c, rb, rw, check_resolved=False).at_centres
    assert fit.flags[4] & int(FitFlag.NOT_CONVERGED)


def test_a_non_scattering_sample_has_no_g(inks):
    model, weights, _ = inks
    lam = weights.wavelength_nm
    grid = model.grid
    rho_b, rho_w = model.reference_rhos
    n = lam.size
    I = grid.intensities(np.full(n, 0.005), np.full(n, 2.0), np.full(n, 0.5), np.full(n, rho_b), np.full(n, rho_w))
    fit = fit_bands(model, weights, weights.diffuse @ I[0], weights.diffuse @ I[1], weights.collimated @ I[2],
                    check_resolved=False).at_centres
    assert np.all(fit.flags & int(FitFlag.G_UNDEFINED)) and np.all(np.isnan(fit.g))
    np.testing.assert_allclose(fit.sigma_t, 2.0, rtol=0.01)
