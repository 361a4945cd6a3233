"""The twin's optics: virtual samples, backgrounds, LEDs with warm-up drift, and the spectrometer model.

Everything is vectorised over the spectrometer's pixels. The data (materials, backgrounds, light
sources, spectrometer) is declared once in host/trimeter/data/materials.toml.

What the spectrometer sees for a plant state (counts/s per pixel, before noise):
    panels  = Σ_{left,right} shutter_open · led_level / 2 · E_d(λ, heat)   (diffuse light)
    beam    = collimated_shutter_open · collimated_level · E_c(λ, heat)
    black slot (or between slots):  panels · (I_b  | ρ_black without a sample)
    white slot:                     panels · (I_w  | ρ_white)
    open slot:                      panels · (I(ρ=0) | 0) + beam · (I_c | 1)
with (I_b, I_w, I_c) of the inserted sample computed for the set-up (geometry, n, ℓ) of the chosen map —
trimeter.twin.observables, not read from the map the host inverts, so a round trip includes the map's
interpolation and Monte Carlo error. Traced set-ups come from the maps' own tracer, reduced to the maps'
own I(ρ) model, so they share that tracer's and that model's errors: they are not independent physics.
Ideal set-ups computed by adding-doubling are: a round trip then shows the whole error of a traced map.
A set-up or material with neither is rendered by the very map the host inverts (AppearanceMap.query);
`physics` records which source it was (PHYSICS) and the demo and the HIL suite say so (physics_line).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

import numpy as np
from scipy.interpolate import PchipInterpolator

from trimeter.errors import InputError
from trimeter.geometry import load_geometry
from trimeter.twin.sensor import As7341Model
from trimeter.twin.observables import setup_observables

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap

# The maps the twin renders with: None (the shipped ones), a map or its path, or a list of them.
MapSource: TypeAlias = ("AppearanceMap | str | Path | list[AppearanceMap | str | Path] | "
                        "tuple[AppearanceMap | str | Path, ...] | None")

# what the twin's detector can be: "c12880ma" is read by the firmware (trimeter.twin.c12880), the others by the host
SENSORS = ("spectrometer", "as7341", "c12880ma")
MATERIALS_FILE = Path(__file__).resolve().parents[1] / "data" / "materials.toml"


@lru_cache(maxsize=1)
def _catalogue() -> dict:
    with open(MATERIALS_FILE, "rb") as f:
        return tomllib.load(f)


def material_names() -> dict[str, str]:
    """Material name → description."""
    return {name: m.get("description", "") for name, m in _catalogue()["material"].items()}


def parse_mixture(name: str) -> list[tuple[str, float]] | None:
    """A mixture's catalogue materials and volume fractions from its name, e.g. "cyan-ink:0.25+yellow-ink:0.75"
    (trimeter.model.mixing.parse_fractions), or None for a plain material name."""
    from trimeter.model.mixing import FRACTION_SEPARATOR, parse_fractions

    if FRACTION_SEPARATOR not in name:
        return None
    parts = parse_fractions(name)
    unknown = [c for c, _ in parts if c not in _catalogue()["material"]]
    if unknown:
        raise InputError(f"mixture {name!r}: {unknown[0]!r} is not a catalogue material "
                         f"({', '.join(_catalogue()['material'])})")
    return parts


def catalogue_entry(name: str) -> dict:
    """What defines a sample: its catalogue entry, or a mixture's fractions with its components' entries
    (the traced observables are stamped with its hash: trimeter.twin.observables)."""
    mixture = parse_mixture(name)
    if mixture is None:
        materials = _catalogue()["material"]
        if name not in materials:
            raise InputError(f"sample must be one of {', '.join(materials)} or a mixture like "
                             f"'cyan-ink:0.5+yellow-ink:0.5', got {name!r}")
        return dict(materials[name])
    return {"mixture": [[c, f] for c, f in mixture], "components": {c: dict(_catalogue()["material"][c])
                                                                   for c, _ in mixture}}


def material_spectra(name: str, wavelengths_nm: np.ndarray) -> dict[str, np.ndarray]:
    """α(λ), σt(λ) [1/mm], g(λ) of a catalogue material, or of a mixture of them by volume fractions
    (`parse_mixture`; trimeter.model.mixing: σa and σs add by fraction, g is σs-weighted), on the
    given wavelengths."""
    mixture = parse_mixture(name)
    if mixture is not None:
        from trimeter.model.mixing import mix_coefficients

        parts = [material_spectra(c, wavelengths_nm) for c, _ in mixture]
        sigma_a, sigma_s, g = mix_coefficients([(1 - p["alpha"]) * p["sigma_t"] for p in parts],
                                               [p["alpha"] * p["sigma_t"] for p in parts], [p["g"] for p in parts],
                                               [f for _, f in mixture])
        sigma_t = sigma_a + sigma_s
        return {"alpha": sigma_s / sigma_t, "sigma_t": sigma_t, "g": g}
    materials = _catalogue()["material"]
    if name not in materials:
        raise InputError(f"sample must be one of {', '.join(materials)} or a mixture like "
                         f"'cyan-ink:0.5+yellow-ink:0.5', got {name!r}")
    m = materials[name]
    lam = np.asarray(wavelengths_nm, dtype=float)
    sigma_s = m["scattering_at_500nm"] * (lam / 500.0) ** (-m["scattering_power"])
    sigma_a = np.full_like(lam, m["absorption_baseline"])
    for band in m.get("bands", []):
        sigma_a += band["peak"] * np.exp(-0.5 * ((lam - band["centre_nm"]) / band["width_nm"]) ** 2)
    sigma_t = sigma_s + sigma_a
    g = np.clip(m["g_at_500nm"] + m["g_slope_per_100nm"] * (lam - 500.0) / 100.0, -0.95, 0.95)
    return {"alpha": sigma_s / sigma_t, "sigma_t": sigma_t, "g": g}


def background_names() -> tuple[str, ...]:
    return ("white", *_catalogue()["background"])


def background_reflectance(name: str, wavelengths_nm: np.ndarray) -> np.ndarray:
    """ρ(λ) of a background; "white" is the geometry's declared white reference (flat)."""
    lam = np.asarray(wavelengths_nm, dtype=float)
    if name == "white":
        from trimeter.geometry import load_geometry

        rho = load_geometry("device")["calibration"]["white_reference_reflectance"]
        return np.full(lam.shape, float(rho))
    backgrounds = _catalogue()["background"]
    if name not in backgrounds:
        raise InputError(f"background must be one of {', '.join(background_names())}, got {name!r}")
    b = backgrounds[name]
    return PchipInterpolator(b["wavelength_nm"], b["reflectance"], extrapolate=True)(lam)


# ------------------------------------------------------------------------------------------ lights
class Led:
    """A white LED as the spectrometer sees it, with a first-order thermal model for warm-up drift.

    heat h ∈ [0, 1] follows the commanded level: h ← level + (h − level)·exp(−Δt/τ) (exact for a level
    held constant over Δt). Output = level · (1 − droop·h) · spectrum(phosphor centre + shift·h).
    """

    def __init__(self, params: dict, wavelengths_nm: np.ndarray) -> None:
        self.p = params
        self.lam = np.asarray(wavelengths_nm, dtype=float)
        self.heat = 0.0
        self._last_time_s: float | None = None
        self._level = 0.0

    def advance(self, time_s: float, level: float) -> None:
        """Account for the time since the last call (at the previous level), then take the new level."""
        if self._last_time_s is not None and time_s > self._last_time_s:
            decay = math.exp(-(time_s - self._last_time_s) / self.p["tau_s"])
            self.heat = self._level + (self.heat - self._level) * decay
        self._last_time_s = time_s
        self._level = min(max(float(level), 0.0), 1.0)

    def spectrum(self, heat: float | None = None) -> np.ndarray:
        """Counts per second at full level for the given (default: current) heat."""
        p, h = self.p, self.heat if heat is None else heat
        blue = p["blue_relative"] * np.exp(-0.5 * ((self.lam - p["blue_centre_nm"] - 0.5 * p["phosphor_shift_nm"] * h)
                                                   / p["blue_width_nm"]) ** 2)
        phosphor = np.exp(-0.5 * ((self.lam - p["phosphor_centre_nm"] - p["phosphor_shift_nm"] * h)
                                  / p["phosphor_width_nm"]) ** 2)
        # A silicon detector's response: falls off towards the UV and the NIR.
        detector = np.exp(-0.5 * ((self.lam - 620.0) / 260.0) ** 2)
        shape = (np.maximum(blue, phosphor) + p["floor_relative"]) * detector
        return p["peak_counts_per_s"] * (1.0 - p["droop"] * h) * shape / shape.max()


# ------------------------------------------------------------------------------------ spectrometer
@dataclass
class SpectrometerModel:
    """Pixels, dispersion, dark counts, shot + read noise, 16-bit ADC saturation, masked pixels."""

    params: dict = field(default_factory=lambda: dict(_catalogue()["spectrometer"]))

    def __post_init__(self) -> None:
        p = self.params
        i = np.arange(p["pixels"], dtype=float)
        c0, c1, c2 = p["dispersion"]
        self.wavelengths_nm = c0 + c1 * i + c2 * i * i
        self.dark_pixels = tuple(range(int(p["masked_pixels"])))
        self.saturation_counts = float(p["adc_max_counts"])
        self.integration_time_us_limits = (int(p["integration_time_us_min"]), int(p["integration_time_us_max"]))

    def description(self) -> dict:
        return {"model": self.params["model"], "serial": self.params["serial"], "pixels": len(self.wavelengths_nm),
                "wavelength_range_nm": [float(self.wavelengths_nm[0]), float(self.wavelengths_nm[-1])],
                "integration_time_us_limits": list(self.integration_time_us_limits),
                "saturation_counts": self.saturation_counts, "dark_pixels": list(self.dark_pixels)}

    def expose(self, rate_counts_per_s: np.ndarray, integration_time_us: int, rng: np.random.Generator) -> np.ndarray:
        """One exposure: light (counts/s) → uint16 counts with dark, shot and read noise, clipped."""
        p, t = self.params, integration_time_us * 1e-6
        signal = np.maximum(np.asarray(rate_counts_per_s, dtype=float), 0.0) * t
        signal[list(self.dark_pixels)] = 0.0
        electrons_per_count = p["electrons_per_count"]
        collected = (signal + p["dark_current_counts_per_s"] * t) * electrons_per_count
        # Poisson overflows for huge means; the ADC clips long before, so cap the mean first.
        collected = rng.poisson(np.minimum(collected, 1e12)) / electrons_per_count
        counts = p["dark_offset_counts"] + collected + rng.normal(0.0, p["read_noise_counts"], collected.shape)
        return np.clip(np.rint(counts), 0, p["adc_max_counts"]).astype(np.uint16)


# ------------------------------------------------------------------------------------------ sample
# Where a virtual sample's I_b, I_w, I_c come from (SampleOptics.physics), and what a round trip against them
# can and cannot show.
PHYSICS = {
    "traced": "traced by the tracer the maps are built with (trimeter.forward.transport, "
              "tools/make_twin_observables.py) and reduced to the maps' own I(ρ) = A + Bρ/(1 − Cρ) model",
    "adding-doubling": "computed by adding-doubling (Prahl's iadpython, tools/make_twin_observables.py), an "
                       "integrator other than the maps' Monte Carlo tracer",
    "map": "queried from the very map the host inverts (no traced observables for this set-up or material)",
}


def physics_line(physics: str, sample: str, map_name: str) -> str:
    """The demo's "independent physics:" line: where the twin's observables of `sample` came from and what
    the errors printed against its truth therefore include."""
    if physics == "traced":
        return (f"independent physics: partly — the twin's '{sample}' was {PHYSICS['traced']}, not read from the "
                f"map {map_name} the fit inverts: the errors below include that map's interpolation and Monte Carlo "
                "error, NOT the tracer's or the I(ρ) model's own (e.g. its single return coefficient C)")
    if physics == "adding-doubling":
        return (f"independent physics: yes — the twin's '{sample}' was {PHYSICS['adding-doubling']}: the errors "
                f"below include the whole of the map {map_name}'s own error (its tracer's, its interpolation's, its "
                "Monte Carlo noise); what both share is the ideal geometry's model itself (an infinite slab over a "
                "Lambertian background, unpolarised Fresnel)")
    if physics == "map":
        return (f"independent physics: none — the twin's '{sample}' was {PHYSICS['map']}, map {map_name}: the "
                "errors below are noise, drift and calibration only, NOT the map's own error "
                "(tools/make_twin_observables.py traces a set-up)")
    raise InputError(f"physics must be one of {', '.join(PHYSICS)}, got {physics!r}")


@dataclass(frozen=True)
class SampleOptics:
    name: str
    thickness_mm: float
    alpha: np.ndarray
    sigma_t: np.ndarray
    g: np.ndarray
    I_b: np.ndarray
    I_w: np.ndarray
    I_c: np.ndarray
    I_open: np.ndarray  # diffuse reflectance over the open slot (no background: ρ = 0)
    map_name: str
    physics: str = "map"  # where I_b, I_w, I_c came from: a key of PHYSICS
    physics_source: str = ""  # how: the traced data's file and provenance, or the map's name


def _load_maps(appearance_map: MapSource) -> list[AppearanceMap]:
    from trimeter.formats.appearance import AppearanceMap, shipped_maps

    if appearance_map is None:
        return [AppearanceMap.load(p) for p in shipped_maps()]
    items = appearance_map if isinstance(appearance_map, (list, tuple)) else [appearance_map]
    return [m if isinstance(m, AppearanceMap) else AppearanceMap.load(m) for m in items]


class Optics:
    """The optical bench: sample, backgrounds, two LEDs, one spectrometer."""

    def __init__(self, appearance_map: MapSource = None, white: str = "white", black: str = "black",
                 sensor: str = "spectrometer") -> None:
        """sensor: what the host reads — "spectrometer" (the pixels) or "as7341" (trimeter.twin.sensor:
        nine channels of the same light)."""
        self.spectrometer = SpectrometerModel()
        lam = self.spectrometer.wavelengths_nm
        self.rho_white = background_reflectance(white, lam)
        self.rho_black = background_reflectance(black, lam)
        lights = _catalogue()["light"]
        self.panels = Led(lights["panels"], lam)
        self.collimated = Led(lights["collimated"], lam)
        if sensor not in SENSORS:
            raise InputError(f"sensor must be one of {', '.join(SENSORS)}, got {sensor!r}")
        self.sensor: SpectrometerModel | As7341Model = self.spectrometer
        if sensor == "as7341":  # its band weights: the lamps warm, as they are after the warm-up
            self.sensor = As7341Model(lam, self.panels.spectrum(1.0), self.collimated.spectrum(1.0))
        self._map_source = appearance_map
        self._maps: list[AppearanceMap] | None = None
        self.sample: SampleOptics | None = None

    @property
    def wavelengths_nm(self) -> np.ndarray:
        return self.spectrometer.wavelengths_nm

    def _map_for(self, thickness_mm: float) -> AppearanceMap:
        if self._maps is None:
            self._maps = _load_maps(self._map_source)
        matching = [m for m in self._maps if abs(m.thickness_mm - thickness_mm) <= 1e-6]
        if matching:  # the instrument's own geometry first: it is what a real device would show
            return next((m for m in matching if m.recipe.get("geometry") == "device"), matching[0])
        have = ", ".join(f"{m.name} ({m.thickness_mm:g} mm)" for m in self._maps) or "none"
        raise InputError(f"thickness_mm={thickness_mm:g}: no appearance map for that thickness (available: {have}); "
                         "pass appearance_map= / --map")

    def insert_sample(self, name: str, thickness_mm: float) -> SampleOptics:
        try:
            thickness_mm = float(thickness_mm)
        except (TypeError, ValueError):
            raise InputError(f"thickness_mm must be a number, got {thickness_mm!r}") from None
        if not math.isfinite(thickness_mm) or thickness_mm <= 0:
            raise InputError(f"thickness_mm must be positive, got {thickness_mm!r}")
        spectra = material_spectra(name, self.wavelengths_nm)
        amap = self._map_for(thickness_mm)
        # only samples the host's map can invert, whichever physics renders them
        for key, axis in (("alpha", amap.alpha), ("sigma_t", amap.sigma_t), ("g", amap.g)):
            values = spectra[key]
            bad = (values < axis[0]) | (values > axis[-1])
            if bad.any():
                lam = self.wavelengths_nm[bad]
                raise InputError(f"sample {name!r}: {key} spans {values.min():.4g}..{values.max():.4g}, outside map "
                                 f"{amap.name}'s {axis[0]:.4g}..{axis[-1]:.4g} at {lam[0]:.0f}-{lam[-1]:.0f} nm")
        computed = setup_observables(str(amap.recipe.get("geometry")), amap.n, thickness_mm)
        alpha, sigma_t, g = spectra["alpha"], spectra["sigma_t"], spectra["g"]
        if computed is not None:
            geometry_params = load_geometry(computed.geometry)
            observed = computed.observables(name, catalogue_entry(name), geometry_params,
                                            self.wavelengths_nm, self.rho_black, self.rho_white)
            if observed is not None:
                I_b, I_w, L, I_open = observed
                I_c = computed.collimated(sigma_t, L, geometry_params)
                self.sample = SampleOptics(name=name, thickness_mm=thickness_mm, alpha=alpha, sigma_t=sigma_t, g=g,
                                           I_b=I_b, I_w=I_w, I_c=I_c, I_open=I_open, map_name=amap.name,
                                           physics=computed.physics, physics_source=computed.source())
                return self.sample
        I_b, I_w, I_c = amap.query(spectra["alpha"], spectra["sigma_t"], spectra["g"], self.rho_black, self.rho_white)
        I_open = amap.diffuse(spectra["alpha"], spectra["sigma_t"], spectra["g"], 0.0)
        self.sample = SampleOptics(name=name, thickness_mm=thickness_mm, alpha=alpha, sigma_t=sigma_t, g=g, I_b=I_b,
                                   I_w=I_w, I_c=I_c, I_open=I_open, map_name=amap.name,
                                   physics="map", physics_source=f"AppearanceMap.query of {amap.name}")
        return self.sample

    def remove_sample(self) -> None:
        self.sample = None

    def advance(self, plant: dict, lamp_failure: str | None = None) -> None:
        """Feed the LEDs' thermal models with a plant state (time_s, commanded levels)."""
        leds = plant.get("leds", {})
        self.panels.advance(plant["time_s"], 0.0 if lamp_failure in ("panels", "both") else leds.get("panels", 0.0))
        self.collimated.advance(plant["time_s"],
                                0.0 if lamp_failure in ("collimated", "both") else leds.get("collimated", 0.0))

    def rate(self, plant: dict, lamp_failure: str | None = None) -> np.ndarray:
        """Light on the spectrometer (counts/s per pixel, before noise) for one plant state."""
        shutters, leds = plant.get("shutters", {}), plant.get("leds", {})
        # Each panel lights the sample through its own shutter; both open at full level = the diffuse spectrum.
        panels_lit = 0.0 if lamp_failure in ("panels", "both") else sum(
            float(bool(shutters.get(k, {}).get("open"))) * float(leds.get(k, leds.get("panels", 0.0)))
            for k in ("panel_left", "panel_right")) / 2.0
        beam_level = 0.0 if lamp_failure in ("collimated", "both") else float(leds.get("collimated", 0.0))
        diffuse = panels_lit * self.panels.spectrum()
        beam = float(bool(shutters.get("collimated", {}).get("open"))) * beam_level * self.collimated.spectrum()
        slot, s = plant.get("slot"), self.sample
        if slot == "white":
            return diffuse * (s.I_w if s else self.rho_white)
        if slot == "open":
            return diffuse * s.I_open + beam * s.I_c if s else beam
        return diffuse * (s.I_b if s else self.rho_black)  # black slot, or the slider body between slots

    def truth(self) -> dict | None:
        s = self.sample
        if s is None:
            return None
        return {"name": s.name, "thickness_mm": s.thickness_mm, "wavelengths_nm": self.wavelengths_nm.copy(),
                "alpha": s.alpha.copy(), "sigma_t": s.sigma_t.copy(), "g": s.g.copy(), "map": s.map_name,
                "physics": s.physics, "physics_source": s.physics_source}
