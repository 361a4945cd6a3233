"""Command groups whose sub-commands are contributed by several modules.

`trimeter map …` collects `register(map_subparsers)` from every module `trimeter/cli/map_*.py`
(appearance maps: build/list/info/query; device map tables: flash/verify/…), and `trimeter bench …`
from every module in `trimeter/bench/` that has a `register(bench_subparsers)`. Each part of the
code base adds its sub-commands in its own file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil


def register_group(subparsers: argparse._SubParsersAction, name: str, help_text: str, package: str,
                   prefix: str = "") -> None:
    parser = subparsers.add_parser(name, help=help_text, description=help_text)
    group = parser.add_subparsers(dest=f"{name}_command", metavar="SUBCOMMAND")
    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith(prefix) and not info.name.startswith("_"):
            module = importlib.import_module(f"{package}.{info.name}")
            if hasattr(module, "register"):
                module.register(group)
