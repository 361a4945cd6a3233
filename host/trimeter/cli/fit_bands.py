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


def read_table(path: Path, option: str, required: tuple[str, ...], text: tuple[str, ...] = (),
               optional: tuple[str, ...] | None = None) -> dict[str, list]:
    """A CSV's columns by name: `text` columns as stripped strings, the others as floats (empty → NaN);
    `optional` None: every other column is read too. One clear InputError per problem."""
    try:
        raw = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{option} {path}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
    lines = (line for line in raw.splitlines() if line.strip() and not line.lstrip().startswith("#"))
    try:
        rows = list(csv.reader(lines))
    except csv.Error as exc:
        raise InputError(f"{option} {path}: not a readable CSV ({exc})") from None
    header = [h.strip() for h in rows[0]] if rows else []
    duplicated = sorted({h for h in header if header.count(h) > 1})
    if duplicated:
        raise InputError(f"{option} {path}: column(s) {', '.join(map(shown, duplicated))} appear more than once")
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(f"{option} {path}: missing column(s) {', '.join(missing)} (have: "
                         f"{', '.join(map(shown, header)) or 'none'})")
    wanted = [c for c in header if c in required or optional is None or c in optional]
    columns: dict[str, list] = {c: [] for c in wanted}
    for row_no, row in enumerate(rows[1:], start=2):
        for c in wanted:
            i = header.index(c)
            cell = row[i].strip() if i < len(row) else ""
            if c in text:
                columns[c].append(cell)
                continue
            try:
                columns[c].append(float(cell) if cell else math.nan)
            except ValueError:
                raise InputError(f"{option} {path}: line {row_no}, column {c}: {shown(cell)} is not a number") from None
    if len(rows) < 2:
        raise InputError(f"{option} {path}: no data rows")
    return columns


def read_weights(spec: str) -> BandWeights:
    """--bands: a WEIGHTS.csv, or a built-in sensor model's name."""
    from trimeter.inversion.bands import band_weights

    if spec in BUILT_IN:
        from trimeter.spectrometer.sensors import as7341_weights

        return as7341_weights()
    path = Path(spec)
    table = read_table(path, "--bands", ("wavelength_nm",))
    names = [c[: -len("_diffuse")] for c in table if c.endswith("_diffuse")]
    lonely = [c for c in table if c.endswith("_collimated") and c[: -len("_collimated")] not in names]
    if not names:
        raise InputError(f"--bands {path}: no <channel>_diffuse columns (have: {', '.join(table)})")
    without = [n for n in names if f"{n}_collimated" not in table]
    if without or lonely:
        raise InputError(f"--bands {path}: each channel needs both <channel>_diffuse and <channel>_collimated "
                         f"(incomplete: {', '.join(without + [c.rsplit('_', 1)[0] for c in lonely])})")
    return band_weights(table["wavelength_nm"], names, [table[f"{n}_diffuse"] for n in names],
                        [table[f"{n}_collimated"] for n in names], where=f"--bands {path}")


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
    table = read_table(args.input, "--input", CHANNEL_COLUMNS, text=("channel",), optional=CHANNEL_OPTIONAL)
    names = table["channel"]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if "" in names or repeated:
        raise InputError(f"--input {args.input}: every row names its channel once ("
                         f"{'an empty name' if '' in names else 'repeated: ' + ', '.join(repeated)})")
    if len(names) < 2:
        raise InputError(f"--input {args.input}: one channel only; a band-aware fit needs at least 2 (it fits "
                         f"spectra across them)")
    weights = weights.select(names, where=f"--input {args.input}")
    col = {k: np.asarray(v, dtype=float) for k, v in table.items() if k != "channel"}
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
