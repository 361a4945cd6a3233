"""The held-out sets `bench fit` and its kin score on: off-grid materials rendered directly, never map grid
points (maps/heldout/<map-name>.held, made by tools/make_heldout.py), their split into a calibration and a
scored part, and their intensities at given backgrounds."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from trimeter.errors import InputError
from trimeter.paths import MAPS_DIR

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap

Heldout = dict[str, np.ndarray]  # a held-out set's arrays by name
HELDOUT_DIR = MAPS_DIR / "heldout"


def heldout_for(amap: AppearanceMap) -> tuple[Path, dict[str, Any], Heldout]:
    from trimeter.errors import MapFileError
    from trimeter.formats.container import read_container

    # a set next to the map first: a map built elsewhere is scored on its own set, not on the shipped one
    candidates = [amap.path.with_suffix(".held")] if amap.path is not None else []
    candidates.append(HELDOUT_DIR / f"{amap.name}.held")
    for path in candidates:
        if path.is_file():
            meta, arrays, _ = read_container(path, "heldout-set")
            # a set rendered for another set-up or model would score the map against the wrong physics
            if not isinstance(meta.get("recipe"), dict):
                raise MapFileError(f"{path} does not say what it was rendered for (no recipe in its header): make "
                                   "it with tools/make_heldout.py")
            made, built = (_setup(meta["recipe"]), _setup({**amap.recipe, "n": amap.n,
                                                           "thickness_mm": amap.thickness_mm}))
            if made != built:
                raise MapFileError(f"{path} was rendered for {made}, the map {amap.name} is {built}: make its set "
                                   "with tools/make_heldout.py")
            return path, meta, {k: np.asarray(v, dtype=float) for k, v in arrays.items()}
    raise MapFileError(f"no held-out set for map {amap.name} (looked for {', '.join(map(str, candidates))}); "
                       f"make one with tools/make_heldout.py")


def _setup(recipe: dict[str, Any]) -> str:
    """A recipe's set-up and model, as far as a held-out set must match its map's."""
    from trimeter.maps.recipe import fresnel_model

    return (f"geometry {recipe.get('geometry')!r}, n {recipe.get('n')}, ℓ {recipe.get('thickness_mm')} mm, "
            f"Fresnel {fresnel_model(recipe.get('polarisation', False))}")


# The held-out materials are split once, here: every CALIBRATION_EVERY-th (σt, g) column (materials that
# share σt and g were traced together, so their errors are correlated: a column stays whole) in the order
# the set lists them is the calibration part, on which map-error constants are chosen
# (trimeter.model.grid.LEAVE_ONE_OUT_SCALE); the rest, the scored part, is what coverage is reported on.
CALIBRATION_EVERY = 4
HELDOUT_PARTS = ("scored", "calibration")


def heldout_part(h: Heldout, part: str) -> Heldout:
    """The `part` ("scored" or "calibration") of a held-out set: its arrays restricted to those materials."""
    if part not in HELDOUT_PARTS:
        raise InputError(f"held-out part must be one of {', '.join(HELDOUT_PARTS)}, got {part!r}")
    pairs = np.column_stack([h["sigma_t"], h["g"]])
    _, first, column = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))  # each column's rank by where it first appears
    calibration = order[column.ravel()] % CALIBRATION_EVERY == 0
    keep = calibration if part == "calibration" else ~calibration
    return {k: v[keep] for k, v in h.items()}


def heldout_intensities(h: Heldout, rho_b: float | np.ndarray,
                        rho_w: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I_b, I_w) of the held-out materials at the backgrounds, from their rendered A, B, C."""
    from trimeter.model.response import background_response

    return background_response(h["A"], h["B"], h["C"], rho_b), background_response(h["A"], h["B"], h["C"], rho_w)


def heldout_collimated(amap: AppearanceMap, h: Heldout, index: slice | np.ndarray = slice(None)) -> np.ndarray:
    """I_c of the held-out materials: the unscattered beam, and the light scattered into the detector's
    aperture where the set has it traced (tools/make_heldout.py --inscatter)."""
    unscattered = amap.collimated(h["sigma_t"][index])
    return unscattered * np.exp(h["inscatter_log1p"][index]) if "inscatter_log1p" in h else unscattered
