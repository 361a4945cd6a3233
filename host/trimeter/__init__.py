"""trimeter: measure spectral bulk optical properties (albedo, extinction, HG g) of translucent samples.

Data flows one way: device -> raw spectra -> reflectances -> map inversion -> parameters -> files/plots.
"""

__version__ = "0.1.0"
