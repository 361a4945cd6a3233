"""`trimeter fit`: measured intensities (CSV) → α, σt [1/mm], g per wavelength (CSV or JSON).

    trimeter fit --map MAP [--map MAP2] --input meas.csv [--thickness MM …] [--method lut|mlp|paper] [-o params.csv]
                 [--json] [--polish N]
    trimeter fit --table TABLE.tlut --input meas.csv [--thickness MM] [--refine [--polish N]] …
    trimeter fit --on-device --port PORT --input meas.csv [--thickness MM] …
    trimeter fit --map MAP --bands WEIGHTS.csv|as7341 --input channels.csv [--grid START:STOP:STEP] …

`--table` fits from a device table alone (maps/<name>.tlut: the inverse grid, the compact forward
model, the in-scattering correction, n, ℓ and the reference backgrounds; no map file needed) with the
instrument's own fit: the C source the firmware runs, here in double precision, so that it gives what
`--on-device` gives with that table (to the device's single precision). That fit returns α, σt, g and
flags; their stds are computed on the host from the same table (trimeter.inversion.table_std: the
intensities' stds — the I_*_std columns, else the fit's noise model — and the map's own error the table
carries, propagated through the table's compact model, as a --map fit propagates them through the map).
`--refine` fits instead on the table's forward model refined at load onto a grid with the map's lut fit
(--polish; between the table's nodes its α and g may differ from the device's). `--on-device` sends the
bins to the instrument, which fits them with the table in its active slot (identified by its SHA-256 on
stderr and in the JSON); the stds are added here from that table, as with --table, and stderr and the
JSON say so. `--polish N`: at most N Newton steps after the method's guess (0: its raw answer; default:
the method's own).

Input columns: wavelength_nm, I_b, I_w, I_c; optional rho_b, rho_w (per-wavelength backgrounds;
default: the map's reference backgrounds) and thickness_mm (required with two maps: tells which rows
belong to which map; both thicknesses must cover the same wavelengths); I_b_std, I_w_std, I_c_std
(the intensities' standard deviations, e.g. `measure`'s reflectances.csv: the stds then are those of
this measurement, not of a default noise model) and thickness_std_mm (the sample thickness's std, one
value per thickness). Empty cells and "nan" are missing values: those bins come back flagged with NaN
results, the others are unaffected (a missing std: the default noise model's for that bin).
`--bands`: a multichannel sensor's band readings, fitted band-aware (trimeter.cli.fit_bands says how).

Output columns: wavelength_nm, alpha, sigma_t, g, alpha_std, sigma_t_std, g_std, flags, sigma_t_beer,
thickness_mm (flags: trimeter.inversion.flags.FitFlag bits; the JSON form also names them).
Rows come out in wavelength order. With CSV output the input is read, fitted and written in chunks, so
an input of any length fits in bounded memory (trimeter.cli.fit_stream: a large input must then be in
wavelength order; a bad row found part way leaves no -o file, while stdout has had the rows before it);
--json and --on-device read their input whole, up to a size limit.
The thickness is never assumed silently: σt scales as 1/ℓ, so a map of another thickness than the
sample's gives σt off by their ratio. The output states the thickness the fit used (the map's; with
two maps "0.4+0.8"), and so does a line on stderr; `--thickness` declares the sample's, and a map of
another thickness is then an error.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, SupportsFloat

import numpy as np

from trimeter.cli import fit_stream
from trimeter.cli._instrument import add_instrument_args
from trimeter.cli.fit_stream import OUTPUT, Chunk, check_declared_thickness, refuse_output_onto_inputs, write_output
from trimeter.errors import InputError
from trimeter.inversion.methods import METHODS

if TYPE_CHECKING:
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.formats.device_table import DeviceTable
    from trimeter.inversion.table_std import TableStds

    # what a fit here inverts through: appearance maps (one per thickness) or one device table
    FitSource = AppearanceMap | DeviceTable



def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("fit", help="invert measured I_b, I_w, I_c to alpha, sigma_t, g per wavelength",
                              description=__doc__.split("\n\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--map", dest="maps", action="append",
                        help="appearance map (file or shipped name); give twice for two thicknesses")
    source.add_argument("--table", type=Path,
                        help="device table (.tlut) to fit from alone, with the instrument's own fit (what "
                             "--on-device gives with that table, here in double precision; stds from the table)")
    source.add_argument("--on-device", action="store_true",
                        help="fit on the instrument (--port) with the table in its active slot")
    p.add_argument("--refine", action="store_true",
                   help="with --table: fit on the table's model refined at load (the lut fit, --polish) "
                        "instead of the instrument's fit")
    add_instrument_args(p, spectrometer=False)
    p.add_argument("--polish", type=_polish_steps, metavar="N",
                   help="at most N Newton steps after the method's guess (0: its raw answer; default: the method's)")
    p.add_argument("--input", required=True, type=Path,
                   help="CSV with wavelength_nm,I_b,I_w,I_c[,rho_b,rho_w,thickness_mm]")
    p.add_argument("--thickness", type=float, action="append",
                   help="the sample's thickness in mm (once per --map); a map of another thickness is an error")
    p.add_argument("--method", choices=METHODS, help="inversion method (default: lut)")
    p.add_argument("--bands", metavar="WEIGHTS.csv",
                   help="band weights of a multichannel sensor (or 'as7341': the built-in model); --input then "
                        "holds one row per channel (channel,I_b,I_w,I_c[,rho_b,rho_w,*_std])")
    p.add_argument("--grid", metavar="START:STOP:STEP", help="with --bands: the spectra on this grid as well (nm)")
    p.add_argument("-o", "--output", type=Path, help="output CSV (default: stdout)")
    p.add_argument("--json", action="store_true", help="print JSON instead of CSV")
    p.set_defaults(func=run)


def _polish_steps(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 100:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of Newton steps in 0..100")
    return value


def _split_thicknesses(data: dict[str, np.ndarray], amaps: Sequence[FitSource], path: Path) -> list[np.ndarray]:
    """Per map, the row indices that belong to it (sorted by wavelength)."""
    n = len(data["wavelength_nm"])
    if len(amaps) == 1:
        if "thickness_mm" in data:
            t = data["thickness_mm"]
            if np.any(np.isfinite(t) & ~amaps[0].setup.matches_thickness(t)):
                raise InputError(f"--input {path}: column thickness_mm has rows not matching the map's "
                                 f"thickness {amaps[0].thickness_mm:g} mm")
        return [np.argsort(data["wavelength_nm"], kind="stable")]
    if "thickness_mm" not in data:
        raise InputError(f"--input {path}: with {len(amaps)} maps the column thickness_mm must say "
                         f"which rows belong to which")
    groups, used = [], np.zeros(n, bool)
    for amap in amaps:
        rows = np.flatnonzero(amap.setup.matches_thickness(data["thickness_mm"]))
        if not len(rows):
            raise InputError(f"--input {path}: no rows with thickness_mm = {amap.thickness_mm:g} (map {amap.name})")
        used[rows] = True
        groups.append(rows[np.argsort(data["wavelength_nm"][rows], kind="stable")])
    if not used.all():
        raise InputError(f"--input {path}: {int((~used).sum())} row(s) have a thickness_mm matching none of the maps")
    ref = data["wavelength_nm"][groups[0]]
    for rows, amap in zip(groups[1:], amaps[1:], strict=True):
        if len(rows) != len(ref) or not np.allclose(data["wavelength_nm"][rows], ref):
            raise InputError(f"--input {path}: thickness {amap.thickness_mm:g} mm does not cover the same "
                             f"wavelengths as {amaps[0].thickness_mm:g} mm")
    return groups


def _fit_models(args: argparse.Namespace) -> list[FitSource]:
    """What the fit inverts through: the maps, or one device table (from a file, or the instrument's)."""
    from trimeter.formats.appearance import AppearanceMap, find_map

    if args.refine and args.table is None:
        raise InputError("--refine: only with --table (it names how the table's model is fitted)")
    if args.maps:
        if args.port:
            raise InputError("--port: only with --on-device (a --map fit runs here)")
        return [AppearanceMap.load(find_map(m)) for m in args.maps]
    if args.method not in (None, "lut"):
        raise InputError(f"--method {args.method}: a device table fits with method lut (the paper and mlp methods "
                         f"need the map and its network: use --map)")
    if args.table is not None:
        from trimeter.formats.device_table import DeviceTable

        if args.port:
            raise InputError("--port: only with --on-device (--table fits here, from the file)")
        if args.polish is not None and not args.refine:
            raise InputError("--polish: the instrument's fit has its own polish (add --refine to polish on the "
                             "table's refined model)")
        return [DeviceTable.load(args.table)]
    if args.polish is not None:
        raise InputError("--polish: the instrument fits with its own polish (fit from its table here with --table)")
    return []  # --on-device: the table is read from the instrument


def run(args: argparse.Namespace) -> int:
    from trimeter.inversion.flags import advice, describe
    from trimeter.inversion.artifacts import fit
    from trimeter.formats.device_table import DeviceTable

    if args.bands is not None:
        from trimeter.cli.fit_bands import run_bands

        return run_bands(args)
    if args.grid is not None:
        raise InputError("--grid: only with --bands (a per-wavelength fit reports at its input's wavelengths)")
    amaps = _fit_models(args)
    if args.on_device:
        return _run_on_device(args)
    table_file = amaps[0] if isinstance(amaps[0], DeviceTable) else None  # --table
    if table_file is not None and not args.refine:
        return _run_table_fit(args, table_file)
    method = args.method or "lut"
    refuse_output_onto_inputs(args.output, [args.input, *(m.path for m in amaps if m.path is not None)])
    if len({round(m.thickness_mm, 9) for m in amaps}) != len(amaps):
        raise InputError("--map: the maps must be for different thicknesses")
    check_declared_thickness(args.thickness, amaps)
    if not args.json:
        return _run_streamed(args, amaps, method, table_file)
    data = fit_stream.read_whole(args.input)
    groups = _split_thicknesses(data, amaps, args.input)
    stack = lambda name: np.stack([data[name][rows] for rows in groups])  # noqa: E731
    rho_b = stack("rho_b") if "rho_b" in data else None
    rho_w = stack("rho_w") if "rho_w" in data else None
    options: dict[str, Any] = {name: stack(name) for name in ("I_b_std", "I_w_std", "I_c_std") if name in data}
    if "thickness_std_mm" in data:
        options["thickness_std_mm"] = _thickness_std(data["thickness_std_mm"], groups, amaps, args.input)
    if args.polish is not None:
        options["polish"] = args.polish
    result = fit(amaps, stack("I_b"), stack("I_w"), stack("I_c"), rho_b, rho_w, method=method, **options)
    columns = {"wavelength_nm": data["wavelength_nm"][groups[0]], **result.as_dict()}
    notes = advice(result.flags, len(amaps))
    for note in notes:  # stderr: stdout may be the CSV
        print(f"note: {note}", file=sys.stderr)
    used = "+".join(f"{m.thickness_mm:g}" for m in amaps)
    identity = _table_identity(table_file, "file") if table_file is not None else None
    print(_thickness_line(args, amaps, identity), file=sys.stderr)
    flag_names = [describe(f) for f in result.flags]
    _write_result(args, columns, used, method, [m.thickness_mm for m in amaps], amaps, flag_names, notes,
                  identity)
    return 0


def _thickness_line(args: argparse.Namespace, amaps: Sequence[FitSource], identity: dict[str, Any] | None) -> str:
    """The stderr line that states the thickness the fit used and what it fitted with."""
    used = "+".join(f"{m.thickness_mm:g}" for m in amaps)
    source = "declared with --thickness" if args.thickness else "not declared: the map's" if len(amaps) == 1 \
        else "not declared: the maps'"
    fitted = f"table {identity['name']} (sha256 {identity['sha256'][:12]}…), refined at load" if identity else \
        f"map {', '.join(m.name for m in amaps)}"
    return f"thickness: {used} mm ({source}; {fitted})"


def _run_streamed(args: argparse.Namespace, models: Sequence[FitSource], method: str,
                  table_file: DeviceTable | None) -> int:
    """The maps (or a table refined at load) with CSV output: the input read, fitted and written in chunks
    (trimeter.cli.fit_stream), the same output as one fit of every row."""
    from trimeter.inversion.artifacts import fit

    thickness_stds: list[list[float]] = [[] for _ in models]  # fixed by the first chunk: one per sample
    bins_before = [0]  # the chunk's first bin in the whole input (the paper method's samples)

    def fit_chunk(chunk: Chunk) -> Chunk:
        groups = _split_thicknesses(chunk, models, args.input)  # checks thickness_mm; in order already
        stack = lambda name: np.stack([chunk[name][rows] for rows in groups])  # noqa: E731
        options: dict[str, Any] = {name: stack(name) for name in ("I_b_std", "I_w_std", "I_c_std") if name in chunk}
        if "thickness_std_mm" in chunk:
            options["thickness_std_mm"] = [
                _streamed_thickness_std(chunk["thickness_std_mm"][rows], seen, model, args.input)
                for rows, seen, model in zip(groups, thickness_stds, models, strict=True)]
        if args.polish is not None:
            options["polish"] = args.polish
        if method == "paper":
            options["first_row"] = bins_before[0]
        bins_before[0] += len(groups[0])
        result = fit(list(models), stack("I_b"), stack("I_w"), stack("I_c"),
                     stack("rho_b") if "rho_b" in chunk else None, stack("rho_w") if "rho_w" in chunk else None,
                     method=method, **options)
        return {"wavelength_nm": chunk["wavelength_nm"][groups[0]], **result.as_dict()}

    identity = _table_identity(table_file, "file") if table_file is not None else None
    chunks = None if len(models) == 1 else lambda read: _paired(read, models, args.input)
    tally = fit_stream.fit_csv(args.input, args.output, fit_chunk, "+".join(f"{m.thickness_mm:g}" for m in models),
                               regroup=chunks)
    for note in tally.advice(len(models)):
        print(f"note: {note}", file=sys.stderr)
    print(_thickness_line(args, models, identity), file=sys.stderr)
    if args.output is not None:
        print(f"wrote {args.output}", file=sys.stderr)
    return 0


def _paired(chunks: Iterator[Chunk], models: Sequence[FitSource], path: Path) -> Iterator[Chunk]:
    """Chunks re-cut so that each holds as many rows of every thickness: the i-th row of one thickness is
    fitted with the i-th of the others, as in one fit of all rows (rows past the shortest thickness's are
    carried into the next chunk)."""
    carry: Chunk | None = None
    for chunk in chunks:
        if carry is not None:
            chunk = {c: np.concatenate([carry[c], v]) for c, v in chunk.items()}
        if "thickness_mm" not in chunk:
            raise InputError(f"--input {path}: with {len(models)} maps the column thickness_mm must say "
                             f"which rows belong to which")
        member = [m.setup.matches_thickness(chunk["thickness_mm"]) for m in models]
        shortest = min(int(m.sum()) for m in member)
        keep = ~np.logical_or.reduce(member)  # rows of no thickness: kept, to be refused with the chunk
        for m in member:
            keep |= m & (np.cumsum(m) <= shortest)
        carry = {c: v[~keep] for c, v in chunk.items()}
        if keep.any():
            yield {c: v[keep] for c, v in chunk.items()}
    if carry is not None and len(carry["wavelength_nm"]):
        counts = [int(m.setup.matches_thickness(carry["thickness_mm"]).sum())
                  for m in models]
        longer = models[int(np.argmax(counts))]
        raise InputError(f"--input {path}: thickness {longer.thickness_mm:g} mm has {max(counts)} more row(s) than "
                         f"another: the thicknesses must cover the same wavelengths")


def _streamed_thickness_std(column: np.ndarray, seen: list[float], model: FitSource, path: Path) -> float:
    """The sample thickness's std for a chunk of a streamed input: the first chunk's (one value), which every
    later row must repeat or leave empty."""
    if not seen:
        _refuse_unknown_std(column, path)
    elif np.isinf(column).any():
        _refuse_unknown_std(column[np.isinf(column)], path)
    values = np.unique(column[np.isfinite(column)])
    first = not seen
    if first:
        seen.append(float(values[0]) if len(values) else math.nan)
    if len(values) > 1 or (len(values) and values[0] != seen[0]):
        if not first and math.isnan(seen[0]):
            raise InputError(f"--input {path}: column thickness_std_mm is empty on the first rows but not later; "
                             f"the rows are fitted as they are read, so give the std from the first row on")
        shown_values = sorted({*values.tolist(), *([] if math.isnan(seen[0]) else [seen[0]])})
        raise InputError(f"--input {path}: column thickness_std_mm differs between the rows of thickness "
                         f"{model.thickness_mm:g} mm ({shown_values[0]:g}, {shown_values[1]:g}, …): one sample, "
                         f"one std")
    return 0.0 if math.isnan(seen[0]) else seen[0]


def _refuse_unknown_std(column: np.ndarray, path: Path) -> None:
    """A sample's thickness_std_mm cells: an infinite one, or none finite at all (NaN, empty), is refused — never
    read as 0, an exact thickness. Empty cells beside a finite one repeat it."""
    if np.isinf(column).any() or not np.isfinite(column).any():
        raise InputError(f"--input {path}: column thickness_std_mm is not a finite number for a sample (NaN, "
                         f"empty or infinite; 0: the thickness is exact)")


def _table_identity(table: DeviceTable, source: str, slot: str | None = None) -> dict[str, Any]:
    """A device table as the output names it: its own SHA-256 and CRC-32, its parent map's SHA-256."""
    out = {"name": table.name, "source": source, "sha256": table.sha256, "crc32": f"{table.crc32:08x}",
           "parent_map_sha256": table.parent_sha256, "thickness_mm": table.thickness_mm}
    if table.path is not None:
        out["path"] = str(table.path)
    if slot is not None:
        out["slot"] = slot
    return out


def _write_result(args: argparse.Namespace, columns: dict[str, np.ndarray], used: str, method: str,
                  thicknesses: list[float], models: Sequence[FitSource], flag_names: list[str], notes: list[str],
                  table: dict[str, Any] | None) -> None:
    """The fit's output, the same for every source: CSV (OUTPUT columns) or JSON."""
    if args.json:
        doc = {"method": method, "thickness_mm": thicknesses if len(thicknesses) > 1 else thicknesses[0],
               "thickness_declared": bool(args.thickness),
               "maps": [{"name": m.name, "thickness_mm": m.thickness_mm, "sha256": m.checksum} for m in models],
               "columns": {k: [_json_number(v) for v in columns[k]] for k in OUTPUT if k != "thickness_mm"},
               "flag_names": flag_names, "advice": notes}
        if table is not None:
            doc["table"] = table
        write_output(args.output, json.dumps(doc, indent=1, allow_nan=False) + "\n")
        return
    write_output(args.output, ",".join(OUTPUT) + "\n" + fit_stream.csv_rows(columns, used))


def _run_table_fit(args: argparse.Namespace, table: DeviceTable) -> int:
    """The bins fitted here with the instrument's own fit (native.TableFitter, double precision) from the
    table file alone, their stds from the same table (table_std.TableStds)."""
    from trimeter.inversion import native
    from trimeter.inversion.table_std import TableStds

    refuse_output_onto_inputs(args.output, [args.input, args.table])
    check_declared_thickness(args.thickness, [table])
    fitter, stds = native.TableFitter(table.to_bytes()), TableStds(table)
    source = "declared with --thickness" if args.thickness else "not declared: the table's"
    fitted = f"table {table.name} (sha256 {table.sha256[:12]}…) with the instrument's fit, stds from the same table"
    where = f"thickness: {table.thickness_mm:g} mm ({source}; {fitted})"
    if not args.json:
        seen: list[float] = []  # the sample thickness's std, fixed by the first chunk

        def fit_chunk(chunk: Chunk) -> Chunk:
            rows = _split_thicknesses(chunk, [table], args.input)[0]
            thickness_std = _streamed_thickness_std(chunk["thickness_std_mm"][rows], seen, table, args.input) \
                if "thickness_std_mm" in chunk else 0.0
            result = fitter.fit(chunk["I_b"][rows], chunk["I_w"][rows], chunk["I_c"][rows],
                                *_backgrounds(chunk, rows, table))
            return _table_fit_columns(chunk, rows, table, stds, result, thickness_std)

        tally = fit_stream.fit_csv(args.input, args.output, fit_chunk, f"{table.thickness_mm:g}")
        for note in tally.advice(1):
            print(f"note: {note}", file=sys.stderr)
        print(where, file=sys.stderr)
        if args.output is not None:
            print(f"wrote {args.output}", file=sys.stderr)
        return 0
    data = fit_stream.read_whole(args.input)
    rows = _split_thicknesses(data, [table], args.input)[0]
    rho_b, rho_w = _backgrounds(data, rows, table)
    result = fitter.fit(data["I_b"][rows], data["I_w"][rows], data["I_c"][rows], rho_b, rho_w)
    _write_table_fit(args, data, rows, table, stds, result, "lut (the instrument's fit)",
                     _table_identity(table, "file"), where)
    return 0


def _run_on_device(args: argparse.Namespace) -> int:
    """The bins fitted by the instrument (Device.fit) with the table in its active slot, which is read
    (or found in the cache) first: its ℓ and reference backgrounds, and its identity for the output."""
    from trimeter.cli._instrument import open_device, settings_from
    from trimeter.device.table_cache import instrument_table

    from trimeter.inversion.table_std import TableStds

    refuse_output_onto_inputs(args.output, [args.input])
    data = fit_stream.read_whole(args.input)
    with open_device(settings_from(args)) as device:
        table, slot, _cached = instrument_table(device)
        check_declared_thickness(args.thickness, [table])
        rows = _split_thicknesses(data, [table], args.input)[0]
        rho_b, rho_w = _backgrounds(data, rows, table)
        result = device.fit(data["I_b"][rows], data["I_w"][rows], data["I_c"][rows], rho_b, rho_w,
                            thickness_mm=table.thickness_mm, table=table.to_bytes())
    source = "declared with --thickness" if args.thickness else "not declared: the table's"
    _write_table_fit(args, data, rows, table, TableStds(table), (result.alpha, result.sigma_t, result.g, result.flags),
                     "lut (on the device)", _table_identity(table, "device", slot),
                     f"thickness: {table.thickness_mm:g} mm ({source}; fitted on the device with its table "
                     f"{table.name}, slot {slot}, sha256 {table.sha256[:12]}…, CRC-32 0x{result.table_crc32:08X}; "
                     f"stds computed here from the same table)")
    return 0


def _backgrounds(data: dict[str, np.ndarray], rows: np.ndarray, table: DeviceTable) -> tuple[np.ndarray, np.ndarray]:
    """The rows' (ρ_b, ρ_w): the input's columns, else the table's reference backgrounds."""
    n = len(rows)
    rho_b = data["rho_b"][rows] if "rho_b" in data else np.full(n, table.rho_b_ref)
    rho_w = data["rho_w"][rows] if "rho_w" in data else np.full(n, table.rho_w_ref)
    return rho_b, rho_w


def _write_table_fit(args: argparse.Namespace, data: dict[str, np.ndarray], rows: np.ndarray, table: DeviceTable,
                     stds: TableStds, fitted: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], method: str,
                     identity: dict[str, Any], where: str) -> None:
    """The output of the instrument's fit (here or on the device) with the stds computed here from the
    same table: the fit's columns, advice and the thickness line on stderr."""
    from trimeter.inversion.flags import advice, describe

    thickness_std = _thickness_std(data["thickness_std_mm"], [rows], [table], args.input)[0] \
        if "thickness_std_mm" in data else 0.0
    columns = _table_fit_columns(data, rows, table, stds, fitted, thickness_std)
    flags = columns["flags"]
    notes = advice(flags, 1)
    for note in notes:  # stderr: stdout may be the CSV
        print(f"note: {note}", file=sys.stderr)
    print(where, file=sys.stderr)
    identity = {**identity, "stds": "computed on the host from this table (trimeter.inversion.table_std)"}
    _write_result(args, columns, f"{table.thickness_mm:g}", method, [table.thickness_mm], [table],
                  [describe(f) for f in flags], notes, identity)


def _table_fit_columns(data: Chunk, rows: np.ndarray, table: DeviceTable, stds: TableStds,
                       fitted: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], thickness_std_mm: float) -> Chunk:
    """The instrument's fit as the output's columns, with its stds from the table (TableStds.result): the
    rows' intensity stds where the input gives them, the sample thickness's std."""
    given = {name: data[name][rows] for name in ("I_b_std", "I_w_std", "I_c_std") if name in data}
    result = stds.result(fitted, data["I_b"][rows], data["I_w"][rows], data["I_c"][rows],
                         *_backgrounds(data, rows, table), thickness_rel_std=thickness_std_mm / table.thickness_mm,
                         **given)
    return {"wavelength_nm": data["wavelength_nm"][rows], **result.as_dict()}


def _thickness_std(column: np.ndarray, groups: list[np.ndarray], amaps: Sequence[FitSource], path: Path) -> list[float]:
    """One thickness std per map from the column: the same value on every row of that thickness."""
    out = []
    for rows, amap in zip(groups, amaps, strict=True):
        _refuse_unknown_std(column[rows], path)
        values = np.unique(column[rows][np.isfinite(column[rows])])
        if len(values) > 1:
            raise InputError(f"--input {path}: column thickness_std_mm differs between the rows of thickness "
                             f"{amap.thickness_mm:g} mm ({values[0]:g}, {values[1]:g}, …): one sample, one std")
        out.append(float(values[0]) if len(values) else 0.0)
    return out


def _json_number(v: SupportsFloat) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None
