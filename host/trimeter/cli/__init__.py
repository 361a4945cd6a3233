"""The `trimeter` command line.

Each sub-command group lives in its own module `trimeter/cli/cmd_<name>.py` exposing
`register(subparsers)`; the parser is assembled from whatever modules exist, so command groups are
added without touching this file. A handler returns an exit code (or None for 0).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from trimeter import __version__
from trimeter.errors import TrimeterError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="trimeter",
        description="Measure spectral albedo, extinction and HG anisotropy of translucent samples.",
    )
    parser.add_argument("--version", action="version", version=f"trimeter {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("cmd_"):
            importlib.import_module(f"{__name__}.{info.name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        rc = args.func(args)
    except TrimeterError as exc:
        print(f"trimeter: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("trimeter: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
