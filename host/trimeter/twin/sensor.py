"""The twin's AS7341: the light the twin's optics put on its fine pixel grid, read through the
AS7341's channel responses (trimeter.spectrometer.sensors) into nine 16-bit channel counts.

What it models, and how (a model, not a characterised chip):
- a channel's count rate is its response times the light per pixel, summed over the pixels; the light
  is the twin's lamps as a silicon detector sees them (trimeter.twin.optics.Led), the response the
  datasheet's band shape;
- gain: counts scale with it (COUNTS_PER_S_AT_GAIN_64 of the brightest channel under the collimated
  beam at gain 64), shot noise in electrons (ELECTRONS_PER_COUNT_AT_GAIN_1 / gain), read noise and a
  small dark offset in counts;
- integration and saturation: the ADC's full scale is min(65535, steps) with the integration time in
  2.78 µs steps; the twin's shortest integration time is 65536 steps, so the full scale is always the
  65535 its description states (the real backend reports the lower full scale of shorter times);
- band weights: what each channel's reading is a weighted mean of (response × the panels' spectrum
  for I_b, I_w; × the collimated LED's for I_c) on the pixel grid — the twin's own, so a host that
  asks for them (`BANDS?`) gets what a user would measure for this unit.
"""

from __future__ import annotations

import numpy as np

from trimeter.inversion.bands import BandWeights, band_weights
from trimeter.spectrometer.i2c import CHANNEL_NM, STEP_US
from trimeter.spectrometer.sensors import as7341_response

COUNTS_PER_S_AT_GAIN_64 = 2.0e5
ELECTRONS_PER_COUNT_AT_GAIN_1 = 64.0
READ_NOISE_COUNTS = 2.0
DARK_OFFSET_COUNTS = 4.0
ADC_MAX_COUNTS = 65535


class As7341Model:
    """Nine channel counts from the twin's per-pixel light (the same interface as optics.SpectrometerModel)."""

    def __init__(self, pixel_nm: np.ndarray, panels: np.ndarray, collimated: np.ndarray, gain: float = 64.0) -> None:
        self.pixel_nm = np.asarray(pixel_nm, dtype=float)
        response = as7341_response(self.pixel_nm)
        self.channels = tuple(CHANNEL_NM)
        self.wavelengths_nm = np.array([CHANNEL_NM[c] for c in self.channels])
        self._density = np.stack([response[c] for c in self.channels])               # (9, pixels) per nm
        self._response = self._density * np.gradient(self.pixel_nm)                   # per pixel
        self.gain = float(gain)
        # counts per (pixel rate unit): the brightest channel under the full beam gives COUNTS_PER_S_AT_GAIN_64
        self._scale = COUNTS_PER_S_AT_GAIN_64 / float(np.max(self._response @ collimated))
        self._panels, self._collimated = np.asarray(panels, float), np.asarray(collimated, float)
        self.dark_pixels: tuple[int, ...] = ()
        self.saturation_counts = float(ADC_MAX_COUNTS)
        self.integration_time_us_limits = (int(np.ceil((ADC_MAX_COUNTS + 1) * STEP_US)), int(256 * 65535 * STEP_US))

    def description(self) -> dict:
        return {"model": "AS7341-TWIN", "serial": "TWINAS01", "pixels": len(self.channels),
                "wavelength_range_nm": [float(self.wavelengths_nm.min()), float(self.wavelengths_nm.max())],
                "integration_time_us_limits": list(self.integration_time_us_limits),
                "saturation_counts": self.saturation_counts, "dark_pixels": [],
                "extra": {"channels": list(self.channels), "gain": self.gain}}

    def band_weights(self) -> BandWeights:
        return band_weights(self.pixel_nm, self.channels, self._density * self._panels,
                            self._density * self._collimated, where="the twin's AS7341")

    def expose(self, rate_counts_per_s: np.ndarray, integration_time_us: int, rng: np.random.Generator) -> np.ndarray:
        """One exposure: per-pixel light (counts/s) → uint16 channel counts with shot, read noise and clipping."""
        t = integration_time_us * 1e-6
        signal = self._response @ np.maximum(np.asarray(rate_counts_per_s, dtype=float), 0.0)
        counts = signal * self._scale * (self.gain / 64.0) * t
        electrons_per_count = ELECTRONS_PER_COUNT_AT_GAIN_1 / self.gain
        collected = rng.poisson(np.minimum(counts * electrons_per_count, 1e12)) / electrons_per_count
        noisy = DARK_OFFSET_COUNTS + collected + rng.normal(0.0, READ_NOISE_COUNTS, collected.shape)
        full = min(ADC_MAX_COUNTS, int(round(integration_time_us / STEP_US)))
        return np.clip(np.rint(noisy), 0, full).astype(np.uint16)
