#!/usr/bin/env python3
"""Build the map table (the `lut` method's inverse, what the instrument stores in a map slot) for
one or more appearance maps: maps/<name>.tmap → maps/<name>.tlut (format: trimeter.inversion.table).

    .venv/bin/python tools/build_table.py maps/device-l0.4.tmap [more maps…] [--n-xy N] [-o OUT]

Prints each table's size, CRC-32 and the source map's checksum. Refuses a map whose table cannot fit
the 128 KiB slot.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    from trimeter.errors import TrimeterError
    from trimeter.inversion.table import MapTable, build_from_map, describe_table, table_path_for
    from trimeter.maps.appearance import AppearanceMap, find_map

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("maps", nargs="+", help="map files or shipped map names")
    ap.add_argument("--n-xy", type=int, help="inverse grid side (default: the largest that fits the slot)")
    ap.add_argument("-o", "--output", type=Path, help="output file (only with one map)")
    args = ap.parse_args(argv)
    if args.output and len(args.maps) > 1:
        ap.error("-o needs exactly one map")
    try:
        for spec in args.maps:
            amap = AppearanceMap.load(find_map(spec))
            t0 = time.perf_counter()
            table = build_from_map(amap, n_xy=args.n_xy)
            out = table.save(args.output or table_path_for(amap.path))
            MapTable.load(out)  # read back: the file on disk must decode
            info = describe_table(out)
            print(f"{out}: {info['size_bytes']} bytes (slot {info['slot_capacity_bytes']}), crc32 {info['crc32']}, "
                  f"inverse {info['inverse_grid']['x']}×{info['inverse_grid']['y']} per σt node, "
                  f"map {amap.checksum[:12]}…, built in {time.perf_counter() - t0:.1f} s")
    except TrimeterError as exc:
        print(f"build_table: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
