"""Is the bounce series' std-error (ColumnTally.bounce_series) the spread it claims? Traces one device column
per seed with the series and compares the spread of its values over the seeds with the mean std-error it
reports, per α (goal: about 1; with S seeds the spread itself is uncertain by about 1/√(2(S − 1))).

    .venv/bin/python tools/series_stderr_check.py --seeds 48 --paths 262144 --g 0.5 --rho 0.9

The std-error is each path's own spread: the series' geometric continuation past its last traced order, and
the noise of that continuation's ratio, are left out of it. This measures whether that matters near α = 1,
where the continuation carries most of the light.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from trimeter.forward.transport import Stack
from trimeter.forward.transport.tally import ColumnTally
from trimeter.forward.transport.trace import trace
from trimeter.geometry import load_geometry

K_MAX = 60


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=48)
    p.add_argument("--paths", type=int, default=1 << 18, help="detector paths per trace")
    p.add_argument("--sigma-t", type=float, nargs="+", default=[3.0, 20.0], help="columns' σt [1/mm]")
    p.add_argument("--g", type=float, default=0.5)
    p.add_argument("--rho", type=float, default=0.9, help="the background the series is summed at")
    p.add_argument("--thickness-mm", type=float, default=0.4)
    p.add_argument("--orders", type=int, default=5, help="background orders traced")
    args = p.parse_args(argv)
    if args.seeds < 3 or args.paths < 1024:
        p.error("needs at least 3 seeds and 1024 paths")
    device = Stack.from_recipe("device", load_geometry("device"), 1.5, args.thickness_mm)
    alpha = np.array([0.9, 0.99, 0.999])
    print(f"device ℓ {args.thickness_mm:g} mm, g {args.g:g}, ρ {args.rho:g}, {args.orders} orders, {args.seeds} "
          f"seeds × {args.paths} paths; the spread's own uncertainty ±{1 / np.sqrt(2 * (args.seeds - 1)):.0%}")
    for sigma_t in args.sigma_t:
        runs = [ColumnTally(trace(device, sigma_t, args.g, args.paths, seed, K_MAX, background_orders=args.orders),
                            None).bounce_series(alpha, args.rho) for seed in range(args.seeds)]
        values, errors = (np.array(x) for x in zip(*runs, strict=True))
        ratio = values.std(axis=0, ddof=1) / errors.mean(axis=0)
        print(f"  σt {sigma_t:g}/mm: spread over the seeds / mean std-error at α "
              + ", ".join(f"{a:g}: {r:.2f}" for a, r in zip(alpha, ratio, strict=True)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
