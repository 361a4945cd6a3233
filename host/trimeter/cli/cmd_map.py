"""`trimeter map …`: appearance maps (build, list, info, query) and device map tables (flash, verify)."""

from trimeter.cli._groups import register_group


def register(subparsers) -> None:
    register_group(subparsers, "map", "appearance maps and the device's map tables", "trimeter.cli", prefix="map_")
