"""Measurement sequences as plans: generators of steps executed by a Runner (or by a test).

    runner = Runner(device, spectrometer)
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    raw = runner.run(sample_capture())
    refl = reflectances(cal, raw)              # the paper's ratios
    combined, per = fit_reflectances([refl], [amap])   # through trimeter.fit (sequences.measure)
"""

from trimeter.sequences.plans import calibration, sample_capture, warm_up
from trimeter.sequences.reflectance import Calibration, CaptureFlag, RawSample, Reflectances, reflectances
from trimeter.sequences.steps import Runner

__all__ = ["Calibration", "CaptureFlag", "RawSample", "Reflectances", "Runner", "calibration", "reflectances",
           "sample_capture", "warm_up"]
