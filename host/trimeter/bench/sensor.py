"""`trimeter bench sensor`: every build's accuracy on the twin's materials, from one run.

The twin's catalogue materials at --thickness, their I_b, I_w, I_c per pixel traced directly
(trimeter.twin.observables: not read off the map the fits invert, though traced by the same tracer), read
as each build reads them:
- ideal spectrometer: the pixels as they are, fitted per wavelength (lut);
- seabreeze: each pixel through the spectrometer's slit (trimeter.spectrometer.sensors.slit_matrix)
  under the panels' and the beam's LEDs (the slit blurs the counts; a reading is sample counts over
  reference counts), fitted per wavelength;
- c12880ma: the micro-spectrometer build: 288 pixels at a typical unit's test-sheet polynomial, each through
  the C12880MA's line-spread function (trimeter.spectrometer.sensors.resample_matrix, C12880_FWHM_NM) under the
  panels' and the beam's LEDs, ρ_black as its calibration measures it (blurred alike), fitted per pixel;
  scored at the pixels whose line-spread function lies inside the twin's pixels;
- AS7341 per-channel: each channel's band reading (the AS7341 model's weights) fitted per channel as
  if monochromatic, the values reported at the datasheet's centres (what the `i2c` backend gives
  today); "at centroids": the same fit scored at the centroid of each channel's weight;
- AS7341 band-aware: trimeter.inversion.bands, scored at the centroids it reports.
Per build: p95 |Δα|, |Δσt|/σt, |Δg| against the material's own spectra at the reported wavelengths
(--band-nm limits the spectrometers' to the AS7341's span), the share of reported values with any
flag, and the fit time per spectrum (the time of the fit calls over the materials, over their number;
a ratio to the ideal build's, measured in the same run). "inks" rows: the four smooth ink-like
materials alone. With --noise, each reading also gets relative Gaussian noise plus 2e-4 absolute
(--draws times). A second table compares the band-aware fit's bases and smoothness on the same readings.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from trimeter.atomic import atomic_write
from trimeter.errors import InputError

INKS = ("cyan-ink", "magenta-ink", "yellow-ink", "black-ink")
MAP_FOR = {0.4: "device-n1.5-l0.4", 0.8: "device-n1.5-l0.8"}
BASIS_VARIANTS = (("cubic", 0.03), ("cubic", 0.0), ("cubic", 0.3), ("not-a-knot", 0.03), ("linear", 0.03))


def register(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser("sensor", help="every build's accuracy (spectrometer, AS7341 per-channel and "
                                                   "band-aware) on the twin's materials",
                                    description=__doc__.split("\n\n")[0])
    p.add_argument("--thickness", type=float, default=0.4, help="sample thickness in mm (0.4 or 0.8)")
    p.add_argument("--noise", type=float, default=0.0, help="relative noise on each reading (default 0: none)")
    p.add_argument("--draws", type=int, default=3, help="noise draws per material with --noise (default 3)")
    p.add_argument("--band-nm", default="400:950", help="the spectrometers' scored wavelengths START:STOP")
    p.add_argument("--out", type=Path, default=Path("out/bench-sensor"))
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


class _Material:
    def __init__(self, optics: Any, name: str, thickness_mm: float, inside: np.ndarray) -> None:
        s = optics.insert_sample(name, thickness_mm)
        self.name, self.physics = name, s.physics
        self.lam = optics.wavelengths_nm[inside]
        self.I = np.stack([s.I_b[inside], s.I_w[inside], s.I_c[inside]])
        self.rho = np.stack([optics.rho_black[inside], optics.rho_white[inside]])
        self.truth = np.stack([s.alpha[inside], s.sigma_t[inside], s.g[inside]])

    def truth_at(self, lam: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(lam, self.lam, t) for t in self.truth])


def _errors(fitted: Any, truth: np.ndarray) -> np.ndarray:
    return np.stack([np.abs(fitted.alpha - truth[0]), np.abs(fitted.sigma_t / truth[1] - 1),
                     np.abs(fitted.g - truth[2])])


def _noisy(values: np.ndarray, level: float, rng: np.random.Generator) -> np.ndarray:
    if level <= 0:
        return values
    return values * (1 + level * rng.standard_normal(values.shape)) + 2e-4 * rng.standard_normal(values.shape)


def build_id(name: str) -> str:
    """A build's stable name for other files to refer to it by ("AS7341 band-aware" -> "as7341-band-aware")."""
    return "-".join("".join(c if c.isalnum() else " " for c in name.lower()).split())


def run(args: Any) -> int:
    doc = measure(args)
    print(f"map {doc['map']}, {doc['material_count']} materials at {doc['thickness_mm']:g} mm (physics: "
          f"{', '.join(doc['physics'])}), noise {doc['noise']:g} x {doc['draws']} draw(s); spectrometers scored at "
          f"{doc['scored_pixels']} pixels {doc['band_nm'][0]:g}-{doc['band_nm'][1]:g} nm (c12880ma at "
          f"{doc['c12880ma_pixels']} pixels {doc['c12880ma_nm'][0]:.0f}-{doc['c12880ma_nm'][1]:.0f} nm), "
          f"AS7341 at {doc['channels']} channels")
    print(f"{'build':34s} {'materials':9s} {'α p95':>7s} {'σt p95':>7s} {'g p95':>7s} {'flagged':>11s} "
          f"{'ms/spectrum':>11s} {'x ideal':>7s}")
    for r in doc["builds"]:
        print(f"{r['build']:34s} {r['materials']:9s} {r['alpha_p95']:7.4f} {100 * r['sigma_t_rel_p95']:6.2f}% "
              f"{r['g_p95']:7.4f} {r['flagged']:5d} of {r['values']:<4d} {r['ms_per_spectrum']:11.1f} "
              f"{r['time_ratio_to_ideal']:7.2f}")
    print("\nband-aware bases on the inks (p95 and max over channels; BAND_UNRESOLVED is judged with the cubic only):")
    print(f"{'basis smoothness':20s} {'α p95':>7s} {'α max':>7s} {'σt p95':>7s} {'σt max':>7s} {'g p95':>7s} "
          f"{'flagged':>9s}")
    for r in doc["bases"]:
        print(f"{r['basis smoothness']:20s} {r['alpha_p95']:7.4f} {r['alpha_max']:7.4f} "
              f"{100 * r['sigma_t_rel_p95']:6.2f}% {100 * r['sigma_t_rel_max']:6.2f}% {r['g_p95']:7.4f} "
              f"{r['flagged']:3d} of {r['values']}")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "sensor.json"
    atomic_write(path, json.dumps({k: doc[k] for k in ("map", "thickness_mm", "noise", "draws", "builds", "bases")},
                                  indent=1) + "\n")
    print(f"wrote {path}")
    return 0


def measure(args: Any) -> dict[str, Any]:
    """Every build's figures from one run (the options of `register`, as a namespace), as a JSON-able dict:
    "builds" one row per build and material set (its "id" from `build_id`), "bases" the band-aware fit's bases."""
    from trimeter.inversion.bands import fit_bands
    from trimeter.inversion.api import fit as fit_map
    from trimeter.inversion.artifacts import load_artifacts
    from trimeter.spectrometer.i2c import CHANNEL_NM
    from trimeter.spectrometer.sensors import (BEAM_LED, C12880_FWHM_NM, PANEL_LEDS, as7341_weights,
                                               c12880_wavelengths_nm, emission, resample_matrix, slit_matrix)
    from trimeter.twin.optics import Optics, material_names

    if args.thickness not in MAP_FOR:
        raise InputError(f"--thickness: one of {', '.join(f'{t:g}' for t in MAP_FOR)} mm (the shipped device maps)")
    if not (0 <= args.noise < 0.5) or args.draws < 1:
        raise InputError("--noise must be in [0, 0.5) and --draws ≥ 1")
    try:
        lo, hi = (float(v) for v in args.band_nm.split(":"))
    except ValueError:
        raise InputError(f"--band-nm {args.band_nm!r}: give START:STOP in nm") from None
    model = load_artifacts(MAP_FOR[args.thickness])
    optics = Optics()
    pixels = optics.wavelengths_nm
    inside = (pixels >= 350) & (pixels <= 995)       # the AS7341 model's bands fall to zero inside
    materials = [_Material(optics, name, args.thickness, inside) for name in material_names()]
    lam = materials[0].lam
    scored = (lam >= lo) & (lam <= hi)
    weights = as7341_weights(lam)
    datasheet = np.array([CHANNEL_NM[c] for c in weights.channels])
    slit = slit_matrix(lam)
    panels, beam = emission(PANEL_LEDS, lam), emission(BEAM_LED, lam)
    rng = np.random.default_rng(args.seed)
    draws = args.draws if args.noise > 0 else 1
    chip_nm = c12880_wavelengths_nm()
    chip_nm = chip_nm[(chip_nm >= lam[0] + 1.5 * C12880_FWHM_NM) & (chip_nm <= lam[-1] - 1.5 * C12880_FWHM_NM)]
    chip_scored = (chip_nm >= lo) & (chip_nm <= hi)
    chip = resample_matrix(lam, chip_nm, C12880_FWHM_NM)
    builds = ("ideal spectrometer", "seabreeze (slit)", "c12880ma", "AS7341 per-channel",
              "AS7341 per-channel at centroids", "AS7341 band-aware")
    errors: dict[str, dict[str, list]] = {b: {} for b in builds}
    flags: dict[str, dict[str, list]] = {b: {} for b in builds}
    seconds: dict[str, float] = dict.fromkeys(builds, 0.0)
    variants: dict[str, list] = {f"{b} {s:g}": [] for b, s in BASIS_VARIANTS}
    variant_flags: dict[str, list] = {k: [] for k in variants}

    def record(build: str, m: _Material, e: np.ndarray, f: np.ndarray) -> None:
        errors[build].setdefault(m.name, []).append(e)
        flags[build].setdefault(m.name, []).append(f != 0)

    for m in materials:
        for _ in range(draws):
            I = _noisy(m.I, args.noise, rng)
            t0 = time.perf_counter()
            ideal = fit_map(model, I[0][scored], I[1][scored], I[2][scored], m.rho[0][scored], m.rho[1][scored])
            seconds["ideal spectrometer"] += time.perf_counter() - t0
            record("ideal spectrometer", m, _errors(ideal, m.truth[:, scored]), ideal.flags)
            # the slit blurs counts: sample (lamp · I) and reference (lamp · ρ_ref) alike
            ref_d, ref_c = slit @ panels, slit @ beam
            blurred = np.stack([slit @ (panels * m.I[0]) / ref_d, slit @ (panels * m.I[1]) / ref_d,
                                slit @ (beam * m.I[2]) / ref_c])
            blurred = _noisy(blurred, args.noise, rng)
            t0 = time.perf_counter()
            sb = fit_map(model, blurred[0][scored], blurred[1][scored], blurred[2][scored], m.rho[0][scored],
                         m.rho[1][scored])
            seconds["seabreeze (slit)"] += time.perf_counter() - t0
            record("seabreeze (slit)", m, _errors(sb, m.truth[:, scored]), sb.flags)
            chip_d, chip_c = chip @ panels, chip @ beam
            read = _noisy(np.stack([chip @ (panels * m.I[0]) / chip_d, chip @ (panels * m.I[1]) / chip_d,
                                    chip @ (beam * m.I[2]) / chip_c]), args.noise, rng)
            chip_rho = np.stack([chip @ (panels * m.rho[0]) / chip_d, chip @ (panels * m.rho[1]) / chip_d])
            t0 = time.perf_counter()
            c12 = fit_map(model, *(r[chip_scored] for r in read), *(r[chip_scored] for r in chip_rho))
            seconds["c12880ma"] += time.perf_counter() - t0
            record("c12880ma", m, _errors(c12, m.truth_at(chip_nm[chip_scored])), c12.flags)
            readings = _noisy(np.stack([weights.diffuse @ m.I[0], weights.diffuse @ m.I[1],
                                        weights.collimated @ m.I[2]]), args.noise, rng)
            r_b, r_w, r_c = readings
            rho_b, rho_w = weights.diffuse @ m.rho[0], weights.diffuse @ m.rho[1]
            t0 = time.perf_counter()
            per_channel = fit_map(model, r_b, r_w, r_c, rho_b, rho_w)
            seconds["AS7341 per-channel"] += time.perf_counter() - t0
            seconds["AS7341 per-channel at centroids"] = seconds["AS7341 per-channel"]
            # the fit's own flags (without PER_CHANNEL_BANDS, which every such value carries)
            record("AS7341 per-channel", m, _errors(per_channel, m.truth_at(datasheet)), per_channel.flags)
            record("AS7341 per-channel at centroids", m, _errors(per_channel, m.truth_at(weights.centre_nm)),
                   per_channel.flags)
            t0 = time.perf_counter()
            band = fit_bands(model, weights, r_b, r_w, r_c, rho_b, rho_w)
            seconds["AS7341 band-aware"] += time.perf_counter() - t0
            record("AS7341 band-aware", m, _errors(band.at_centres, m.truth_at(weights.centre_nm)),
                   band.at_centres.flags)
            if m.name in INKS:
                for basis, smooth in BASIS_VARIANTS:
                    v = fit_bands(model, weights, r_b, r_w, r_c, rho_b, rho_w, basis=basis,
                                  smoothness=smooth).at_centres
                    variants[f"{basis} {smooth:g}"].append(_errors(v, m.truth_at(weights.centre_nm)))
                    variant_flags[f"{basis} {smooth:g}"].append(v.flags != 0)

    spectra = len(materials) * draws
    rows: list[dict[str, Any]] = []
    for build in builds:
        for label, names in (("all", [m.name for m in materials]), ("inks", list(INKS))):
            e = np.concatenate([x for n in names for x in errors[build][n]], axis=1)
            f = np.concatenate([x for n in names for x in flags[build][n]])
            p95 = np.nanpercentile(e, 95, axis=1)
            rows.append({"id": build_id(build), "build": build, "materials": label, "alpha_p95": float(p95[0]),
                         "sigma_t_rel_p95": float(p95[1]), "g_p95": float(p95[2]),
                         "flagged": int(f.sum()), "values": int(f.size),
                         "ms_per_spectrum": 1e3 * seconds[build] / spectra,
                         "time_ratio_to_ideal": seconds[build] / seconds["ideal spectrometer"]})
    basis_rows: list[dict[str, Any]] = []
    for key, es in variants.items():
        e = np.concatenate(es, axis=1)
        p95 = np.nanpercentile(e, 95, axis=1)
        f = np.concatenate(variant_flags[key])
        basis_rows.append({"basis smoothness": key, "alpha_p95": float(p95[0]), "sigma_t_rel_p95": float(p95[1]),
                           "g_p95": float(p95[2]), "alpha_max": float(np.nanmax(e[0])),
                           "sigma_t_rel_max": float(np.nanmax(e[1])), "flagged": int(f.sum()), "values": int(f.size)})
    return {"map": model.name, "thickness_mm": args.thickness, "noise": args.noise, "draws": draws,
            "material_count": len(materials), "physics": sorted({m.physics for m in materials}),
            "scored_pixels": int(scored.sum()), "band_nm": [lo, hi], "channels": len(weights.channels),
            "c12880ma_pixels": int(chip_scored.sum()),
            "c12880ma_nm": [float(chip_nm[chip_scored][0]), float(chip_nm[chip_scored][-1])],
            "builds": rows, "bases": basis_rows}
