"""The mixture check of the paper's Sec. 5.2 (Fig. 13): do the measured parameters of a few inks predict
the colour of their mixtures?

For each mixture (volume fractions of the components), its reflectance on the instrument's black and
white backgrounds is predicted from the components' measured parameters — σa and σs add by fraction, g
is σs-weighted (SpectralMaterial.mixture) — through the forward model of the mixture's own set-up (the
appearance map of its thickness, at its measured backgrounds ρ_b(λ), ρ_w(λ)), and compared with the
reflectance measured on the mixture: ΔE2000 (CIE 1931 2°, D65; trimeter.library.colour) on black and
on white per square, and a colour-checker figure whose squares show the prediction (left) beside the
measurement (right), on white above and on black below.

Where the numbers come from:
- `take`: components from the library (`library:NAME`), results directories or parameters files;
  mixtures from results directories (their first thickness's I_b, I_w, ρ_b, ρ_w; the map their
  measurement.json names, or --map).
- `on_twin`: the twin's optics (trimeter.twin.optics, the same samples and backgrounds `trimeter sim`
  serves) render the components at 0.4 and 0.8 mm and the mixtures at 0.4 mm; the intensities get
  Gaussian noise of `noise_rel` (a capture's scatter, handed to the fit as the intensities' stds); the
  components are fitted on both thicknesses jointly with the shipped device maps (`trimeter.fit`, lut).
  This skips the firmware, the Modbus link and the spectrometer's exposures — what `trimeter measure`
  adds to a capture is covered by its own tests; a full-loop run is `trimeter sim --sample
  cyan-ink:0.5+yellow-ink:0.5` + `trimeter measure`, then `take`. The twin traces its samples
  independently of the map (trimeter.twin.observables; the check's mixtures too: tools/make_twin_observables.py
  --twin-mixtures), so the check sees the map's own error on inks and mixtures and the inks' fit errors;
  a mixture nobody traced is rendered with the map (mixtures.json says which).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trimeter.errors import InputError
from trimeter.library.colour import delta_e_2000, reflectance_to_xyz, xyz_to_lab
from trimeter.model.mixing import parse_fractions
from trimeter.results.medium import SpectralMaterial

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap

TWIN_INKS = ("cyan-ink", "magenta-ink", "yellow-ink")
TWIN_THICKNESSES_MM = (0.4, 0.8)
COLOUR_RANGE_NM = (380.0, 780.0)   # where the colour-matching functions weigh; the bins outside are not used
PASS_MEDIAN_DE = 1.0               # the paper's criterion for "indistinguishable" at a glance


@dataclass(frozen=True)
class MixtureObservation:
    """A measured mixture: its fractions, reflectances on black and white over its bins, its set-up."""
    label: str
    fractions: list[tuple[str, float]]
    wavelengths_nm: np.ndarray
    I_b: np.ndarray
    I_w: np.ndarray
    rho_b: np.ndarray
    rho_w: np.ndarray
    forward: AppearanceMap
    source: str


@dataclass(frozen=True)
class Square:
    """One mixture's predicted and measured colours (CIELAB, sRGB) and their ΔE2000 on black and on white."""
    label: str
    fractions: list[tuple[str, float]]
    source: str                   # where the mixture was measured
    lab_predicted: np.ndarray     # (2, 3): on black, on white
    lab_measured: np.ndarray
    srgb_predicted: np.ndarray    # (2, 3) linear sRGB
    srgb_measured: np.ndarray
    delta_e: np.ndarray           # (2,): on black, on white


def default_twin_mixtures(inks: Sequence[str] = TWIN_INKS, steps: Sequence[float] = (1 / 3, 1 / 2, 2 / 3)
                          ) -> list[list[tuple[str, float]]]:
    """Every pair of inks at each step, and all inks in equal parts (3 inks, 3 steps: 10 mixtures)."""
    out = [[(a, f), (b, 1.0 - f)] for a, b in combinations(inks, 2) for f in steps]
    if len(inks) > 2:
        out.append([(ink, 1.0 / len(inks)) for ink in inks])
    return out


def mixture_label(fractions: Sequence[tuple[str, float]]) -> str:
    return "+".join(f"{name}:{f:.4g}" for name, f in fractions)


def predict_square(components: dict[str, SpectralMaterial], obs: MixtureObservation) -> Square:
    """The prediction for one observed mixture and its colour difference (module docstring)."""
    missing = [name for name, _ in obs.fractions if name not in components]
    if missing:
        raise InputError(f"mixture {obs.label}: no component {missing[0]!r} (have: {', '.join(components)})")
    mixed = SpectralMaterial.mixture([components[n] for n, _ in obs.fractions], [f for _, f in obs.fractions])
    inside = (obs.wavelengths_nm >= COLOUR_RANGE_NM[0]) & (obs.wavelengths_nm <= COLOUR_RANGE_NM[1])
    lam = obs.wavelengths_nm[inside]
    on = mixed.at(lam)
    I_b, I_w, _ = obs.forward.query(on.alpha, on.sigma_t, on.g, obs.rho_b[inside], obs.rho_w[inside])
    predicted = np.stack([I_b, I_w])
    measured = np.stack([obs.I_b[inside], obs.I_w[inside]])
    usable = np.all(np.isfinite(predicted), axis=0) & np.all(np.isfinite(measured), axis=0)
    if usable.sum() < 0.9 * len(lam) or len(lam) < 10:
        raise InputError(f"mixture {obs.label}: the prediction or the measurement has no value in "
                         f"{np.count_nonzero(~usable)} of {len(lam)} bins within {COLOUR_RANGE_NM[0]:g}-"
                         f"{COLOUR_RANGE_NM[1]:g} nm (outside the map {obs.forward.name}?)")
    from trimeter.results.export import spectra_to_linear_srgb

    lab_p, lab_m = (xyz_to_lab(reflectance_to_xyz(lam[usable], s[:, usable])) for s in (predicted, measured))
    return Square(obs.label, obs.fractions, obs.source, lab_p, lab_m,
                  spectra_to_linear_srgb(lam[usable], predicted[:, usable]),
                  spectra_to_linear_srgb(lam[usable], measured[:, usable]), delta_e_2000(lab_p, lab_m))


# ------------------------------------------------------------------------------------------ the twin
def _twin_capture(optics: object, name: str, thickness_mm: float, rng: np.random.Generator, noise_rel: float,
                  keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from trimeter.twin.optics import Optics

    assert isinstance(optics, Optics)
    s = optics.insert_sample(name, thickness_mm)
    I_b, I_w, I_c = (v[keep] * (1.0 + noise_rel * rng.standard_normal(np.count_nonzero(keep)))
                     for v in (s.I_b, s.I_w, s.I_c))
    return I_b, I_w, I_c


def on_twin(mixtures: Sequence[Sequence[tuple[str, float]]] | None = None, *, noise_rel: float = 0.002,
            seed: int = 0) -> tuple[dict[str, SpectralMaterial], list[MixtureObservation], dict]:
    """Components measured (two thicknesses, fitted jointly) and mixtures measured (0.4 mm) on the twin's
    optics (module docstring). Returns (components, mixtures, what was done)."""
    from trimeter.inversion.artifacts import fit, open_map
    from trimeter.results.writer import Parameters
    from trimeter.twin.optics import Optics

    mixtures = default_twin_mixtures() if mixtures is None else [list(m) for m in mixtures]
    if not math.isfinite(noise_rel) or not 0 <= noise_rel <= 0.1:
        raise InputError(f"noise must be within 0-0.1 (relative), got {noise_rel!r}")
    inks = sorted({name for m in mixtures for name, _ in m})
    rng = np.random.default_rng(seed)
    maps = [open_map(f"device-n1.5-l{t:g}") for t in TWIN_THICKNESSES_MM]
    optics = Optics(appearance_map=[m.path for m in maps if m.path is not None])
    lam = optics.wavelengths_nm
    keep = (lam >= COLOUR_RANGE_NM[0] - 10) & (lam <= COLOUR_RANGE_NM[1] + 10)
    wl = lam[keep]
    rho_b, rho_w = optics.rho_black[keep], optics.rho_white[keep]
    components = {}
    for ink in inks:
        I = np.stack([np.stack(_twin_capture(optics, ink, t, rng, noise_rel, keep)) for t in TWIN_THICKNESSES_MM])
        std = np.maximum(noise_rel * np.abs(I), 1e-6) if noise_rel > 0 else None
        result = fit(maps, I[:, 0], I[:, 1], I[:, 2], rho_b, rho_w, "lut",
                     I_b_std=None if std is None else std[:, 0], I_w_std=None if std is None else std[:, 1],
                     I_c_std=None if std is None else std[:, 2])
        components[ink] = SpectralMaterial.from_parameters(Parameters.from_fit(wl, result))
    observed = []
    for fractions in mixtures:
        label = mixture_label(fractions)
        I_b, I_w, _ = _twin_capture(optics, label, TWIN_THICKNESSES_MM[0], rng, noise_rel, keep)
        physics = optics.sample.physics if optics.sample is not None else "?"
        observed.append(MixtureObservation(label, list(fractions), wl, I_b, I_w, rho_b, rho_w, maps[0],
                                           f"twin optics, {TWIN_THICKNESSES_MM[0]:g} mm, rendered by {physics}"))
    info = {"source": "twin optics", "components": inks, "component_thicknesses_mm": list(TWIN_THICKNESSES_MM),
            "mixture_thickness_mm": TWIN_THICKNESSES_MM[0], "noise_rel": noise_rel, "seed": seed,
            "maps": [m.name for m in maps], "method": "lut"}
    return components, observed, info


# ------------------------------------------------------------------------------------------ taking
def component_material(source: str, library_db: str | None = None) -> SpectralMaterial:
    """A component: `library:NAME` (the material library), a results directory or a parameters file."""
    if source.startswith("library:"):
        from trimeter.library.store import Library

        with Library(library_db) as lib:
            return lib.get(source[len("library:"):]).material()
    from trimeter.results.reader import load_result

    return load_result(source).material


def observed_mixture(spec: str, result: str, forward: str | None = None) -> MixtureObservation:
    """A mixture `spec` (NAME:FRACTION+…, names of components) measured in the results directory `result`."""
    from trimeter.inversion.artifacts import open_map
    from trimeter.results.reader import load

    fractions = parse_fractions(spec)
    m = load(result)
    refl = m.reflectances[0]
    name = forward or (m.maps[0] if m.maps else None)
    if name is None:
        raise InputError(f"{m.path}: names no map; give --map")
    try:
        amap = open_map(name)
    except InputError as exc:
        raise InputError(f"{m.path}: its map {name!r} is not here ({exc}); give --map") from None
    return MixtureObservation(spec, fractions, np.asarray(refl.wavelengths_nm, float), np.asarray(refl.I_b, float),
                              np.asarray(refl.I_w, float), np.asarray(refl.rho_b, float),
                              np.asarray(refl.rho_w, float), amap, str(m.path))


# ------------------------------------------------------------------------------------------ output
def table(squares: Sequence[Square]) -> str:
    lines = [f"{'mixture':44s} {'ΔE00 black':>10s} {'ΔE00 white':>10s}"]
    lines += [f"{s.label:44s} {s.delta_e[0]:10.2f} {s.delta_e[1]:10.2f}" for s in squares]
    every = np.concatenate([s.delta_e for s in squares])
    lines.append(f"{'median (every square, both backgrounds)':44s} {np.median(every):10.2f}   "
                 f"max {every.max():.2f}; median on black {np.median([s.delta_e[0] for s in squares]):.2f}, "
                 f"on white {np.median([s.delta_e[1] for s in squares]):.2f}")
    return "\n".join(lines)


def draw_checker(path: Path, squares: Sequence[Square], *, columns: int = 5, title: str = "") -> Path:
    """Fig. 13's layout: each square on white (top) and on black (bottom), predicted left, measured right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from trimeter.atomic import atomic_output
    from trimeter.results.export import srgb_encode

    rows = math.ceil(len(squares) / columns)
    fig, ax = plt.subplots(figsize=(1.9 * columns + 0.4, 2.2 * rows + 0.7))
    ax.set_xlim(0, columns)
    ax.set_ylim(rows, 0)
    ax.set_axis_off()
    fig.patch.set_facecolor("0.45")
    for k, s in enumerate(squares):
        r, c = divmod(k, columns)
        for y0, i in ((0.05, 1), (0.40, 0)):   # white above, black below
            for x0, rgb in ((0.05, s.srgb_predicted[i]), (0.51, s.srgb_measured[i])):   # a hairline between
                ax.add_patch(plt.Rectangle((c + x0, r + y0), 0.44, 0.35, color=srgb_encode(rgb)))
        parts = [f"{name.removesuffix('-ink')} {f:.2f}" for name, f in s.fractions]
        ax.text(c + 0.5, r + 0.88, " + ".join(parts[:2]) + ("\n+ " + " + ".join(parts[2:]) if parts[2:] else "")
                + f"\nΔE00 {s.delta_e[1]:.2f} / {s.delta_e[0]:.2f}", ha="center", va="center", fontsize=6,
                color="white")
    fig.suptitle(title or "predicted (left) | measured (right); on white (top), on black (bottom); "
                 "ΔE00 white / black", fontsize=8, color="white")
    with atomic_output(path) as f:
        fig.savefig(f, format="png", dpi=120, facecolor=fig.get_facecolor())
    plt.close(fig)
    return path


def write_outputs(out: Path, squares: Sequence[Square], info: dict) -> dict:
    from trimeter.atomic import atomic_write

    out.mkdir(parents=True, exist_ok=True)
    every = np.concatenate([s.delta_e for s in squares])
    summary = {**info, "mixtures": [{"mixture": s.label, "measured": s.source,
                                     "delta_e2000_black": float(s.delta_e[0]),
                                     "delta_e2000_white": float(s.delta_e[1]),
                                     "lab_predicted": s.lab_predicted.tolist(), "lab_measured": s.lab_measured.tolist()}
                                    for s in squares],
               "median_delta_e2000": float(np.median(every)), "max_delta_e2000": float(every.max()),
               "observer": "CIE 1931 2°", "illuminant": "D65", "figure": "checker.png"}
    atomic_write(out / "mixtures.json", json.dumps(summary, indent=1))
    draw_checker(out / "checker.png", squares)
    return summary


# ------------------------------------------------------------------------------------------ command
def register_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("mixtures", help="the mixture check (paper Sec. 5.2): predicted vs measured ΔE2000",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--twin", action="store_true", help="measure 3 inks and 10 mixtures on the twin's optics")
    p.add_argument("--noise", default="0.002", help="--twin: relative noise of the intensities (default 0.002)")
    p.add_argument("--seed", default="0", help="--twin: noise seed")
    p.add_argument("--component", action="append", default=[], metavar="NAME=SOURCE",
                   help="a component: library:MATERIAL, a results directory or a parameters file")
    p.add_argument("--mixture", action="append", default=[], metavar="NAME:F+NAME:F=RESULT",
                   help="a measured mixture of named components by volume fractions and its results directory")
    p.add_argument("--map", help="the forward model of the mixtures' set-up (default: the map each names)")
    p.add_argument("-o", "--output", help="directory for mixtures.json and checker.png (default: "
                                          "<data dir>/mixture-check/<time>)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import time

    from trimeter.paths import data_dir
    from trimeter.validation import require_number

    if args.twin == bool(args.component or args.mixture):
        raise InputError("either --twin, or --component NAME=SOURCE … and --mixture SPEC=RESULT …")
    if args.twin:
        components, observed, info = on_twin(noise_rel=require_number("--noise", args.noise, lo=0.0, hi=0.1),
                                             seed=int(require_number("--seed", args.seed, lo=0, hi=2**31)))
    else:
        components = {}
        for item in args.component:
            name, sep, source = item.partition("=")
            if not sep or not name or not source:
                raise InputError(f"--component {item!r}: NAME=SOURCE")
            components[name] = component_material(source, getattr(args, "db", None))
        observed = []
        for item in args.mixture:
            spec, sep, result = item.rpartition("=")
            if not sep or not spec or not result:
                raise InputError(f"--mixture {item!r}: NAME:FRACTION+NAME:FRACTION=RESULT")
            observed.append(observed_mixture(spec, result, args.map))
        if not observed:
            raise InputError("no --mixture given")
        info = {"source": "taken", "components": {i.partition("=")[0]: i.partition("=")[2] for i in args.component},
                "mixture_results": [o.source for o in observed]}
    squares = [predict_square(components, o) for o in observed]
    print(table(squares))
    sources: dict[str, int] = {}
    for o in observed:
        sources[o.source] = sources.get(o.source, 0) + 1
    if len(sources) < len(observed):   # the twin's: how they were rendered (taken ones: mixtures.json)
        print("mixtures measured: " + "; ".join(f"{k} ×{n}" for k, n in sources.items()))
    out = Path(args.output) if args.output else data_dir() / "mixture-check" / time.strftime("%Y%m%dT%H%M%S")
    summary = write_outputs(out, squares, info)
    verdict = "within" if summary["median_delta_e2000"] <= PASS_MEDIAN_DE else "above"
    print(f"median ΔE2000 {summary['median_delta_e2000']:.2f}: {verdict} {PASS_MEDIAN_DE:g}; "
          f"mixtures.json and checker.png in {out}")
    return 0
