"""Appearance maps: the (α, σt, g) → (I_b, I_w, I_c) relation rendered once per sample set-up."""

from trimeter.maps.appearance import AppearanceMap, find_map, shipped_maps

__all__ = ["AppearanceMap", "find_map", "shipped_maps"]
