"""The package's version, at the bottom of the layers: files and stamps record it, and importing it pulls
in nothing else (the package's __init__ reaches the whole API)."""

__version__ = "0.1.0"
