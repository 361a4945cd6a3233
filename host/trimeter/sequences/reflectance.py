"""Raw spectra → reflectances, exactly as the paper's Sec. 4.2 defines them (the calibration's own
definitions: trimeter.domain.calibration):
    I_b = black_sample / diffuse,  I_w = white_sample / diffuse,  I_c = collimated_sample / collimated
and the map is queried at the measured backgrounds ρ_b = ρ_black(λ), ρ_w = ρ_white_ref.

Bad bins never raise: a bin that saturated in every exposure, read NaN, or had no reference light
gets NaN (and a CaptureFlag bit); the fit flags NaN inputs as unusable.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain import Calibration, Capture, RawSample, Reflectances
from trimeter.errors import InputError
from trimeter.sequences import lamp_monitor

# A bin's frame spread comes from a few frames (settings.frames, default 2: one degree of freedom), so
# its own std is a poor estimate of its noise: a ±1σ from it covers far less than 68 % (Student's t).
# The noise level changes slowly with wavelength (shot and read noise of a smooth spectrum), so each
# bin takes the mean relative variance of this many neighbours (~5 nm here): tens of degrees of freedom.
STD_POOL_BINS = 15
# The part of a lamp's drift since the calibration that the monitor's correction leaves, relative to the
# correction (see lamp_correction): a warming white LED dims by a few % and its phosphor shifts by 1-2 nm
# (paper Sec. 4.2; the twin's Led model), so on the flanks of the pump's and the phosphor's peaks a
# bin's light moves about as much as the dimming the photodiode sees, and near their centres hardly.
LAMP_SPECTRAL_REL = 1.0


def pooled_relative_std(rel_std: ArrayLike) -> np.ndarray:
    """Relative stds pooled over STD_POOL_BINS neighbouring bins (root of their mean square, NaN bins
    left out and left NaN)."""
    rel = np.asarray(rel_std, dtype=float)
    ok = np.isfinite(rel)
    kernel = np.ones(min(STD_POOL_BINS, max(len(rel), 1)))
    total = np.convolve(np.where(ok, rel * rel, 0.0), kernel, mode="same")
    count = np.convolve(ok.astype(float), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, np.sqrt(total / count), np.nan)


def lamp_correction(light: dict | None, setup: str) -> tuple[float, float]:
    """(fraction, its relative std) of the calibrated light the lamps of one set-up gave during its shot,
    from the lamp monitor (lamp_monitor.relative_light): the mean of its open lamps' readings (after the
    shutters settled and after the last exposure: the exposures lie between them). The shot is divided
    by the fraction; its std is half the readings' range (how far the light moved during the shot), in
    quadrature with the part of a drift the photodiodes cannot see: a warming LED's spectrum also shifts,
    which a broadband photodiode does not tell from dimming (LAMP_SPECTRAL_REL of the correction).
    (1, 0) without readings or when they cannot be compared (the shot checks refuse those)."""
    if not light or "error" in light or setup not in light:
        return 1.0, 0.0
    entry = light[setup]
    readings = [f for lamp, values in entry["fractions"].items()
                if (entry["collimated"] if lamp == "collimated" else entry["panels"]) for f in values]
    values = np.asarray(readings, dtype=float)
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values <= lamp_monitor.DEAD_FRACTION):
        return 1.0, 0.0
    fraction = float(values.mean())
    spread = 0.5 * float(values.max() - values.min()) / fraction
    return fraction, float(np.hypot(spread, LAMP_SPECTRAL_REL * abs(fraction - 1.0)))


def reflectances(calibration: Calibration, sample: RawSample) -> Reflectances:
    """The paper's ratios, vectorised over bins; unusable bins become NaN with a flag, never an error."""
    if len(sample.wavelengths_nm) != len(calibration.wavelengths_nm) or not np.allclose(
            sample.wavelengths_nm, calibration.wavelengths_nm, rtol=0, atol=1e-3):
        raise InputError("the calibration was taken with another spectrometer or wavelength set: calibrate again")
    flags = calibration.flags | sample.black.flags() | sample.white.flags() | sample.collimated.flags()
    light = lamp_monitor.relative_light(calibration.lamp_monitor, sample.lamp_monitor)
    (f_b, d_b), (f_w, d_w), (f_c, d_c) = (lamp_correction(light, key) for key in ("black", "white", "collimated"))
    with np.errstate(invalid="ignore", divide="ignore"):
        i_b = sample.black.rate / calibration.diffuse / f_b
        i_w = sample.white.rate / calibration.diffuse / f_w
        i_c = sample.collimated.rate / calibration.collimated / f_c
    bad = flags != 0
    nan = np.float64("nan")

    def std(value: np.ndarray, capture: Capture, reference_rel: np.ndarray | None,
            lamp_rel: np.ndarray | float) -> np.ndarray | None:
        if reference_rel is None or capture.rate_std is None:
            return None
        with np.errstate(invalid="ignore"):
            rel = np.hypot(np.hypot(pooled_relative_std(capture.relative_std()), pooled_relative_std(reference_rel)),
                           lamp_rel)
            return np.where(bad, nan, np.abs(value) * rel)

    return Reflectances(calibration.wavelengths_nm.copy(), np.where(bad, nan, i_b), np.where(bad, nan, i_w),
                        np.where(bad, nan, i_c), calibration.rho_black.copy(),
                        np.full_like(calibration.rho_black, calibration.rho_white), flags.astype(np.int32),
                        std(i_b, sample.black, calibration.diffuse_rel_std, d_b),
                        std(i_w, sample.white, calibration.diffuse_rel_std, d_w),
                        std(i_c, sample.collimated, calibration.collimated_rel_std, d_c), light)
