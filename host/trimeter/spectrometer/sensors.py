"""What each build's detector sees of a spectrum: the AS7341's channel responses, the lamps' emission
and a spectrometer's slit function, declared once.

These are models, not measurements, and say so:
- AS7341 channels: Gaussians at the datasheet's (DS000504) peak wavelengths and FWHM. The datasheet's
  curves are close to Gaussian over the passband but have weak side lobes and a slower far tail;
  a user with measured responses supplies them as band weights (`fit --bands WEIGHTS.csv`). The NIR
  channel's FWHM is not in the datasheet's table; 50 nm is an assumption.
- Lamps (hardware/bom.toml): the panels' CRI ≥ 95 white strip as a blue pump at 450 nm plus a green and
  a red phosphor; the collimated LED (a violet-pumped full-spectrum white, Nichia Optisolis class) as a
  violet pump at 405 nm plus one broad phosphor. Both with a small broadband floor (a phosphor's
  far tail, which is what the NIR channel sees). Gaussian components: a documented approximation of
  the parts' published spectra.
- Spectrometer slit: a Gaussian line-spread function of SLIT_FWHM_NM (a compact VIS-NIR spectrometer
  with a 25-50 µm slit), sampled at its own pixels.
- C12880MA micro-spectrometer: 288 pixels at the unit's test-sheet polynomial (a typical unit's are the
  register map's defaults, spectro_wl_*), each reading through a Gaussian line-spread function of
  C12880_FWHM_NM (the datasheet gives 15 nm as the maximum; 12 nm is a typical unit's).

A channel's effective weight is response × emission (the white reference is flat: the geometry's);
trimeter.inversion.bands normalises it. Measured weights come as a CSV (read_band_weights):
`wavelength_nm` and per channel `<CH>_diffuse`, `<CH>_collimated`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from trimeter.errors import InputError
from trimeter.inversion.bands import BandWeights, band_weights

# channel: (peak nm, FWHM nm) — DS000504's table; NIR's width assumed
AS7341_CHANNELS = {"F1": (415.0, 26.0), "F2": (445.0, 30.0), "F3": (480.0, 36.0), "F4": (515.0, 39.0),
                   "F5": (555.0, 39.0), "F6": (590.0, 40.0), "F7": (630.0, 50.0), "F8": (680.0, 52.0),
                   "NIR": (910.0, 50.0)}
# (centre nm, FWHM nm, relative height) per emission component, and the broadband floor
PANEL_LEDS = ((450.0, 20.0, 0.55), (535.0, 95.0, 0.85), (630.0, 90.0, 1.0))
BEAM_LED = ((405.0, 16.0, 0.6), (590.0, 210.0, 1.0))
LED_FLOOR = 0.004
SLIT_FWHM_NM = 2.5
C12880_FWHM_NM = 12.0
C12880_PIXELS = 288
MAX_WEIGHTS_BYTES = 64_000_000  # a weights table on a 0.1 nm grid of a few dozen channels is a few MB
# the wavelength grid of the built-in weights: wide enough for every channel's band to fall to zero
WEIGHTS_GRID_NM = (350.0, 1000.0, 1.0)

_FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def _gaussian(lam: np.ndarray, centre: float, fwhm: float) -> np.ndarray:
    return np.exp(-0.5 * ((lam - centre) / (fwhm * _FWHM_TO_SIGMA)) ** 2)


def emission(components: tuple[tuple[float, float, float], ...], wavelengths_nm: ArrayLike) -> np.ndarray:
    """A white LED's relative emission (peak 1) from its Gaussian components and the floor."""
    lam = np.asarray(wavelengths_nm, dtype=float)
    shape = np.full(lam.shape, LED_FLOOR)
    for c, w, h in components:
        shape += h * _gaussian(lam, c, w)
    return shape / shape.max()


def as7341_response(wavelengths_nm: ArrayLike) -> dict[str, np.ndarray]:
    """Each spectral channel's relative response (peak 1)."""
    lam = np.asarray(wavelengths_nm, dtype=float)
    return {name: _gaussian(lam, c, w) for name, (c, w) in AS7341_CHANNELS.items()}


def as7341_weights(wavelengths_nm: ArrayLike | None = None) -> BandWeights:
    """The AS7341 build's band weights: each channel's response under the panels (diffuse: I_b, I_w)
    and under the collimated LED (I_c)."""
    lam = np.arange(*WEIGHTS_GRID_NM) if wavelengths_nm is None else np.asarray(wavelengths_nm, dtype=float)
    response = as7341_response(lam)
    panels, beam = emission(PANEL_LEDS, lam), emission(BEAM_LED, lam)
    names = tuple(response)
    return band_weights(lam, names, np.stack([response[n] * panels for n in names]),
                        np.stack([response[n] * beam for n in names]), where="AS7341 model")


def slit_matrix(wavelengths_nm: ArrayLike, fwhm_nm: float = SLIT_FWHM_NM) -> np.ndarray:
    """(N, N): what each pixel reads of a spectrum sampled at the pixels (rows sum to 1)."""
    lam = np.asarray(wavelengths_nm, dtype=float)
    M = _gaussian(lam[:, None] - lam[None, :], 0.0, fwhm_nm) * np.gradient(lam)[None, :]
    return M / M.sum(axis=1, keepdims=True)


def c12880_coefficients() -> tuple[float, ...]:
    """A typical unit's test-sheet polynomial (A0, B1..B5): the register map's defaults."""
    from trimeter import registers as regs

    return tuple(float(regs.BY_NAME[f"spectro_wl_{k}"].default) for k in ("a0", "b1", "b2", "b3", "b4", "b5"))


def c12880_wavelengths_nm(coefficients: ArrayLike | None = None) -> np.ndarray:
    """Each pixel's wavelength, nm, from a test-sheet polynomial λ(p) = A0 + B1 p + … + B5 p⁵, p = 1..288."""
    c = np.asarray(c12880_coefficients() if coefficients is None else coefficients, dtype=float)
    return np.polynomial.polynomial.polyval(np.arange(1, C12880_PIXELS + 1, dtype=float), c)


def resample_matrix(source_nm: ArrayLike, target_nm: ArrayLike, fwhm_nm: float) -> np.ndarray:
    """(targets, sources): what a detector with pixels at target_nm and a Gaussian line-spread function of
    fwhm_nm reads of a spectrum sampled at source_nm (rows sum to 1: a weighted mean; rows whose line-spread
    function misses the source grid are NaN)."""
    src, dst = np.asarray(source_nm, dtype=float), np.asarray(target_nm, dtype=float)
    M = _gaussian(src[None, :] - dst[:, None], 0.0, fwhm_nm) * np.gradient(src)[None, :]
    total = M.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 1e-6 * fwhm_nm, M / total, np.nan)
def read_band_weights(path: str | Path, what: str = "weights") -> BandWeights:
    """Measured band weights from a CSV (`wavelength_nm`, `<CH>_diffuse`, `<CH>_collimated` per channel),
    read by trimeter.tables; every problem is one InputError."""
    from trimeter.tables import read_columns

    path = Path(path)
    name = f"{what} {path}"
    table = read_columns(path, required=("wavelength_nm",), max_bytes=MAX_WEIGHTS_BYTES, what=what)
    names = [c[: -len("_diffuse")] for c in table if c.endswith("_diffuse")]
    lonely = [c[: -len("_collimated")] for c in table if c.endswith("_collimated")
              and c[: -len("_collimated")] not in names]
    if not names:
        raise InputError(f"{name}: no <channel>_diffuse columns (have: {', '.join(table)})")
    without = [n for n in names if f"{n}_collimated" not in table]
    if without or lonely:
        raise InputError(f"{name}: each channel needs both <channel>_diffuse and <channel>_collimated "
                         f"(incomplete: {', '.join(without + lonely)})")
    return band_weights(table["wavelength_nm"], names, [table[f"{n}_diffuse"] for n in names],
                        [table[f"{n}_collimated"] for n in names], where=name)
