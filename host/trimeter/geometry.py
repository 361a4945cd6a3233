"""The instrument geometry, loaded from hardware/geometry.toml (its one declaration)."""

from __future__ import annotations

import tomllib
from functools import lru_cache

from trimeter.errors import InputError
from trimeter.paths import GEOMETRY_FILE

PRESETS = ("ideal", "device")


@lru_cache(maxsize=1)
def _load_all() -> dict:
    with open(GEOMETRY_FILE, "rb") as f:
        return tomllib.load(f)


def load_geometry(preset: str) -> dict:
    """Return the named preset as a plain dict (a copy: callers may store it in a map's metadata)."""
    if preset not in PRESETS:
        raise InputError(f"geometry must be one of {', '.join(PRESETS)}, got {preset!r}")
    import copy

    return copy.deepcopy(_load_all()[preset])


def cover_slide_n(params: dict) -> float | None:
    """The cover slides' refractive index for a geometry's parameters, None without slides (the
    argument trimeter.model.collimated takes)."""
    return float(params["cover_slide_n"]) if params.get("cover_slides") else None


def cover_slide_thickness_mm(params: dict) -> float:
    """Each cover slide's thickness for a geometry's parameters, 0 without slides."""
    return float(params["cover_slide_thickness_mm"]) if params.get("cover_slides") else 0.0
