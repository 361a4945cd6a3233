"""From samples to a written results directory: the one door into the inversion (`prepare_fit`) and the
one-shot pipeline (capture → fit → write, `measure`) that `trimeter measure`, `trimeter serve`, the web
page and the tests all call. The web page's re-fit of saved captures enters through `prepare_fit` too.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from trimeter.domain import Calibration, InstrumentInfo, Measurement, Provenance, Sample, SampleCapture
from trimeter.domain.measurement import DeviceTableCheck, Estimate
from trimeter.domain.parameters import FitResult
from trimeter.errors import CheckError, DeviceError, InputError, TrimeterError
from trimeter.inversion.methods import METHODS
from trimeter.inversion.flags import FitFlag, advice
from trimeter.formats.appearance import AppearanceMap, find_map, shipped_maps
from trimeter.formats.device_table import DeviceTable
from trimeter.results.spool import CaptureSpooled, prepare_results_dir, write_or_spool
from trimeter.results.writer import Parameters
from trimeter.sequences.checks import calibration_problems, fit_problems, shot_problems, usable_bins
from trimeter.sequences.plans import sample_capture
from trimeter.sequences.reflectance import reflectances
from trimeter.sequences.settings import HostSettings
from trimeter.sequences.steps import Runner

if TYPE_CHECKING:
    from trimeter.inversion.bands import BandWeights
    from trimeter.spectrometer import Spectrometer


def map_for_thickness(thickness_mm: float, explicit: str | Path | None = None,
                      search: list[Path] | None = None) -> AppearanceMap:
    """The map named/pathed explicitly, else the shipped map (device geometry first) of this thickness."""
    if explicit:
        amap = AppearanceMap.load(find_map(explicit))
        Sample(thickness_mm, amap).check_map()
        return amap
    candidates = []
    for path in (search if search is not None else shipped_maps()):
        try:
            amap = AppearanceMap.load(path)
        except Exception:  # a broken map file must not hide the good ones; `trimeter map info` names it
            continue
        if amap.setup.matches_thickness(thickness_mm):
            candidates.append(amap)
    if not candidates:
        raise InputError(f"thickness: no appearance map for ℓ = {thickness_mm:g} mm (give one with --map, or build "
                         "one with `trimeter map build`)")
    candidates.sort(key=lambda m: (m.recipe.get("geometry") != "device", m.name))
    return candidates[0]


def resolve_samples(requests: Iterable[tuple[float, str | Path | None]],
                    instrument_table: Callable[[], DeviceTable] | None = None) -> list[Sample]:
    """(thickness, map name/path or None) pairs → samples with their maps loaded. None: the table the
    instrument carries (`instrument_table()`, read when first needed), which the first such sample must be
    for; a later sample of another thickness (the instrument holds one table) falls back to the shipped
    map of its thickness. Without `instrument_table`, None means the shipped map."""
    samples: list[Sample] = []
    table: DeviceTable | None = None
    for thickness, explicit in requests:
        if explicit or instrument_table is None:
            samples.append(Sample(thickness, map_for_thickness(thickness, explicit)))
            continue
        if table is None:
            table = instrument_table()
            check_instrument_table(table, thickness)
        if table.setup.matches_thickness(thickness):
            samples.append(Sample(thickness, table))
        else:
            samples.append(Sample(thickness, map_for_thickness(thickness)))
    return samples


def check_instrument_table(table: DeviceTable, thickness_mm: float) -> None:
    """InputError unless the instrument's table is for the declared thickness."""
    if not table.setup.matches_thickness(thickness_mm):
        raise InputError(f"thickness: the instrument's map table {table.name} is for ℓ = {table.thickness_mm:g} mm, "
                         f"not the declared {thickness_mm:g} mm (σt would come out ×"
                         f"{thickness_mm / table.thickness_mm:.3g}); flash the table for {thickness_mm:g} mm "
                         f"(`trimeter map flash`) or pass --map")


@dataclass(frozen=True)
class PreparedFit:
    """What the fit of these samples needs, checked before any light is measured. Built by `prepare_fit`."""

    samples: tuple[Sample, ...]
    method: str
    # a multichannel sensor's band weights (its bins are its channels, in order): the fit is band-aware
    bands: BandWeights | None = None
    # the bins are a multichannel sensor's channels: fitted per channel, every value is PER_CHANNEL_BANDS
    multichannel: bool = False

    def fit_table_bytes(self) -> bytes | None:
        """The inverse table the fit of the first sample uses (what the device's active map slot should
        hold), or None when the method fits without one."""
        if self.method != "lut":
            return None
        from trimeter.inversion.artifacts import load_artifacts

        return load_artifacts(self.samples[0].map).inverter.table.to_bytes()

    def fit(self, captures: list[SampleCapture]) -> tuple[Parameters, list[Parameters]]:
        """trimeter.fit over one or several of the prepared samples' captures; returns (combined,
        per-sample estimates: empty for one sample)."""
        import trimeter

        if not captures or not all(any(c.sample is s for s in self.samples) for c in captures):
            raise InputError("the captures are not of the samples this fit was prepared for")
        refls = [c.reflectances for c in captures]
        maps = [c.sample.map for c in captures]
        wl = refls[0].wavelengths_nm
        # The fit's noise model σ_I = noise_rel·I + noise_abs, with noise_rel measured from the frame spread
        # (so the reported uncertainties are this measurement's, not a default's).
        measured = [m for r in refls if (m := r.noise_rel()) is not None]
        noise: dict[str, Any] = ({"noise_rel": float(np.clip(max(measured), 1e-4, 0.2))} if len(measured) == len(refls)
                                 else {})
        # and each bin's own stds from the capture (frame scatter, dark, the calibration's), where it has them
        for name in ("I_b_std", "I_w_std", "I_c_std"):
            if all(getattr(r, name) is not None for r in refls):
                noise[name] = np.stack([getattr(r, name) for r in refls]) if len(refls) > 1 else getattr(refls[0],
                                                                                                         name)
        if self.bands is not None:
            return self._fit_bands(captures, noise)
        if len(refls) == 1:
            r = refls[0]
            result = self._per_channel(trimeter.fit(maps[0], r.I_b, r.I_w, r.I_c, rho_b=r.rho_b, rho_w=r.rho_w,
                                                    method=self.method, **noise))
            return Parameters.from_fit(wl, result, thickness_mm=maps[0].thickness_mm), []
        stack = {k: np.stack([getattr(r, k) for r in refls]) for k in ("I_b", "I_w", "I_c", "rho_b", "rho_w")}
        result = self._per_channel(trimeter.fit(maps, stack["I_b"], stack["I_w"], stack["I_c"], rho_b=stack["rho_b"],
                                                rho_w=stack["rho_w"], method=self.method, **noise))
        per = [Parameters.from_fit(wl, single, thickness_mm=amap.thickness_mm)
               for single, amap in zip(result.per_thickness, maps, strict=True)]
        return Parameters.from_fit(wl, result), per

    def _per_channel(self, result: FitResult) -> FitResult:
        """A multichannel sensor's channels fitted as if monochromatic: every value says so."""
        if self.multichannel:
            for r in (result, *result.per_thickness):
                r.flags = r.flags | int(FitFlag.PER_CHANNEL_BANDS)
        return result

    def _fit_bands(self, captures: list[SampleCapture], noise: dict[str, Any]) -> tuple[Parameters, list[Parameters]]:
        """The band-aware fit (trimeter.inversion.bands) of each capture, at the channels' centroids;
        several thicknesses combined by inverse-variance weighting as the per-wavelength fit does."""
        from trimeter.inversion.finish import combine
        from trimeter.inversion.bands import fit_bands
        from trimeter.inversion.artifacts import load_artifacts

        bands = self.bands
        assert bands is not None
        singles = []
        for i, capture in enumerate(captures):
            r = capture.reflectances
            if len(r.I_b) != len(bands.channels):
                raise InputError(f"the sensor reads {len(r.I_b)} bins but its band weights have "
                                 f"{len(bands.channels)} channels")
            stds = {k: (v[i] if len(captures) > 1 else v) for k, v in noise.items() if k.endswith("_std")}
            fitted = fit_bands(load_artifacts(capture.sample.map), bands, r.I_b, r.I_w, r.I_c, r.rho_b, r.rho_w,
                               noise_rel=noise.get("noise_rel", 0.005), **stds)
            singles.append(fitted.at_centres)
        per = [Parameters.from_fit(bands.centre_nm, single, thickness_mm=c.sample.map.thickness_mm)
               for single, c in zip(singles, captures, strict=True)]
        if len(singles) == 1:
            return per[0], []
        return Parameters.from_fit(bands.centre_nm, combine(singles, "bands")), per


def prepare_fit(samples: Iterable[Sample], method: str) -> PreparedFit:
    """The method is known, each map is for its sample's thickness, and one harmless bin fits with each map:
    a stale table, a missing model or a bad method then fails in a second, not after a whole capture."""
    import trimeter

    samples = tuple(samples)
    if not samples:
        raise InputError("no sample to fit")
    if method not in METHODS:
        raise InputError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    for sample in samples:
        sample.check_map()
    for sample in samples:
        trimeter.fit(sample.map, [0.2], [0.5], [0.1], method=method)
    return PreparedFit(samples, method)


def for_sensor(prepared: PreparedFit, spectrometer: Spectrometer) -> PreparedFit:
    """The prepared fit for this detector: band-aware when it is a multichannel sensor that has band
    weights (`band_weights()`), flagged PER_CHANNEL_BANDS when it is one without them."""
    weights = getattr(spectrometer, "band_weights", None)
    bands = weights() if callable(weights) else None
    multichannel = bands is not None or bool(spectrometer.description.extra.get("channels"))
    return replace(prepared, bands=bands, multichannel=multichannel)


def for_recorded_sensor(prepared: PreparedFit, spectrometer: dict) -> PreparedFit:
    """A re-fit of saved captures, for the detector the calibration recorded (its description's dict):
    an AS7341 build band-aware with its built-in weights; another multichannel sensor (the twin's, whose
    weights the record does not hold) per channel, flagged PER_CHANNEL_BANDS."""
    extra = spectrometer.get("extra") or {}
    if not extra.get("channels"):
        return prepared
    bands = None
    if spectrometer.get("model") == "AS7341":
        from trimeter.spectrometer.sensors import as7341_weights

        bands = as7341_weights().select(list(extra["channels"]), where="the recorded AS7341")
    return replace(prepared, bands=bands, multichannel=True)


def check_calibration(calibration: Calibration | None) -> Calibration:
    """The calibration a measurement may use, or why not."""
    if calibration is None:
        raise DeviceError("no calibration: run a calibration with the holder empty first")
    if problems := calibration_problems(calibration):
        raise CheckError("the calibration fails its checks (" + "; ".join(problems) + "); calibrate again "
                         "with the holder empty")
    return calibration


def capture_samples(runner: Runner, calibration: Calibration, samples: Iterable[Sample], *, frames: int,
                    hdr_decades: int, between: Callable[[float], None] | None = None
                    ) -> tuple[list[SampleCapture], TrimeterError | None]:
    """Capture each sample (calling `between(ℓ)` before the 2nd, to swap samples) and check the shot.
    Returns the captures and, when `between` raised a TrimeterError (the next sample never came), that
    error: the captures then hold the samples measured before it."""
    captures: list[SampleCapture] = []
    for i, sample in enumerate(samples):
        if i and between:
            try:
                between(sample.thickness_mm)
            except TrimeterError as exc:
                return captures, exc
        raw = runner.run(sample_capture(frames=frames, hdr_decades=hdr_decades,
                                        label=f"sample ℓ = {sample.thickness_mm:g} mm"))
        refl = reflectances(calibration, raw)
        if problems := shot_problems(refl, sample.map):
            raise CheckError(f"the {sample.thickness_mm:g} mm capture was refused, nothing was written: "
                             + "; ".join(problems))
        captures.append(SampleCapture(sample, raw, refl))
    return captures, None


@dataclass
class MeasurementOutcome:
    """What `measure` wrote (`path`: the results directory, or the spool's when `spooled`)."""

    path: Path
    measurement: Measurement
    timing: dict[str, float]
    spooled: CaptureSpooled | None = None     # the results directory could not take it: kept in the spool
    stopped: TrimeterError | None = None      # why fewer samples than asked were measured

    @property
    def parameters(self) -> Estimate:
        return self.measurement.parameters

    @property
    def incomplete(self) -> str | None:
        return self.measurement.provenance.incomplete


def measure(runner: Runner, calibration: Calibration | None, samples: list[Sample], settings: HostSettings, *,
            label: str | None = None, between: Callable[[float], None] | None = None,
            device_table: Callable[[PreparedFit], DeviceTableCheck] | None = None,
            on_warning: Callable[[str], None] = lambda message: None) -> MeasurementOutcome:
    """Capture → fit → write, once: check the calibration, prepare the fit, make sure the results directory
    can take it, capture each sample, fit, check the fit and write (or spool) the results directory.
    `device_table(prepared)` says whether the device's active map table is the fit's (None: not asked).
    When `between` raises a TrimeterError, what was captured is still fitted and written, marked incomplete."""
    calibration = check_calibration(calibration)
    prepared = for_sensor(prepare_fit(samples, settings.method), runner.spectrometer)
    for note in prepare_results_dir(settings.results_path, n_bins=len(calibration.wavelengths_nm),
                                    n_samples=len(samples)):
        on_warning(note)  # leftovers of interrupted writes, moved to the spool
    table = device_table(prepared) if device_table is not None else None
    if table is not None and table.slot and not table.matches_fit_table:
        on_warning(f"the device's active map table (slot {table.slot}, CRC-32 {table.crc32}) is not the table of "
                   f"map {samples[0].map.name}; `trimeter map flash` the right one")
    captures, stopped = capture_samples(runner, calibration, samples, frames=settings.frames,
                                        hdr_decades=settings.hdr_decades, between=between)
    incomplete = None
    if stopped is not None:
        n = len(captures)
        incomplete = (f"only {n} of {len(samples)} samples measured ({stopped}); the results hold "
                      f"{'it' if n == 1 else 'them'} alone")
    t0 = time.monotonic()
    combined, per = prepared.fit(captures)
    fit_s = time.monotonic() - t0
    for capture, params in zip(captures, per or [combined], strict=True):
        if problems := fit_problems(params.flags, usable_bins(capture.reflectances)):
            raise CheckError(f"the {capture.sample.thickness_mm:g} mm capture was refused, nothing was written: "
                             + "; ".join(problems))
    timing = runner.timing.to_dict()
    timing["fit_wall_s"] = round(fit_s, 4)
    device = runner.device
    stats = getattr(device.transport, "stats", None)
    provenance = Provenance(
        method="bands" if prepared.bands is not None else prepared.method, label=label, timing=dict(timing),
        instrument=None if device.identity is None else InstrumentInfo.of(device.identity),
        device_map_table=table, noise_rel_measured=[c.reflectances.noise_rel() for c in captures],
        incomplete=incomplete, advice=advice(combined.flags, len(captures)),
        link={} if stats is None else vars(stats).copy(),
        extra={"instrument": settings.name} if settings.name else {})
    measurement = Measurement(calibration, captures, combined, per, provenance)
    t0 = time.monotonic()
    try:
        path = write_or_spool(settings.results_path, measurement, label=label)
    except CaptureSpooled as exc:
        return MeasurementOutcome(exc.path, measurement, timing, spooled=exc, stopped=stopped)
    timing["write_wall_s"] = round(time.monotonic() - t0, 4)
    return MeasurementOutcome(path, measurement, timing, stopped=stopped)
