"""trimeter: measure spectral bulk optical properties (albedo, extinction, HG g) of translucent samples.

Data flows one way: device -> raw spectra -> reflectances -> map inversion -> parameters -> files/plots.
"""

from typing import Any

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    # `trimeter.fit(...)` is the inversion entry point on maps by name or path (trimeter.maps.artifacts);
    # imported lazily so `import trimeter` stays light.
    if name == "fit":
        from trimeter.maps.artifacts import fit

        return fit
    raise AttributeError(f"module 'trimeter' has no attribute {name!r}")
