"""Measurement sequences as plans: generators of steps executed by a Runner (or by a test).

    runner = Runner(device, spectrometer)
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    raw = runner.run(sample_capture())
    refl = reflectances(cal, raw)              # the paper's ratios

The one-shot pipeline (capture → fit → write) is sequences.measure.measure; the data it works on
(Calibration, RawSample, Reflectances, Measurement) lives in trimeter.domain.
"""

from trimeter.sequences.plans import calibration, sample_capture, warm_up
from trimeter.sequences.reflectance import reflectances
from trimeter.sequences.steps import Runner

__all__ = ["Runner", "calibration", "reflectances", "sample_capture", "warm_up"]
