"""`trimeter fit --bands WEIGHTS.csv --input CHANNELS.csv`: a multichannel sensor's band readings → α, σt, g.

WEIGHTS: `wavelength_nm` and per channel `<CH>_diffuse`, `<CH>_collimated`, its effective weight under
the diffuse panels (I_b, I_w) and under the collimated LED (I_c), e.g. its measured response times the
lamp's spectrum (normalised by the fit); `--bands as7341` takes the built-in AS7341 model
(trimeter.spectrometer.sensors). CHANNELS: one row per channel, `channel, I_b, I_w, I_c` and optional
`rho_b, rho_w, I_b_std, I_w_std, I_c_std`. The fit (trimeter.inversion.bands) finds smooth spectra whose
band integrals match the readings; the output has one row per channel in input order, at the centroid
of its diffuse weight (`wavelength_nm`), and with `--grid START:STOP:STEP` rows on that wavelength grid
after them (their `channel` empty).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.inversion.bands import BandWeights
from trimeter.validation import shown

CHANNEL_COLUMNS = ("channel", "I_b", "I_w", "I_c")
CHANNEL_OPTIONAL = ("rho_b", "rho_w", "I_b_std", "I_w_std", "I_c_std")
OUTPUT = ("channel", "wavelength_nm", "alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "flags",
          "sigma_t_beer")
BUILT_IN = ("as7341",)
MAX_TABLE_BYTES = 1_000_000  # a CHANNELS table: one row per channel


def read_channels(path: Path) -> tuple[list[str], dict[str, np.ndarray]]:
    """CHANNELS: the channel names (the one text column) and the number columns, through the tables
    reader's rules (trimeter.tables); one clear InputError per problem."""
    from trimeter.tables import read_columns, read_text

    numbers = read_columns(path, required=CHANNEL_COLUMNS[1:], optional=CHANNEL_OPTIONAL, max_bytes=MAX_TABLE_BYTES,
                           what="--input")
    lines = [line for line in read_text(path, max_bytes=MAX_TABLE_BYTES, what="--input").splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    try:
        rows = list(csv.reader(lines))
    except csv.Error as exc:
        raise InputError(f"--input {path}: not a readable CSV ({exc})") from None
    header = [h.strip() for h in rows[0]]
    if "channel" not in header:
        raise InputError(f"--input {path}: missing column channel (have: {', '.join(map(shown, header))})")
    i = header.index("channel")
    return [row[i].strip() if i < len(row) else "" for row in rows[1:]], numbers


def read_weights(spec: str) -> BandWeights:
    """--bands: a WEIGHTS.csv, or a built-in sensor model's name."""
    from trimeter.spectrometer.sensors import as7341_weights, read_band_weights

    return as7341_weights() if spec in BUILT_IN else read_band_weights(Path(spec), what="--bands")


def parse_grid(text: str) -> np.ndarray:
    try:
        start, stop, step = (float(v) for v in text.split(":"))
    except ValueError:
        raise InputError(f"--grid {text!r}: give START:STOP:STEP in nm, e.g. 400:700:5") from None
    if not (all(map(math.isfinite, (start, stop, step))) and step > 0 and stop >= start) or (stop - start) / step > 1e5:
        raise InputError(f"--grid {text!r}: need START ≤ STOP and a positive STEP (at most 1e5 points)")
    return np.arange(start, stop + 0.5 * step, step)


def run_bands(args: argparse.Namespace) -> int:
    from trimeter.cli.cmd_fit import _write, check_declared_thickness, refuse_output_onto_inputs
    from trimeter.inversion.bands import fit_bands
    from trimeter.inversion.flags import advice
    from trimeter.maps.appearance import AppearanceMap, find_map
    from trimeter.maps.artifacts import load_artifacts

    if not args.maps or len(args.maps) != 1:
        raise InputError("--bands: fits with one --map (one thickness)")
    if args.method not in (None, "lut") or args.polish is not None:
        raise InputError("--bands: the band-aware fit has its own solver (no --method/--polish)")
    amap = AppearanceMap.load(find_map(args.maps[0]))
    check_declared_thickness(args.thickness, [amap])
    refuse_output_onto_inputs(args.output, [args.input, args.bands, *([amap.path] if amap.path else [])])
    grid_nm = parse_grid(args.grid) if args.grid else None
    weights = read_weights(args.bands)
    names, col = read_channels(args.input)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if "" in names or repeated:
        raise InputError(f"--input {args.input}: every row names its channel once ("
                         f"{'an empty name' if '' in names else 'repeated: ' + ', '.join(repeated)})")
    if len(names) < 2:
        raise InputError(f"--input {args.input}: one channel only; a band-aware fit needs at least 2 (it fits "
                         f"spectra across them)")
    weights = weights.select(names, where=f"--input {args.input}")
    result = fit_bands(load_artifacts(amap), weights, col["I_b"], col["I_w"], col["I_c"], col.get("rho_b"),
                       col.get("rho_w"), I_b_std=col.get("I_b_std"), I_w_std=col.get("I_w_std"),
                       I_c_std=col.get("I_c_std"), grid_nm=grid_nm)
    parts = [(names, result.centre_nm, result.at_centres)]
    if result.on_grid is not None and result.grid_nm is not None:
        parts.append(([""] * len(result.grid_nm), result.grid_nm, result.on_grid))
    notes = advice(result.at_centres.flags)
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    source = "declared with --thickness" if args.thickness else "not declared: the map's"
    print(f"thickness: {amap.thickness_mm:g} mm ({source}; map {amap.name}, band-aware fit of {len(names)} channels)",
          file=sys.stderr)
    if args.json:
        doc = {"method": "bands", "thickness_mm": amap.thickness_mm, "thickness_declared": bool(args.thickness),
               "maps": [{"name": amap.name, "thickness_mm": amap.thickness_mm, "sha256": amap.checksum}],
               "channels": _columns(*parts[0]), "advice": notes}
        if len(parts) > 1:
            doc["grid"] = _columns(*parts[1])
        _write(args.output, json.dumps(doc, indent=1, allow_nan=False) + "\n")
        return 0
    lines = [",".join((*OUTPUT, "thickness_mm"))]
    for labels, lam, r in parts:
        for i, label in enumerate(labels):
            values = [f"{v[i]:.9g}" for v in (lam, r.alpha, r.sigma_t, r.g, r.alpha_std, r.sigma_t_std, r.g_std)]
            lines.append(",".join([label, *values, str(int(r.flags[i])), f"{r.sigma_t_beer[i]:.9g}",
                                   f"{amap.thickness_mm:g}"]))
    _write(args.output, "\n".join(lines) + "\n")
    return 0


def _columns(labels: list[str], lam: np.ndarray, r: FitResult) -> dict:
    from trimeter.inversion.flags import describe

    def number(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    out: dict = {"channel": list(labels), "wavelength_nm": [number(v) for v in lam]}
    for k in OUTPUT[2:]:
        out[k] = [int(v) for v in r.flags] if k == "flags" else [number(v) for v in getattr(r, k)]
    out["flag_names"] = [describe(f) for f in r.flags]
    return out
