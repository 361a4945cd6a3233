"""From reflectances to parameters (through `trimeter.fit`), and the map that belongs to a thickness.

Kept apart from the plans: this is pure computation on files and arrays, used identically by
`trimeter measure`, `trimeter serve`, `trimeter demo` and offline re-fits of saved raw data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trimeter.errors import InputError
from trimeter.maps.appearance import AppearanceMap, find_map, shipped_maps
from trimeter.results.writer import Parameters
from trimeter.sequences.reflectance import Reflectances


def map_for_thickness(thickness_mm: float, explicit: str | Path | None = None,
                      search: list[Path] | None = None) -> AppearanceMap:
    """The map named/pathed explicitly, else the shipped map (device geometry first) of this thickness."""
    if explicit:
        amap = AppearanceMap.load(find_map(explicit))
        if abs(amap.thickness_mm - thickness_mm) > 1e-6:
            raise InputError(f"map {amap.name} is for ℓ = {amap.thickness_mm:g} mm, "
                             f"not the sample's {thickness_mm:g} mm")
        return amap
    candidates = []
    for path in (search if search is not None else shipped_maps()):
        try:
            amap = AppearanceMap.load(path)
        except Exception:  # a broken map file must not hide the good ones; `trimeter map info` names it
            continue
        if abs(amap.thickness_mm - thickness_mm) <= 1e-6:
            candidates.append(amap)
    if not candidates:
        raise InputError(f"thickness: no appearance map for ℓ = {thickness_mm:g} mm (give one with --map, or build "
                         "one with `trimeter map build`)")
    candidates.sort(key=lambda m: (m.recipe.get("geometry") != "device", m.name))
    return candidates[0]


def check_map_thicknesses(thicknesses, maps: list[AppearanceMap]) -> None:
    """Each map must be for its sample's declared thickness: a map of another ℓ scales σt by their ratio."""
    for thickness, amap in zip(thicknesses, maps, strict=True):
        thickness = float(thickness)
        if abs(amap.thickness_mm - thickness) > 1e-6 * max(1.0, thickness):
            raise InputError(f"map {amap.name} is for ℓ = {amap.thickness_mm:g} mm, not the declared "
                             f"{thickness:g} mm")


def preflight(maps: list[AppearanceMap], method: str) -> None:
    """Fit one harmless bin with each map before any light is measured: a stale table, a missing model or
    a bad method then fails in a second, not after a whole capture."""
    import trimeter

    for amap in maps:
        trimeter.fit(amap, [0.2], [0.5], [0.1], method=method)


def fit_reflectances(refls: list[Reflectances], maps: list[AppearanceMap], *, method: str = "lut"
                     ) -> tuple[Parameters, list[Parameters]]:
    """trimeter.fit over one or two thicknesses; returns (combined, per-thickness estimates)."""
    import trimeter

    if len(refls) != len(maps) or not refls:
        raise InputError("need one map per measured thickness")
    wl = refls[0].wavelengths_nm
    # The fit's noise model σ_I = noise_rel·I + noise_abs, with noise_rel measured from the frame spread
    # (so the reported uncertainties are this measurement's, not a default's).
    measured = [r.noise_rel() for r in refls]
    noise = {"noise_rel": float(np.clip(max(measured), 1e-4, 0.2))} if all(m is not None for m in measured) else {}
    # and each bin's own stds from the capture (frame scatter, dark, the calibration's), where it has them
    for name in ("I_b_std", "I_w_std", "I_c_std"):
        if all(getattr(r, name) is not None for r in refls):
            noise[name] = np.stack([getattr(r, name) for r in refls]) if len(refls) > 1 else getattr(refls[0], name)
    if len(refls) == 1:
        r = refls[0]
        result = trimeter.fit(maps[0], r.I_b, r.I_w, r.I_c, rho_b=r.rho_b, rho_w=r.rho_w, method=method, **noise)
        return Parameters.from_fit(wl, result, thickness_mm=maps[0].thickness_mm), []
    stack = {k: np.stack([getattr(r, k) for r in refls]) for k in ("I_b", "I_w", "I_c", "rho_b", "rho_w")}
    result = trimeter.fit(maps, stack["I_b"], stack["I_w"], stack["I_c"], rho_b=stack["rho_b"], rho_w=stack["rho_w"],
                          method=method, **noise)
    per = [Parameters.from_fit(wl, single, thickness_mm=amap.thickness_mm)
           for single, amap in zip(result.per_thickness, maps, strict=True)]
    return Parameters.from_fit(wl, result), per
