"""The light the twin's optics put on the firmware sim's C12880MA (firmware/ports/sim/c12880_chip.h).

The chip model lives in the firmware sim (the firmware captures, not the host); it composes the light
itself from the plant's slot, shutters and LED levels, as trimeter.twin.optics.Optics.rate does, out of four
components the twin sends over the plant socket whenever they change (a sample inserted, the lamps' warm-up):
    diffuse_black  panels · (I_b | ρ_black)      diffuse_white  panels · (I_w | ρ_white)
    diffuse_open   panels · (I(ρ=0) | 0)         beam_open      beam · (I_c | 1)
each in counts/s per nm at gain 1 on GRID_NM. The lamps' spectra are sent at their current shape but nominal
magnitude: the plant multiplies by each lamp's emission (the twin's lamp_* feed, warm-up droop included)
as it does for the lamp-monitor photodiodes. Brightness: the white reference under warm panels peaks at
WHITE_PEAK_COUNTS_PER_S_NM.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from trimeter.twin.optics import Optics

GRID_NM = (300.0, 5.0, 121)            # start, step, samples: 300..900 nm, the chip's 308..885 inside
WHITE_PEAK_COUNTS_PER_S_NM = 2.0e5     # the white reference's peak under warm panels, at gain 1
RESEND = 2e-3                          # relative change of a component that is sent again


class C12880Light:
    def __init__(self, optics: Optics) -> None:
        lam = optics.wavelengths_nm
        self.grid_nm = GRID_NM[0] + GRID_NM[1] * np.arange(GRID_NM[2])
        self._per_nm = 1.0 / np.gradient(lam)
        warm_white = optics.panels.spectrum(1.0) / self._droop(optics.panels, 1.0) * optics.rho_white * self._per_nm
        self._scale = WHITE_PEAK_COUNTS_PER_S_NM / float(np.max(warm_white))
        self._sent: dict[str, np.ndarray] = {}

    @staticmethod
    def _droop(led: object, heat: float | None = None) -> float:
        spectrum = led.spectrum  # type: ignore[attr-defined]
        return float(spectrum(heat).sum() / spectrum(0.0).sum())

    def components(self, optics: Optics) -> dict[str, np.ndarray]:
        lam, s = optics.wavelengths_nm, optics.sample
        panels = optics.panels.spectrum() / self._droop(optics.panels)
        beam = optics.collimated.spectrum() / self._droop(optics.collimated)
        parts = {"diffuse_black": panels * (s.I_b if s else optics.rho_black),
                 "diffuse_white": panels * (s.I_w if s else optics.rho_white),
                 "diffuse_open": panels * s.I_open if s else np.zeros_like(lam),
                 "beam_open": beam * (s.I_c if s else 1.0)}
        return {k: np.interp(self.grid_nm, lam, v * self._per_nm * self._scale, left=0.0, right=0.0)
                for k, v in parts.items()}

    def requests(self, optics: Optics, force: bool = False) -> list[dict]:
        """The plant requests that bring the chip's light up to date (none when nothing changed)."""
        out = []
        for name, values in self.components(optics).items():
            sent = self._sent.get(name)
            if not force and sent is not None and np.all(np.abs(values - sent) <= RESEND * max(float(sent.max()), 1.0)):
                continue
            out.append({"cmd": "spectro_light", "component": name, "start_nm": GRID_NM[0], "step_nm": GRID_NM[1],
                        "values": [round(float(v), 1) for v in values]})
            self._sent[name] = values
        return out
