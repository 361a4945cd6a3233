"""`trimeter bench …`: benchmarks that print figures and ratios against a baseline run alongside."""

import argparse

from trimeter.cli._groups import register_group


def register(subparsers: argparse._SubParsersAction) -> None:
    register_group(subparsers, "bench", "benchmarks (speed and accuracy against a same-run baseline)", "trimeter.bench")
