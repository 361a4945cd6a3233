"""`trimeter bench gpu-check` (`make gpu-check`): the map tracer on a GPU against the CPU, for a lent GPU.

For every shipped recipe (maps/recipes/*.toml), a few (σt, g) columns — the first, the middle and the
last of the grid, by default — are traced with the same seeds and path count on the CUDA backend and
on the LLVM one (the backend the shipped maps were traced on). Per column: both backends' seconds (after
one small warm-up column per recipe and backend, so kernel compilation is not counted) and the z-scores
of I(ρ) = A + B·q at both reference backgrounds and every α of the grid,
z = (I_cuda − I_llvm) / √(se_cuda² + se_llvm²). The same seeds give the same paths on either backend up
to their floating-point differences, so the z-scores sit near 0 unless a backend is wrong; the check
is the tracer check's rule on their distribution (trimeter.forward.transport.agreement.z_summary).
Then the inversion's tests (pytest tests/inversion), where the checkout has them.

Without a CUDA device it prints one `SKIPPED: …` line saying why and exits 0. `--against llvm` traces the
"GPU" half on LLVM as well, with other seeds (the same ones would give the same bits): the whole check,
its output and its verdict on two independent traces, on a machine without a GPU.

Output (stable, one record per line, so a run can be pasted into the validation page):
    gpu-check v1 | <backend> vs llvm | <paths> paths per column | trimeter <v> | drjit <v> | <device>
    column | <recipe> | j <j> | k <k> | sigma_t <σt> | g <g> | <backend> <s> s | llvm <s> s | speed-up <x> | max |z| <z>
    agreement | <backend> vs llvm | count <n> | mean z <m> | p95 |z| <p> | max |z| <z> | PASS or FAIL
    inversion tests | <command> | PASS or FAIL (exit <code>) or NOT RUN (<why>)
    RESULT | PASS or FAIL
Exit status 0 when everything passes (or SKIPPED), 1 otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from trimeter.errors import InputError

FORMAT_VERSION = 1
DEFAULT_PATHS = 1 << 22
WARM_UP_PATHS = 4096


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("gpu-check", help="the map tracer's CUDA backend against LLVM on a few columns of "
                                                "each shipped recipe, then the inversion's tests (skips without a GPU)")
    p.add_argument("--paths", type=int, default=DEFAULT_PATHS,
                   help=f"detector paths per column on each backend (default {DEFAULT_PATHS})")
    p.add_argument("--columns", type=int, default=3,
                   help="columns per recipe, spread from the grid's first (σt, g) to its last (default 3)")
    p.add_argument("--recipes", nargs="*", default=None, metavar="TOML",
                   help="recipes (default: every maps/recipes/*.toml)")
    p.add_argument("--against", choices=("cuda", "llvm"), default="cuda",
                   help="the backend checked against LLVM (llvm: the whole check without a GPU)")
    p.add_argument("--tests", default=None, metavar="DIR",
                   help="the inversion's tests (default: tests/inversion of this checkout); 'none' skips them")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from trimeter.version import __version__
    from trimeter.maps.recipe import load_recipe
    from trimeter.paths import MAPS_DIR, REPO_ROOT

    if not WARM_UP_PATHS <= args.paths <= 1 << 28:
        raise InputError(f"--paths must be {WARM_UP_PATHS}…{1 << 28}, got {args.paths}")
    if not 1 <= args.columns <= 64:
        raise InputError(f"--columns must be 1…64, got {args.columns}")
    recipe_paths = ([Path(p) for p in args.recipes] if args.recipes is not None
                    else sorted((MAPS_DIR / "recipes").glob("*.toml")))
    if not recipe_paths:
        raise InputError("no recipes to check (maps/recipes/*.toml is empty and --recipes names none)")
    recipes = [load_recipe(p) for p in recipe_paths]   # bad recipes are refused before any work

    missing = missing_backend(args.against)
    if missing:
        print(f"SKIPPED: gpu-check needs a CUDA device: {missing}")
        return 0
    dr_version = _drjit_version()
    print(f"gpu-check v{FORMAT_VERSION} | {args.against} vs llvm | {args.paths} paths per column | "
          f"trimeter {__version__} | drjit {dr_version} | {gpu_name() if args.against == 'cuda' else 'no GPU'}")
    z_all = []
    for recipe in recipes:
        for j, k in spread_columns(recipe, args.columns):
            row = compare_column(recipe, j, k, args.paths, args.against)
            z_all.append(row["z"])
            print(f"column | {recipe.name} | j {j} | k {k} | sigma_t {recipe.sigma_t[j]:.4g} | g {recipe.g[k]:.4g} | "
                  f"{args.against} {row['seconds'][0]:.3f} s | llvm {row['seconds'][1]:.3f} s | "
                  f"speed-up {row['seconds'][1] / max(row['seconds'][0], 1e-9):.1f} | "
                  f"max |z| {np.abs(row['z']).max():.3f}")
    summary = agreement(np.concatenate(z_all))
    print(f"agreement | {args.against} vs llvm | count {summary['count']} | mean z {summary['mean']:+.3f} | "
          f"p95 |z| {summary['p95_abs']:.3f} | max |z| {summary['max_abs']:.3f} | "
          f"{'PASS' if summary['ok'] else 'FAIL'}")
    tests_ok = run_inversion_tests(args.tests if args.tests is not None else str(REPO_ROOT / "tests" / "inversion"))
    ok = summary["ok"] and tests_ok
    print(f"RESULT | {'PASS' if ok else 'FAIL'}")
    return 0 if ok else 1


def missing_backend(backend: str) -> str | None:
    """Why `backend` cannot run here (None: it can). Dr.Jit cannot record a CUDA kernel without the
    driver: its CUDA arrays need jit_init(CUDA), which needs libcuda and a device."""
    if backend == "llvm":
        return None
    try:
        import drjit as dr
    except ImportError as exc:
        return f"Dr.Jit is not installed ({exc})"
    if not dr.has_backend(dr.JitBackend.CUDA):
        return "Dr.Jit finds no CUDA driver and device on this machine"
    return None


def spread_columns(recipe, count: int) -> list[tuple[int, int]]:
    """`count` (σt, g) columns from the grid's first to its last, evenly along both axes (distinct)."""
    _, n_sigma, n_g = recipe.shape
    steps = np.linspace(0.0, 1.0, count) if count > 1 else np.array([0.5])
    picks = [(int(round(s * (n_sigma - 1))), int(round(s * (n_g - 1)))) for s in steps]
    return list(dict.fromkeys(picks))


def compare_column(recipe, j: int, k: int, paths: int, against: str) -> dict:
    """One column traced on `against` and on LLVM with the same seeds: seconds per backend and the
    z-scores of I(ρ) at both reference backgrounds over α."""
    from trimeter.maps import builder
    from trimeter.forward.transport import Stack
    from trimeter.forward.transport import trace_column as trace_pair

    fixed = dataclasses.replace(recipe, sampling=dataclasses.replace(recipe.sampling, min_paths=paths, max_paths=paths))
    warm = dataclasses.replace(recipe, sampling=dataclasses.replace(recipe.sampling, min_paths=WARM_UP_PATHS,
                                                                    max_paths=WARM_UP_PATHS))
    stack = Stack.from_recipe(recipe.geometry, recipe.geometry_params, recipe.n, recipe.thickness_mm)
    # LLVM against itself with the same seeds would be the same bits: the checked half gets other seeds
    checked_seed = recipe.seed if against == "cuda" else recipe.seed + 1
    columns, seconds = [], []
    for backend, seed in ((against, checked_seed), ("llvm", recipe.seed)):
        tracer = functools.partial(trace_pair, backend=backend)
        builder.trace_column(warm, stack, j, k, tracer)          # compiles this stack's kernels
        t0 = time.perf_counter()
        columns.append(builder.trace_column(dataclasses.replace(fixed, seed=seed), stack, j, k, tracer))
        seconds.append(time.perf_counter() - t0)
    return {"seconds": seconds, "z": column_z(recipe, columns[0], columns[1])}


def column_z(recipe, a, b) -> np.ndarray:
    """z-scores of I(ρ) = A + B·ρ/(1 − Cρ) between two traces of one column, both reference ρ, every α."""
    z = []
    for rho, se_a, se_b in ((recipe.reference_rho_b, a.std_b, b.std_b), (recipe.reference_rho_w, a.std_w, b.std_w)):
        value_a = a.A + a.B * rho / (1 - a.C * rho)
        value_b = b.A + b.B * rho / (1 - b.C * rho)
        # at α = 0 both std-errors can be 0 (no scattering: every path alike) and the values equal
        se = np.sqrt(se_a**2 + se_b**2)
        z.append(np.divide(value_a - value_b, se, out=np.zeros_like(se), where=se > 0))
    return np.concatenate(z)


def agreement(z: np.ndarray) -> dict:
    from trimeter.forward.transport.agreement import z_summary

    return z_summary(z)


def run_inversion_tests(tests: str) -> bool:
    """pytest over the inversion's tests; prints one line. Absent tests (an installed package, not a
    checkout) are NOT RUN and fail the check: the check is incomplete without them."""
    if tests == "none":
        print("inversion tests | NOT RUN (--tests none)")
        return True
    if not Path(tests).is_dir():
        print(f"inversion tests | NOT RUN ({tests} is not a directory: run from a checkout)")
        return False
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", tests]
    done = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    tail = done.stdout.strip().splitlines()[-1:] or [""]
    print(f"inversion tests | pytest -q {tests} | {'PASS' if done.returncode == 0 else 'FAIL'} "
          f"(exit {done.returncode}) | {tail[0]}")
    if done.returncode != 0:
        print(done.stdout)
    return done.returncode == 0


def _drjit_version() -> str:
    from importlib import metadata

    try:
        return metadata.version("drjit")
    except metadata.PackageNotFoundError:
        return "unknown"


def gpu_name() -> str:
    """The GPU's name from nvidia-smi where it is on the PATH (Dr.Jit does not report it)."""
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return "GPU (nvidia-smi not found)"
    try:
        out = subprocess.run([smi, "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True,
                             timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return "GPU (nvidia-smi failed)"
    return out.stdout.strip().splitlines()[0] if out.returncode == 0 and out.stdout.strip() else "GPU (unnamed)"
