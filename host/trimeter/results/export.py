"""A measured material for renderers: `trimeter export RESULT --to mitsuba|pbrt|blender|rgb`.

RESULT is a measurement directory (its parameters.json, with measurement.json for provenance) or a
parameters file written by `trimeter fit -o` (CSV or JSON). Every export writes `provenance.json` beside
its files (source, measurement, map(s), method, what was converted how, trimeter version, date) and
repeats the essentials in the files' own comments.

- mitsuba: trimeter.results.medium (the spectral `homogeneous` medium; spectral only in *_spectral variants).
- pbrt: a PBRT-v4 named `homogeneous` medium (medium.pbrt) whose σa and σs are `.spd` files of
  "wavelength_nm value" lines; σ in 1/mm, so `"float scale"` is the millimetres per scene unit.
- blender: per linear-sRGB channel σa, σs and g (blender.json) and a script (blender_volume.py, run in
  Blender's Python console or `blender --python`) that builds the node set: one Volume Absorption
  (Color = 1 − σa/Density, Density = max σa) and one Volume Scatter per channel (Color = that channel's
  unit vector, Density = its σs, Anisotropy = its g), summed by Add Shader nodes into a material's
  Volume output. Densities are per Blender unit (1 m by default: σ per mm × 1000).
- rgb: linear sRGB σa, σs, σt, g per channel (rgb.json, rgb.csv), see `linear_srgb_coefficients`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from trimeter.atomic import atomic_write
from trimeter.errors import InputError
from trimeter.results.medium import VARIANT_NOTE, SpectralMaterial, write_medium
from trimeter.tables import MAX_RESULT_FILE_BYTES
from trimeter.version import __version__

if TYPE_CHECKING:
    from trimeter.domain.measurement import SpectralColumns

FORMATS = ("mitsuba", "pbrt", "blender", "rgb")
MAX_INPUT_BYTES = MAX_RESULT_FILE_BYTES
CMFS = "CIE 1931 2 Degree Standard Observer"
COLOUR_RANGE_NM = (360.0, 780.0)
TRANSMITTANCE_FLOOR = 1e-6  # the darkest channel transmittance kept at the reference thickness
MIN_STEP_NM = 0.1  # a resampling step finer than any spectrometer's bin only multiplies the output
DEFAULT_SCENE_UNIT_MM = {"mitsuba": 1.0, "pbrt": 1.0, "blender": 1000.0, "rgb": 1.0}


@dataclass(frozen=True)
class LoadedResult:
    material: SpectralMaterial
    source: dict = field(default_factory=dict)   # provenance of the measurement

    def measured_thickness_mm(self) -> float | None:
        """The (first) sample thickness the measurement states, if any."""
        for value in (self.source.get("thickness_mm"), *(self.source.get("thicknesses_mm") or [])):
            if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0:
                return float(value)
        return None


def _material(parameters: SpectralColumns, path: Path) -> SpectralMaterial:
    try:
        return SpectralMaterial.from_parameters(parameters)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def loaded_parameters(parameters: SpectralColumns, source: dict, where: str | Path) -> LoadedResult:
    """Fitted parameters (with their stds: a measurement's, a library material's) and their origin, as an
    export takes them; `where` names them in errors."""
    return LoadedResult(_material(parameters, Path(where)), source)


# ------------------------------------------------------------------------------------- colour
def _colour_science() -> Any:
    """colour-science, imported without what its import does to the whole process: it sets numpy's 1.13
    legacy print mode, in which str() of a numpy number has six or twelve digits, not the shortest that reads
    back, in every later text this process writes (a configuration backup after an export)."""
    options = np.get_printoptions()
    import colour

    np.set_printoptions(**options)
    return colour


@lru_cache(maxsize=8)
def _tristimulus_weights(illuminant: str) -> tuple[np.ndarray, np.ndarray]:
    """(λ, W) with XYZ = Σ_λ W(λ)·T(λ) for a transmittance or reflectance T: colour-science's CIE 1931 2°
    observer × the illuminant at 1 nm over 360-780 nm, normalised so that T ≡ 1 has Y = 1 (its
    "Integration" method, tested against colour.sd_to_XYZ)."""
    colour = _colour_science()

    if illuminant not in colour.SDS_ILLUMINANTS or illuminant not in colour.CCS_ILLUMINANTS[CMFS]:
        raise InputError(f"illuminant must be a CIE illuminant colour-science knows (D65, D50, A, F2, …), "
                         f"got {illuminant!r}")
    shape = colour.SpectralShape(*COLOUR_RANGE_NM, 1)
    cmfs = colour.MSDS_CMFS[CMFS].copy().align(shape)
    light = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape)
    weights = cmfs.values * light.values[:, None]
    return np.asarray(shape.wavelengths, dtype=float), weights / weights[:, 1].sum()


def spectra_to_linear_srgb(wavelengths_nm: ArrayLike, values: ArrayLike, illuminant: str = "D65") -> np.ndarray:
    """Linear sRGB of reflectance/transmittance spectra (`values`: (..., len(wavelengths))) seen under
    `illuminant`, adapted to sRGB's D65 white (CAT02) when the illuminant is another. Spectra are
    interpolated linearly onto 1 nm and held constant beyond their ends."""
    colour = _colour_science()

    lam, weights = _tristimulus_weights(illuminant)
    values = np.asarray(values, dtype=float)
    wl = np.asarray(wavelengths_nm, dtype=float)
    on = np.apply_along_axis(lambda v: np.interp(lam, wl, v), -1, values)
    XYZ = on @ weights
    white = colour.CCS_ILLUMINANTS[CMFS][illuminant]
    return colour.XYZ_to_RGB(XYZ, "sRGB", illuminant=white,
                             chromatic_adaptation_transform=None if illuminant == "D65" else "CAT02",
                             apply_cctf_encoding=False)


def srgb_encode(linear: ArrayLike) -> np.ndarray:
    """sRGB's transfer function (for swatches and images), linear values clipped to [0, 1]."""
    colour = _colour_science()

    return colour.cctf_encoding(np.clip(np.asarray(linear, dtype=float), 0.0, 1.0), function="sRGB")


# How the RGB coefficients are derived, written into rgb.json beside them.
RGB_METHOD = (
    "Why not the mean of σ over each channel's band: an RGB renderer attenuates each channel by exp(−σ_c·d), "
    "and the colour of light through a coloured material is the band-average of exp(−σ(λ)·d), not exp(−(band-"
    "average of σ)·d) — a narrow absorption band would come out far too weak. So for σt and σa the spectral "
    "transmittance over the reference thickness d is converted to linear sRGB (XYZ under the illuminant), "
    "normalised by a non-absorbing sample's (which is then exactly (1, 1, 1)), and σ_c = −ln(T_c)/d: a slab "
    "of thickness d renders with the measured colour of its unscattered transmittance and its absorption. "
    "σs_c = σt_c − σa_c keeps σt = σa + σs, which renderers assume. g_c is g(λ) weighted by σs(λ) and the "
    "channel's (positive) colour-matching weight. A transmittance outside sRGB's gamut is desaturated towards"
    " its luminance until it fits (`gamut_saturation` < 1 says how much was kept). Exact at d, inside the "
    "gamut, and for spectrally flat materials; other thicknesses shift the colour slightly.")


def linear_srgb_coefficients(material: SpectralMaterial, thickness_mm: float = 1.0,
                             illuminant: str = "D65") -> dict:
    """σa, σs, σt [1/mm] and g per linear-sRGB channel, through transmittance at `thickness_mm`, by
    RGB_METHOD."""
    if not (math.isfinite(thickness_mm) and thickness_mm > 0):
        raise InputError(f"reference thickness must be positive [mm], got {thickness_mm!r}")
    wl = material.wavelengths_nm
    transmittance = np.exp(-np.stack([material.sigma_t, material.sigma_a]) * thickness_mm)
    rgb = spectra_to_linear_srgb(wl, transmittance, illuminant)
    rgb = rgb / spectra_to_linear_srgb(wl, np.ones_like(wl), illuminant)
    _refuse_opaque(rgb, material, thickness_mm)
    rgb, saturation = _into_gamut(rgb)
    sigma_t, sigma_a = -np.log(np.clip(rgb, TRANSMITTANCE_FLOOR, 1.0)) / thickness_mm
    sigma_a = np.clip(sigma_a, 0.0, sigma_t) + 0.0
    lam, weights = _tristimulus_weights(illuminant)
    colour = _colour_science()

    to_rgb = colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB
    channel = np.clip(weights @ to_rgb.T, 0.0, None)                   # (λ, 3) positive channel weights
    ss = np.interp(lam, wl, material.sigma_s)[:, None] * channel
    g = np.interp(lam, wl, material.g)
    g_rgb = np.where(ss.sum(0) > 0, (g[:, None] * ss).sum(0) / np.maximum(ss.sum(0), 1e-300), material.g_mean())
    return {"sigma_a": sigma_a, "sigma_s": sigma_t - sigma_a, "sigma_t": sigma_t, "g": np.clip(g_rgb, -0.99, 0.99),
            "reference_thickness_mm": float(thickness_mm), "illuminant": illuminant,
            "gamut_saturation": {"sigma_t": float(saturation[0]), "sigma_a": float(saturation[1])}}


def _refuse_opaque(rgb: np.ndarray, material: SpectralMaterial, thickness_mm: float) -> None:
    """InputError when the unscattered (σt) or unabsorbed (σa) transmittance at the reference thickness is
    darker than TRANSMITTANCE_FLOOR: an RGB coefficient can only say "at least −ln(floor)/d" there, so a dense
    scatterer would come out as a pure absorber of that density, silently."""
    luminance = np.nan_to_num(rgb @ np.array([0.2126, 0.7152, 0.0722]), nan=0.0)
    for row, name in ((0, "σt"), (1, "σa")):
        if luminance[row] < TRANSMITTANCE_FLOOR:
            sigma = material.sigma_t if row == 0 else material.sigma_a
            typical = float(np.nanmedian(np.where(np.isfinite(sigma), sigma, np.nan))) if np.isfinite(sigma).any() \
                else math.inf
            hint = (f"; a --reference-thickness of at most {-math.log(TRANSMITTANCE_FLOOR) / typical:.3g} mm keeps it "
                    f"representable" if 0 < typical < math.inf else "")
            raise InputError(f"the material is opaque in {name} at the reference thickness {thickness_mm:g} mm "
                             f"(transmittance below {TRANSMITTANCE_FLOOR:g}): no RGB coefficient represents it{hint}")


def _into_gamut(rgb: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Transmittances (rows) moved into [floor, 1] towards their own luminance grey, keeping luminance:
    a saturated colour outside sRGB (a cyan's red channel below 0) would otherwise give an infinite or
    negative coefficient. Returns the moved colours and the saturation kept per row (1: untouched)."""
    rgb = np.asarray(rgb, dtype=float)
    luminance = np.clip(rgb @ np.array([0.2126, 0.7152, 0.0722]), TRANSMITTANCE_FLOOR, 1.0)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        low = np.where(rgb < TRANSMITTANCE_FLOOR, (luminance - TRANSMITTANCE_FLOOR) / (luminance - rgb), 1.0)
        high = np.where(rgb > 1.0, (1.0 - luminance) / (rgb - luminance), 1.0)
    keep = np.clip(np.minimum(low, high).min(axis=1), 0.0, 1.0)
    return luminance + keep[:, None] * (rgb - luminance), keep


# -------------------------------------------------------------------------------------- writers
def _floats(a: ArrayLike, digits: int = 6) -> list[float]:
    return [float(f"{v:.{digits}g}") for v in np.asarray(a, dtype=float)]


def _write_mitsuba(out: Path, material: SpectralMaterial, opts: dict) -> tuple[list[str], dict]:
    info = write_medium(out, material, scale=opts["scene_unit_mm"], step_nm=opts["step_nm"])
    if not info.get("written"):
        raise InputError(f"cannot write a Mitsuba medium: {info.get('reason')}")
    return info["files"], {"spectral_variants": VARIANT_NOTE, "g_mean": info["g_mean"],
                           "scale": opts["scene_unit_mm"]}


def _spd(wavelengths: np.ndarray, values: np.ndarray, what: str, provenance_line: str) -> str:
    lines = [f"# {what}, trimeter export ({provenance_line})", "# wavelength_nm value"]
    lines += [f"{w:.2f} {v:.6g}" for w, v in zip(wavelengths, values, strict=True)]
    return "\n".join(lines) + "\n"


def _write_pbrt(out: Path, material: SpectralMaterial, opts: dict) -> tuple[list[str], dict]:
    m = material.resampled(opts["step_nm"]) if opts["step_nm"] else material
    origin = opts["origin_line"]
    atomic_write(out / "sigma_a.spd", _spd(m.wavelengths_nm, m.sigma_a, "absorption σa [1/mm]", origin))
    atomic_write(out / "sigma_s.spd", _spd(m.wavelengths_nm, m.sigma_s, "scattering σs [1/mm]", origin))
    g = m.g_mean()
    scale = opts["scene_unit_mm"]
    atomic_write(out / "medium.pbrt", (
        f"# trimeter export ({origin})\n"
        "# PBRT-v4 homogeneous medium: σa and σs in 1/mm (the .spd files next to this one: wavelength_nm value);\n"
        f"# \"scale\" = millimetres per scene unit ({scale:g}). g: the σs-weighted mean of the measured g(λ).\n"
        "# Use: Include \"medium.pbrt\", then MediumInterface \"trimeter_sample\" \"\" on the object's shape.\n"
        'MakeNamedMedium "trimeter_sample"\n'
        '    "string type" "homogeneous"\n'
        '    "spectrum sigma_a" "sigma_a.spd"\n'
        '    "spectrum sigma_s" "sigma_s.spd"\n'
        f'    "float scale" [ {scale:g} ]\n'
        f'    "float g" [ {g:.6g} ]\n'))
    return ["medium.pbrt", "sigma_a.spd", "sigma_s.spd"], {"g_mean": g, "scale": scale, "bins": len(m.wavelengths_nm)}


def _write_rgb(out: Path, material: SpectralMaterial, opts: dict) -> tuple[list[str], dict]:
    c = linear_srgb_coefficients(material, opts["reference_thickness_mm"], opts["illuminant"])
    doc = {"units": "1/mm", "colour_space": "linear sRGB (D65 white), channels R, G, B",
           **{k: _floats(c[k]) if isinstance(c[k], np.ndarray) else c[k] for k in c},
           "method": RGB_METHOD}
    atomic_write(out / "rgb.json", json.dumps(doc, indent=1))
    rows = ["channel,sigma_a_per_mm,sigma_s_per_mm,sigma_t_per_mm,g"]
    rows += [f"{ch},{c['sigma_a'][i]:.6g},{c['sigma_s'][i]:.6g},{c['sigma_t'][i]:.6g},{c['g'][i]:.6g}"
             for i, ch in enumerate("RGB")]
    atomic_write(out / "rgb.csv", "\n".join(rows) + "\n")
    return ["rgb.json", "rgb.csv"], {"reference_thickness_mm": c["reference_thickness_mm"],
                                     "illuminant": c["illuminant"], "gamut_saturation": c["gamut_saturation"]}


_BLENDER_SCRIPT = '''"""Build the measured material as Cycles volume nodes (trimeter export; values from blender.json).
Run in Blender: Scripting workspace → Open → Run, or `blender --python blender_volume.py`. Adds the material
"{name}" (no surface: assign it to a closed mesh); densities are per Blender unit ({unit_mm:g} mm)."""
import bpy

SIGMA_A = {sigma_a}   # absorption per Blender unit, linear sRGB R, G, B
SIGMA_S = {sigma_s}   # scattering per Blender unit
G = {g}               # Henyey-Greenstein anisotropy per channel

mat = bpy.data.materials.new("{name}")
mat.use_nodes = True
nodes, links = mat.node_tree.nodes, mat.node_tree.links
nodes.remove(nodes["Principled BSDF"])
output = nodes["Material Output"]
absorb = nodes.new("ShaderNodeVolumeAbsorption")
density = max(SIGMA_A) or 1.0
absorb.inputs["Color"].default_value = (*(1.0 - a / density for a in SIGMA_A), 1.0)
absorb.inputs["Density"].default_value = density if max(SIGMA_A) > 0 else 0.0
total = absorb.outputs["Volume"]
for channel in range(3):  # one Volume Scatter per channel: each keeps its own anisotropy
    scatter = nodes.new("ShaderNodeVolumeScatter")
    scatter.inputs["Color"].default_value = (*(1.0 if c == channel else 0.0 for c in range(3)), 1.0)
    scatter.inputs["Density"].default_value = SIGMA_S[channel]
    scatter.inputs["Anisotropy"].default_value = G[channel]
    add = nodes.new("ShaderNodeAddShader")
    links.new(total, add.inputs[0])
    links.new(scatter.outputs["Volume"], add.inputs[1])
    total = add.outputs["Shader"]
links.new(total, output.inputs["Volume"])
'''


def _write_blender(out: Path, material: SpectralMaterial, opts: dict) -> tuple[list[str], dict]:
    c = linear_srgb_coefficients(material, opts["reference_thickness_mm"], opts["illuminant"])
    unit = opts["scene_unit_mm"]
    per_unit = {k: _floats(np.asarray(c[k]) * unit) for k in ("sigma_a", "sigma_s")}
    doc = {"blender_unit_mm": unit,
           "nodes": "Volume Absorption (Color = 1 − σa/Density, Density = max σa) + one Volume Scatter per "
                    "channel (Color = the channel's unit vector, Density = σs of that channel, Anisotropy = g of "
                    "that channel), summed with Add Shader into Material Output → Volume",
           "sigma_a_per_blender_unit": per_unit["sigma_a"], "sigma_s_per_blender_unit": per_unit["sigma_s"],
           "g": _floats(c["g"]), "sigma_a_per_mm": _floats(c["sigma_a"]), "sigma_s_per_mm": _floats(c["sigma_s"]),
           "reference_thickness_mm": c["reference_thickness_mm"], "illuminant": c["illuminant"],
           "gamut_saturation": c["gamut_saturation"], "colour_space": "linear sRGB (Blender's default scene linear)"}
    atomic_write(out / "blender.json", json.dumps(doc, indent=1))
    atomic_write(out / "blender_volume.py", _BLENDER_SCRIPT.format(
        name=opts["name"].replace('"', "'"), unit_mm=unit, sigma_a=per_unit["sigma_a"],
        sigma_s=per_unit["sigma_s"], g=doc["g"]))
    return ["blender.json", "blender_volume.py"], {"blender_unit_mm": unit, "illuminant": c["illuminant"],
                                                   "reference_thickness_mm": c["reference_thickness_mm"],
                                                   "gamut_saturation": c["gamut_saturation"]}


_WRITERS = {"mitsuba": _write_mitsuba, "pbrt": _write_pbrt, "blender": _write_blender, "rgb": _write_rgb}


def export(result: LoadedResult, fmt: str, out_dir: str | Path, *, step_nm: float = 5.0,
           reference_thickness_mm: float = 1.0, illuminant: str = "D65",
           scene_unit_mm: float | None = None) -> dict:
    """Write `fmt`'s files and provenance.json into `out_dir`; return the provenance."""
    if fmt not in FORMATS:
        raise InputError(f"--to must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if not (math.isfinite(step_nm) and (step_nm == 0 or MIN_STEP_NM <= step_nm <= 100)):
        raise InputError(f"step must be 0 (the measured bins) or within {MIN_STEP_NM:g}-100 nm, got {step_nm!r}")
    unit = DEFAULT_SCENE_UNIT_MM[fmt] if scene_unit_mm is None else float(scene_unit_mm)
    if not (math.isfinite(unit) and unit > 0):
        raise InputError(f"scene unit must be a positive number of millimetres, got {scene_unit_mm!r}")
    out = Path(out_dir)
    name = str(result.source.get("sample") or result.source.get("label") or result.source.get("measurement")
               or Path(result.source.get("path", "trimeter_sample")).stem)
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    what = (result.source.get("measurement") or result.source.get("path")
            or (f"library material {result.source['library_material']}" if "library_material" in result.source
                else "?"))
    origin = f"{what}, trimeter {__version__}, {now}"
    opts = {"step_nm": step_nm, "reference_thickness_mm": float(reference_thickness_mm), "illuminant": illuminant,
            "scene_unit_mm": unit, "name": name, "origin_line": origin}
    out.mkdir(parents=True, exist_ok=True)
    files, details = _WRITERS[fmt](out, result.material, opts)
    provenance = {"format": fmt, "files": files, "source": result.source, "trimeter_version": __version__,
                  "exported_utc": now, "step_nm": step_nm, "wavelength_range_nm":
                  [float(result.material.wavelengths_nm[0]), float(result.material.wavelengths_nm[-1])], **details}
    atomic_write(out / "provenance.json", json.dumps(provenance, indent=1, default=str))
    return provenance
