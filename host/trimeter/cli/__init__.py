"""The `trimeter` command line.

Each sub-command group lives in its own module `trimeter/cli/cmd_<name>.py` exposing
`register(subparsers)`; the parser is assembled from whatever modules exist, so command groups are
added without touching this file. A handler returns an exit code (or None for 0).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import signal
import sys

from trimeter.version import __version__
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
    try:
        rc = int(_dispatch(argv) or 0)
    except TrimeterError as exc:
        rc = _report(f"trimeter: error: {exc}", 2)
    except KeyboardInterrupt:
        rc = _report("trimeter: interrupted", 130)
    except BrokenPipeError:  # the reader went away (`trimeter … | head -1`): stop quietly, as Unix tools do
        _discard_stdout()
        return 128 + signal.SIGPIPE
    except OSError as exc:  # e.g. the output's disk is full (a named file says which)
        rc = _report(f"trimeter: error: {exc.filename + ': ' if exc.filename else ''}{exc.strerror or exc}", 2)
    try:
        if sys.stdout is not None:
            sys.stdout.flush()  # a closed pipe or a full disk shows here, not as a traceback at exit
    except BrokenPipeError:
        _discard_stdout()
        return 128 + signal.SIGPIPE
    except OSError as exc:
        _discard_stdout()
        return _report(f"trimeter: error: cannot write to standard output ({exc.strerror or exc})", 2)
    return rc


def _dispatch(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return args.func(args)


def _discard_stdout() -> None:
    """Point standard output at /dev/null, so the interpreter's own flush at exit does not fail again."""
    if sys.stdout is None:
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # ValueError: stdout replaced by an object without a descriptor
        pass


def _report(line: str, rc: int) -> int:
    """Print `line` on stderr; return the exit code `rc`."""
    with contextlib.suppress(OSError, AttributeError):  # no stderr either: the exit code says it
        print(line, file=sys.stderr, flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
