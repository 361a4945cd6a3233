"""Domain data at the bottom of the package: what the instrument captures, its calibration, the
reflectances derived from them and a measurement with its provenance. Pure data and pure functions:
devices, sequences, the inversion and the results writer all import downward from here."""

from trimeter.domain.calibration import Calibration
from trimeter.domain.capture import Capture, CaptureFlag, RawSample
from trimeter.domain.instrument import InstrumentInfo
from trimeter.domain.measurement import MapIdentity, Measurement, Provenance, Sample, SampleCapture
from trimeter.domain.reflectances import Reflectances

__all__ = ["Calibration", "Capture", "CaptureFlag", "InstrumentInfo", "MapIdentity", "Measurement", "Provenance",
           "RawSample", "Reflectances", "Sample", "SampleCapture"]
