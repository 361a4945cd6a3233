"""trimeter: measure spectral bulk optical properties (albedo, extinction, HG g) of translucent samples.

Data flows one way: device -> raw spectra -> reflectances -> map inversion -> parameters -> files/plots.
"""

from typing import TYPE_CHECKING, Any

from trimeter.version import __version__ as __version__  # re-exported: `trimeter.__version__`

if TYPE_CHECKING:  # what the lazy names below resolve to, for type checkers and the API reference
    from trimeter.inversion.artifacts import fit, open_map
    from trimeter.prediction import predict
    from trimeter.results.reader import Measurement, load

__all__ = ["Measurement", "fit", "load", "open_map", "predict"]


# The Python API, each name imported from its module on first use so `import trimeter` stays light: `fit` the
# inversion on maps by name or path, `load` a results directory, `predict` a slab's look, `open_map` by name.
_LAZY = {"fit": "trimeter.inversion.artifacts", "load": "trimeter.results.reader",
         "Measurement": "trimeter.results.reader", "predict": "trimeter.prediction",
         "open_map": "trimeter.inversion.artifacts"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        # kept as a module global: later uses find it directly instead of coming back here to import
        value = globals()[name] = getattr(importlib.import_module(_LAZY[name]), name)
        return value
    raise AttributeError(f"module 'trimeter' has no attribute {name!r}")
