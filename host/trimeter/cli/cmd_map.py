"""`trimeter map …`: appearance maps (build, list, info, query) and device map tables (flash, verify)."""

import argparse

from trimeter.cli._groups import register_group


def register(subparsers: argparse._SubParsersAction) -> None:
    register_group(subparsers, "map", "appearance maps and the device's map tables", "trimeter.cli", prefix="map_")
