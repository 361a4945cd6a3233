"""The twin: the simulated instrument (firmware sim + plant + optics + spectrometer + fault injection).

Contract (Python API, control socket, spectrometer line protocol): README.md in this package.
"""

from trimeter.twin.faults import FaultConfig
from trimeter.twin.twin import Twin, TwinClient, TwinControl

__all__ = ["Twin", "TwinClient", "TwinControl", "FaultConfig"]
