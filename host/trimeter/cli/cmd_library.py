"""`trimeter library`: named materials from repeated measurements, in an SQLite file beside the history.

  trimeter library add "cyan batch 3" RESULT... [--tag ink] [--notes TEXT]   # combine measurements
  trimeter library list | show NAME [--json] | remove NAME
  trimeter library tag NAME [--add T] [--remove T] [--notes TEXT]
  trimeter library export NAME -o DIR [--to trimeter|mitsuba|pbrt|blender|rgb]
  trimeter library import DIR [--as NAME] [--replace]
  trimeter library mixtures --twin | --component NAME=SOURCE … --mixture NAME:F+NAME:F=RESULT …   # Sec. 5.2

Members are combined by inverse variance, with the spread between repeats and a flag where they
disagree beyond their stds; members measured at different thicknesses are re-fitted jointly
(trimeter.library.combine). The export format (`--to trimeter`, the default) is documented in
docs/library.md with its JSON Schema; the renderer formats are `trimeter export`'s.
"""

from __future__ import annotations

import argparse
import json

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from trimeter.library.store import Library, LibraryMaterial

FORMATS = ("trimeter", "mitsuba", "pbrt", "blender", "rgb")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("library", help="named materials from repeated measurements; the mixture check",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--db", help="the library file (default: library.sqlite in the data directory)")
    sub = p.add_subparsers(dest="library_command", metavar="ACTION", required=True)
    a = sub.add_parser("add", help="combine results directories into a named material")
    a.add_argument("name")
    a.add_argument("results", nargs="+", help="results directories (repeats; one or two thicknesses)")
    a.add_argument("--tag", action="append", default=[], help="a tag (repeatable)")
    a.add_argument("--notes", default="")
    a.add_argument("--no-joint", action="store_true", help="members at different thicknesses: combine their "
                                                           "parameters instead of re-fitting their reflectances")
    a.add_argument("--replace", action="store_true", help="replace a material of that name")
    a.set_defaults(func=_add)
    sub.add_parser("list", help="the materials").set_defaults(func=_list)
    s = sub.add_parser("show", help="one material: members, combination, spectra summary")
    s.add_argument("name")
    s.add_argument("--json", action="store_true", help="the whole material as JSON")
    s.set_defaults(func=_show)
    r = sub.add_parser("remove", help="remove a material (its results directories stay)")
    r.add_argument("name")
    r.set_defaults(func=_remove)
    t = sub.add_parser("tag", help="change a material's tags or notes")
    t.add_argument("name")
    t.add_argument("--add", action="append", default=[])
    t.add_argument("--remove", action="append", default=[])
    t.add_argument("--notes")
    t.set_defaults(func=_tag)
    e = sub.add_parser("export", help="write a material in the open format or for a renderer")
    e.add_argument("name")
    e.add_argument("-o", "--output", required=True, help="output directory (must not exist for --to trimeter)")
    e.add_argument("--to", choices=FORMATS, default="trimeter")
    e.set_defaults(func=_export)
    i = sub.add_parser("import", help="add a material exported by `library export`")
    i.add_argument("path")
    i.add_argument("--as", dest="as_name", help="store it under another name")
    i.add_argument("--replace", action="store_true")
    i.set_defaults(func=_import)
    from trimeter.library.mixtures import register_command

    register_command(sub)


def _library(args: argparse.Namespace) -> Library:
    from trimeter.library.store import Library

    return Library(args.db)


def _add(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        m = lib.add(args.name, args.results, notes=args.notes, tags=args.tag, joint=not args.no_joint,
                    replace=args.replace)
        _print_summary(m)
    return 0


def _print_summary(m: LibraryMaterial) -> None:
    doc = m.document
    c = doc.columns
    disagree = int(np.count_nonzero(c["flags"].astype(int) & 1))
    print(f"{doc.name}: {len(doc.members)} member(s), {doc.combination['method']} over "
          f"{'+'.join(f'{t:g}' for t in doc.combination['thicknesses_mm'])} mm, {len(c['wavelength_nm'])} bins "
          f"{c['wavelength_nm'][0]:.0f}-{c['wavelength_nm'][-1]:.0f} nm; repeats disagree beyond their stds in "
          f"{disagree} bin(s)")
    for p in ("alpha", "sigma_t", "g"):
        print(f"  {p:8s} median {np.nanmedian(c[p]):.4g}   std {np.nanmedian(c[p + '_std']):.3g}   spread between "
              f"repeats {np.nanmedian(c[p + '_spread']) if np.isfinite(c[p + '_spread']).any() else float('nan'):.3g}")


def _list(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        rows = lib.summaries()
    if not rows:
        print(f"no materials in {lib.db_path}")
    for r in rows:
        print(f"{r['name']:24s} {r['members']:3d} member(s)  {r['combination']:16s} "
              f"{'+'.join(f'{t:g}' for t in r['thicknesses_mm'])} mm  {r['origin']:8s} "
              f"{','.join(r['tags'])}")
    return 0


def _show(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        m = lib.get(args.name)
        missing = m.missing_members()
    if args.json:
        print(json.dumps({**m.document.to_json(), "origin": m.origin, "member_problems": missing}))
        return 0
    _print_summary(m)
    print(f"  origin {m.origin}; created {m.document.created_utc}; tags {', '.join(m.document.tags) or '-'}")
    if m.document.notes:
        print(f"  notes: {m.document.notes}")
    for member in m.document.members:
        print(f"  member {member['measurement']}  {'+'.join(f'{t:g}' for t in member['thicknesses_mm'])} mm  "
              f"{member['method']}  {', '.join(member['maps'])}")
    for problem in missing:
        print(f"  warning: member {problem}")
    return 0


def _remove(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        lib.remove(args.name)
    print(f"removed {args.name} (its results directories are untouched)")
    return 0


def _tag(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        m = lib.annotate(args.name, notes=args.notes, add_tags=args.add, remove_tags=args.remove)
    print(f"{m.name}: tags {', '.join(m.document.tags) or '-'}")
    return 0


def _export(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        if args.to == "trimeter":
            out = lib.export(args.name, args.output)
            print(f"{args.name}: material.json + spectra.csv in {out}")
            return 0
        m = lib.get(args.name)
        provenance = m.export(args.to, args.output)
    print(f"{args.to}: {', '.join(provenance['files'])} + provenance.json in {args.output}")
    return 0


def _import(args: argparse.Namespace) -> int:
    with _library(args) as lib:
        m = lib.import_(args.path, name=args.as_name, replace=args.replace)
    print(f"imported {m.name} ({len(m.document.members)} member(s), {len(m.document.columns['wavelength_nm'])} bins)")
    return 0
