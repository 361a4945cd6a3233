#!/usr/bin/env python3
"""Train the `mlp` inverse for an appearance map and export it to ONNX next to the map: the onnx stage
of `trimeter map build RECIPE --stages onnx` (trimeter.maps.pipeline; training in
trimeter.maps.mlp_training), for a map given by file or shipped name.

    .venv/bin/python tools/train_mlp.py maps/device-l0.4.tmap [-o maps/device-l0.4.onnx]
        [--hidden 64,64] [--activation relu] [--samples 300000] [--epochs 60] [--seed 0]

(the defaults: trimeter.maps.mlp_training.DEFAULTS; jitter and the learning-rate schedule are its defaults too)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from trimeter.maps.mlp_training import DEFAULTS, export, network_graph, train, training_set

__all__ = ["export", "network_graph", "train", "training_set", "main"]


def main(argv=None) -> int:
    from trimeter.errors import TrimeterError
    from trimeter.formats.appearance import AppearanceMap, find_map
    from trimeter.maps.pipeline import Options, make_child

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", help="map file or shipped map name")
    ap.add_argument("-o", "--output", type=Path, help="default: next to the map, <name>.onnx")
    ap.add_argument("--hidden", default=",".join(map(str, DEFAULTS["hidden"])),
                    help="hidden layer sizes, comma-separated")
    ap.add_argument("--samples", type=int, default=DEFAULTS["samples"])
    ap.add_argument("--epochs", type=int, default=DEFAULTS["epochs"])
    ap.add_argument("--seed", type=int, default=DEFAULTS["seed"])
    ap.add_argument("--activation", default=DEFAULTS["activation"], choices=("tanh", "relu"))
    args = ap.parse_args(argv)
    try:
        hidden = tuple(int(h) for h in args.hidden.split(","))
    except ValueError:
        ap.error(f"--hidden: comma-separated layer sizes, got {args.hidden!r}")
    if not hidden or min(hidden) < 1 or args.samples < 100 or args.epochs < 1:
        ap.error("--hidden sizes, --samples (≥ 100) and --epochs must be positive")
    try:
        amap = AppearanceMap.load(find_map(args.map))
        make_child("onnx", amap, Options(mlp_hidden=hidden, mlp_samples=args.samples, mlp_epochs=args.epochs,
                                         mlp_seed=args.seed, mlp_activation=args.activation), out=args.output)
    except TrimeterError as exc:
        print(f"train_mlp: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
