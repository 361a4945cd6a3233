#!/usr/bin/env python3
"""Build the map table (the `lut` method's inverse, what the instrument stores in a map slot) for
one or more appearance maps: maps/<name>.tmap → maps/<name>.tlut. The tlut stage of
`trimeter map build RECIPE --stages tlut` (trimeter.maps.pipeline), for maps given by file or name.

    .venv/bin/python tools/build_table.py maps/device-l0.4.tmap [more maps…] [--n-xy N] [-o OUT]

Prints each table's size and CRC-32. Refuses a map whose table cannot fit the 128 KiB slot.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    from trimeter.errors import TrimeterError
    from trimeter.formats.appearance import AppearanceMap, find_map
    from trimeter.maps.pipeline import Options, make_child

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("maps", nargs="+", help="map files or shipped map names")
    ap.add_argument("--n-xy", type=int, help="inverse grid side (default: the largest that fits the slot)")
    ap.add_argument("-o", "--output", type=Path, help="output file (only with one map)")
    args = ap.parse_args(argv)
    if args.output and len(args.maps) > 1:
        ap.error("-o needs exactly one map")
    try:
        for spec in args.maps:
            make_child("tlut", AppearanceMap.load(find_map(spec)), Options(table_n_xy=args.n_xy), out=args.output)
    except TrimeterError as exc:
        print(f"build_table: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
