"""Benchmarks. Each module with `register(bench_subparsers)` adds a `trimeter bench <name>` command."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def write_figures(report: Any, path: Path) -> None:
    """Write a bench's figures as JSON (atomically, its directory made) and say where."""
    from trimeter.atomic import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps(report, indent=1, default=float) + "\n")
    print(f"\nall figures: {path}")
