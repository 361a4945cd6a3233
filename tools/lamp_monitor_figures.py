"""What a dimmed lamp does to a measurement on the twin, and whether the lamp monitor refuses it.

    .venv/bin/python tools/lamp_monitor_figures.py [--time-scale 50] [--seed 3] [--map MAP.tmap]

The twin (the real firmware, its plant's photodiodes, the HIL map's optics, sample cyan-ink 0.4 mm) is
warmed up and calibrated with the holder empty; then, per case, a lamp is dimmed (twin fault lamp_dimmed)
and the sample captured and fitted as `measure` does. Printed per case: the median error of α and the
median relative error of σt against the twin's truth (what would have been written without the monitor),
and the verdict of the shot checks — the spectra-only ones (the triple is physically possible) and the
lamp monitor's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from trimeter.device import Device
from trimeter.domain import Sample, SampleCapture
from trimeter.formats.appearance import AppearanceMap
from trimeter.sequences import checks, lamp_monitor
from trimeter.sequences.measure import prepare_fit
from trimeter.sequences.plans import calibration, sample_capture, warm_up
from trimeter.sequences.reflectance import reflectances
from trimeter.sequences.service import lamps_on
from trimeter.sequences.steps import Runner
from trimeter.spectrometer import open_spectrometer
from trimeter.twin import Twin

# The HIL suite's set-up (tests/hil_support.py), named here as data rather than imported from the tests.
HIL_MAP = Path(__file__).resolve().parents[1] / "tests" / "hil" / "data" / "hil-ideal-l0.4.tmap"
SAMPLE = "cyan-ink"
THICKNESS_MM = 0.4
CASES = (None, "panels:0.5", "panels:0.8", "collimated:0.5", "panels:0.97", "panels:0.99", "collimated:0.98")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--time-scale", type=float, default=50.0)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--map", type=Path, default=HIL_MAP, help="the host's map (default: the HIL suite's)")
    args = parser.parse_args()
    amap = AppearanceMap.load(args.map)
    with Twin(sample=None, thickness_mm=THICKNESS_MM, time_scale=args.time_scale, appearance_map=amap,
              seed=args.seed) as twin:
        assert twin.modbus_port is not None  # set by start()
        device = Device.open(twin.modbus_port, timeout_s=0.2)
        spectrometer = open_spectrometer(twin.spectrometer_url)
        runner = Runner(device, spectrometer)
        lamps_on(device)
        runner.run(warm_up(threshold=0.002, interval_s=10.0, timeout_s=900.0))
        cal = runner.run(calibration(white_reference_reflectance=0.99))
        assert not checks.calibration_problems(cal), checks.calibration_problems(cal)
        twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        truth = twin.control.truth()
        assert truth is not None  # the sample was just inserted
        fit = prepare_fit([Sample(THICKNESS_MM, amap)], "lut")
        print(f"{'lamp_dimmed':<16} {'median Δα':>10} {'median ΔσT/σT':>14}  spectra-only checks | lamp monitor")
        for case in CASES:
            twin.control.set_fault(lamp_dimmed=case)
            raw = runner.run(sample_capture(frames=2, hdr_decades=2))
            refl = reflectances(cal, raw)
            params, _ = fit.fit([SampleCapture(fit.samples[0], raw, refl)])
            true = {k: np.interp(refl.wavelengths_nm, truth["wavelengths_nm"], truth[k]) for k in ("alpha", "sigma_t")}
            d_alpha = float(np.nanmedian(params.alpha - true["alpha"]))
            d_sigma = float(np.nanmedian(params.sigma_t / true["sigma_t"] - 1.0))
            spectra_only = checks.shot_problems(refl, amap)
            spectra_only = [p for p in spectra_only if "lamp monitor" not in p]
            spectra_only += checks.fit_problems(params.flags, checks.usable_bins(refl))
            monitor = lamp_monitor.shot_problems(refl.lamp_light)
            print(f"{case or 'none':<16} {d_alpha:>+10.3f} {d_sigma:>+14.1%}  "
                  f"{'refused' if spectra_only else 'accepted':<19} | {'refused' if monitor else 'accepted'}"
                  + (f": {monitor[0][:110]}" if monitor else ""))
        device.close()
        spectrometer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
