"""Per-bin fit flags, declared once. Every method and the CLI report these bits; 0 means a clean fit.

A bin whose flag includes any of `UNUSABLE` has α, σt, g = NaN. Other flags qualify a finite result:
it is still inside physical bounds, but read it with the caveat the flag names.
"""

from __future__ import annotations

import enum

import numpy as np


class FitFlag(enum.IntFlag):
    NONE = 0
    NONFINITE_INPUT = 1 << 0      # an intensity or background reflectance is NaN or ±inf  → NaN outputs
    NEGATIVE_INPUT = 1 << 1       # an intensity is < 0 (beyond a small noise tolerance)  → NaN outputs
    ABOVE_ONE = 1 << 2            # an intensity is > 1 (more light than the reference)     → NaN outputs
    BLACK_NOT_BELOW_WHITE = 1 << 3  # I_b ≥ I_w: impossible for a passive sample; fitted, projected onto the gamut
    IC_BELOW_FLOOR = 1 << 4       # I_c under the noise floor: σt is only a lower bound
    G_UNDEFINED = 1 << 5          # α ≈ 0: nothing scatters, the phase function is unobservable → g = NaN
    OUTSIDE_MAP = 1 << 6          # the solution hit the map's range; the value is clamped to the range edge
    NOT_CONVERGED = 1 << 7        # the forward-map residual stayed above tolerance (outside the measurable gamut)
    THICKNESS_DISAGREE = 1 << 8   # two thicknesses disagree beyond their combined uncertainty
    BAD_BACKGROUND = 1 << 9       # ρ_b, ρ_w not in [0, 1] with ρ_b < ρ_w                    → NaN outputs
    # At this thickness the map barely tells α and g apart (first-order std of α > 0.1 or of g > 0.2
    # with the intensities' stds at least the fit's noise model, so that one quiet capture does not
    # hide it): an optically thick sample (I_b ≈ I_w, the background no longer shows through, so only
    # a combination of α and g is determined) or a very thin one. The value solves the map, but so would
    # others; the stds say by how much this capture pinned it down.
    UNDERDETERMINED = 1 << 10
    # The stds are first-order (the map's Jacobian at the solution), and the map is not linear over
    # ±2σ here: (α, g) re-fitted from intensities moved by ±2σ land off the Jacobian's prediction
    # (newton.first_order_holds). The truth lies outside ±2σ more often than 5 %; the stds
    # give the scale only.
    STD_APPROXIMATE = 1 << 11
    # A band-aware fit (trimeter.inversion.bands): the spectra within this channel's band are not pinned
    # by the readings (another interpolation between the channels fits them as well and moves the value
    # at the centre beyond the band tolerances), or the wavelength lies beyond the outermost channels.
    BAND_UNRESOLVED = 1 << 12
    # A multichannel sensor's band readings fitted per channel as if monochromatic: biased wherever the
    # spectrum changes within a band (the band-aware fit, `fit --bands`, takes the bands into account).
    PER_CHANNEL_BANDS = 1 << 13


UNUSABLE = FitFlag.NONFINITE_INPUT | FitFlag.NEGATIVE_INPUT | FitFlag.ABOVE_ONE | FitFlag.BAD_BACKGROUND


def describe(value: int) -> str:
    """'IC_BELOW_FLOOR|G_UNDEFINED' for a flag word (or 'NONE')."""
    names = [f.name for f in FitFlag if f.name and (int(value) & f)]
    return "|".join(names) if names else "NONE"


def advice(flags: np.ndarray | list[int], thicknesses: int = 1, *,
           counts: np.ndarray | list[int] | None = None) -> list[str]:
    """What a person should do about a fit's flagged bins: one sentence per kind of problem, with how
    many of the bins it concerns (empty when nothing needs doing). `thicknesses`: how many samples
    were fitted together. `counts`: how many bins carry each word of `flags` (a streamed fit's tally of
    distinct words), instead of one word per bin."""
    flags = np.asarray(flags, dtype=np.int64)
    weights = np.ones(len(flags), np.int64) if counts is None else np.asarray(counts, dtype=np.int64)
    n = int(weights.sum())

    def count(flag: int) -> int:
        return int(weights[(flags & int(flag)) != 0].sum())

    notes = []
    if k := count(UNUSABLE):
        notes.append(f"{k} of {n} bins are NaN, their input unusable (NaN, negative or above 1, typically where "
                     f"the lamps give too little light to measure; or a bad background reflectance); if that is "
                     f"more than the spectrum's edges, check the capture and the calibration")
    if k := count(FitFlag.UNDERDETERMINED):
        if thicknesses < 2:
            notes.append(f"{k} of {n} bins are UNDERDETERMINED: at this thickness α and g are not told apart "
                         f"at the instrument's usual noise (see their stds); measure a second thickness of the same "
                         f"material (thinner if it is nearly opaque, thicker if nearly clear) and fit both (fit: a "
                         f"second --map; measure: --thickness twice; serve: --second-thickness)")
        else:
            notes.append(f"{k} of {n} bins are UNDERDETERMINED even with {thicknesses} thicknesses "
                         f"(see their stds); a further thickness would constrain them")
    if k := count(FitFlag.IC_BELOW_FLOOR):
        notes.append(f"{k} of {n} bins: I_c is under the noise floor, so σt there is only a lower bound; "
                     f"a thinner sample would measure it")
    if k := count(FitFlag.OUTSIDE_MAP | FitFlag.NOT_CONVERGED):
        notes.append(f"{k} of {n} bins fall outside the map's range (values clamped to its edge or not "
                     f"converged): a map for another thickness may cover them")
    if k := count(FitFlag.STD_APPROXIMATE):
        notes.append(f"{k} of {n} bins are STD_APPROXIMATE: the map bends within their ±2σ, so their stds are "
                     f"a scale, not a ±1σ/±2σ that covers the truth at 68/95 %; lower noise (more frames "
                     f"averaged) or a second thickness narrows them to where first order holds")
    if k := count(FitFlag.PER_CHANNEL_BANDS):
        notes.append(f"{k} of {n} bins are PER_CHANNEL_BANDS: a multichannel sensor's band readings fitted as if "
                     f"monochromatic, biased where the spectrum changes within a band; fit them band-aware "
                     f"(fit --bands WEIGHTS.csv)")
    if k := count(FitFlag.BAND_UNRESOLVED):
        notes.append(f"{k} of {n} bins are BAND_UNRESOLVED: the spectrum changes within that channel's band more "
                     f"than the channels resolve (or the wavelength is beyond the outermost channels); take "
                     f"the value as the band's, or measure with a spectrometer there")
    if k := count(FitFlag.THICKNESS_DISAGREE):
        notes.append(f"{k} of {n} bins: the thicknesses disagree beyond their uncertainty; check the stated "
                     f"thicknesses and that both samples are the same material")
    return notes
