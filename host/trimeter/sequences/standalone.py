"""A standalone press's result, as a measurement: what the device kept of its last press (file
standalone_result: its calibration, the sample's dark-subtracted rates and its own fit with its active map
table; hardware/registers.toml, enums.standalone_*) turned into the Measurement the results writer stores,
with provenance saying it was captured and fitted on the device with no host attached.

Nothing is fitted again here: α, σt, g and their flags are the device's; the reflectances are the device's
ratios recomputed from the same rates (NaN where the device gave the fit no input: unlit or saturated bins).
The device computes no standard errors (NaN columns).

A press whose lamps' light differed from the calibration's (status lamp_changed: the device's lamp-monitor
photodiodes against its calibration press's) is still a measurement, recorded with its lamp levels, but a
biased one: `recalibrate_advice` says so, in the words the operator reads. A calibration press the device
refused (its references did not look like an empty holder; the calibration it had still holds) is explained by
`calibration_refusal`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from trimeter import registers as regs
from trimeter.domain import Calibration, Capture, InstrumentInfo, Measurement, Provenance, Reflectances, Sample
from trimeter.domain.capture import CaptureFlag, RawSample
from trimeter.domain.measurement import DeviceTableCheck, SampleCapture
from trimeter.domain.parameters import FitResult
from trimeter.errors import DeviceError
from trimeter.results.writer import Parameters
from trimeter.sequences.lamp_monitor import LAMP_NAMES

if TYPE_CHECKING:
    from trimeter.device import Device
    from trimeter.device.client import StandaloneResult
    from trimeter.formats.device_table import DeviceTable

SETUPS = (("black", "black"), ("white", "white"), ("collimated", "open"))  # (RawSample field, device set-up)
MEASUREMENTS = (regs.StandaloneStatus.DONE, regs.StandaloneStatus.FLAGGED, regs.StandaloneStatus.LAMP_CHANGED)


def read_standalone(device: Device) -> tuple[Measurement, StandaloneResult]:
    """The device's last standalone measurement and the raw result it came from. DeviceError when the last
    press was no measurement (a calibration, a refusal, none since the device started) or when the device's
    active table is no longer the one it fitted with."""
    from trimeter.device.client import table_own_crc32
    from trimeter.device.table_cache import instrument_table

    result = device.standalone_result()
    if result.status == regs.StandaloneStatus.CALIBRATION_REFUSED:
        values = device.read_many("standalone_check", "standalone_check_value")
        raise DeviceError(f"the device's last standalone press was a calibration it refused: "
                          f"{calibration_refusal(values['standalone_check'], values['standalone_check_value'])}")
    if result.status == regs.StandaloneStatus.CALIBRATED:
        raise DeviceError("the device's last standalone press was a calibration: insert a sample and press again")
    if result.status not in MEASUREMENTS:
        raise DeviceError(f"the device's last standalone press ended {result.status.name.lower()}: it holds no "
                          "measurement (hardware/registers.md, standalone_status)")
    identity = device.check_identity()
    table, slot, _ = instrument_table(device)
    if table_own_crc32(table.to_bytes()) != result.table_crc32:
        raise DeviceError("the device's active map table changed since its last standalone press: the table that "
                          "fitted it is gone, so its result cannot be recorded with its table")
    return measurement_of(result, table, slot, InstrumentInfo.of(identity)), result


def recalibrate_advice(result: StandaloneResult) -> str | None:
    """The line that tells the operator to calibrate again when the lamps changed since the device's calibration
    (status lamp_changed); None when they did not."""
    from trimeter.device.client import STANDALONE_LAMP_TOLERANCE

    if result.status != regs.StandaloneStatus.LAMP_CHANGED:
        return None
    changed = result.changed_lamps()
    what = "; ".join(f"the {LAMP_NAMES[lamp]} gave {level:.1%} of its light at the calibration"
                     for lamp, level in changed.items()) or "a lamp's light changed"
    return (f"RECALIBRATE: {what} (lamp monitor, bound ±{STANDALONE_LAMP_TOLERANCE:.0%}): this result is biased "
            "(α by about a third of the change, σt by up to all of it). Empty the holder, run `trimeter device "
            "standalone calibrate`, press the button, then measure again (replace a lamp that keeps dimming).")


def calibration_refusal(check: regs.StandaloneCheck, value: float) -> str:
    """Why the device refused a calibration press (standalone_check, and what it saw), in the words the operator
    acts on; the bounds are the host calibration's (trimeter.sequences.checks), declared once for both."""
    from trimeter.sequences.checks import RHO_BLACK_AGREEMENT, RHO_BLACK_MAX

    holder = regs.StandaloneHolder
    beam_bound = holder.BEAM_AGREEMENT_PERMILLE / 1000
    again = "Empty the holder and press the button again (the calibration the device had still holds)."
    reasons = {
        regs.StandaloneCheck.LITTLE_LIGHT: f"only {value:.0%} of the bins had light from both lamps (expected ≥ "
                                           f"{holder.MIN_LIT_PERMILLE / 1000:.0%}): something opaque covers the "
                                           "holder, or a lamp, a shutter or the spectrometer failed.",
        regs.StandaloneCheck.SLOTS_SWAPPED: f"ρ_black {value:.3g} is at or above the white reference's: the black and "
                                            "white slots seem swapped, or the white reference is missing.",
        regs.StandaloneCheck.HOLDER_NOT_EMPTY: f"ρ_black {value:.2f} (expected ≤ {RHO_BLACK_MAX:g}): a sample seems "
                                               f"to be in the holder. {again}",
        regs.StandaloneCheck.RHO_BLACK_CHANGED: f"ρ_black changed by {value:.3f} from the device's calibration (bound "
                                                f"{RHO_BLACK_AGREEMENT:g}): something is in the holder or on the black "
                                                f"background. {again}",
        regs.StandaloneCheck.BEAM_CHANGED: f"the collimated beam gives {value:.0%} of its light at the device's "
                                           f"calibration, per its lamp's own light (bound ±{beam_bound:.0%}): "
                                           f"something is in the beam. {again} If the collimated LED was replaced, "
                                           "`trimeter device standalone calibrate --force` accepts it.",
    }
    return reasons.get(check, f"check {int(check)} failed (value {value:g})")


def measurement_of(result: StandaloneResult, table: DeviceTable, slot: str, instrument: InstrumentInfo) -> Measurement:
    """The Measurement of a standalone result fitted with `table` (the device's active one, in `slot`)."""
    b = result.bins
    wl = b["wavelength_nm"].astype(float)
    capture_flags = b["capture_flags"].astype(np.int32)
    no_light = (capture_flags & int(CaptureFlag.NO_REFERENCE_LIGHT)) != 0
    saturated = (capture_flags & int(CaptureFlag.SATURATED)) != 0
    diffuse, collimated = b["diffuse"].astype(float), b["collimated"].astype(float)
    calibration = Calibration(
        wl, np.where(no_light, np.nan, diffuse), np.where(no_light, np.nan, collimated), b["rho_black"].astype(float),
        result.rho_white, np.where(no_light, int(CaptureFlag.NO_REFERENCE_LIGHT), 0).astype(np.int32),
        spectrometer={"model": "C12880MA", "on_device": True, "bins": "adjacent pixel pairs"}, device=instrument)
    empty = np.empty((0, len(wl)))
    captures = {field: Capture(b[setup].astype(float), saturated, np.empty(0), empty, empty)
                for field, setup in SETUPS}
    raw = RawSample(wl, captures["black"], captures["white"], captures["collimated"])
    usable = ~no_light & ~saturated
    with np.errstate(invalid="ignore", divide="ignore"):
        i_b, i_w = captures["black"].rate / diffuse, captures["white"].rate / diffuse
        i_c = captures["collimated"].rate / collimated
    nan = np.float64("nan")
    reflectances = Reflectances(wl, np.where(usable, i_b, nan), np.where(usable, i_w, nan), np.where(usable, i_c, nan),
                                np.where(usable, calibration.rho_black, nan), np.full(len(wl), result.rho_white),
                                capture_flags)
    stds = np.full(len(wl), np.nan)
    fit = FitResult(b["alpha"].astype(float), b["sigma_t"].astype(float), b["g"].astype(float), stds, stds.copy(),
                    stds.copy(), b["fit_flags"].astype(np.int32), table.setup.beer_lambert_sigma_t(reflectances.I_c),
                    "lut")
    # the device fitted for its table's ℓ (it refuses any other); its register holds it in single precision
    sample = Sample(table.thickness_mm, table)
    sample.check_map()
    provenance = Provenance(
        method="lut", instrument=instrument,
        device_map_table=DeviceTableCheck(slot, True, f"0x{result.table_crc32:08x}", map=table.name),
        extra={"fitted_on": "device", "hostless": True,
               "standalone": {"status": result.status.name.lower(), "sequence": result.sequence,
                              "flagged_bins": result.flagged_bins, "integration_us": result.integration_us,
                              "white_reference_reflectance": result.rho_white,
                              # against the calibration's light; None: not compared
                              "lamp_levels": {lamp: level if np.isfinite(level) else None
                                              for lamp, level in result.lamp_levels.items()},
                              "recalibrate": result.status == regs.StandaloneStatus.LAMP_CHANGED}})
    return Measurement(calibration, [SampleCapture(sample, raw, reflectances)],
                       Parameters.from_fit(wl, fit, thickness_mm=sample.thickness_mm), provenance=provenance)
