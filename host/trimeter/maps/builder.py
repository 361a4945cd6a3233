"""The map builder: a recipe → an AppearanceMap, one (k, m)-tally trace per (σt, g) column.

- Deterministic: the random stream of column (j, k) batch b is seeded from (recipe seed, j, k, b) only,
  so the same recipe gives the same map whatever the order, interruptions or thread count (the
  shipped device maps' columns re-trace to within 1.5e-8, not bit for bit: see maps/README.md).
- Adaptive: a column is traced with `min_paths`, then topped up (at most three times) to reach
  `target_stderr` (the max over α of the std-error of I at both reference backgrounds) and, if the
  recipe sets it, `target_alpha_stderr` (the max over α ∈ [0.02, 0.99] of α's std-error, g held),
  capped at `max_paths`; the std-error reached is stored per point either way.
- Checkpointed: each finished column is written (atomically, plain .npz, no pickle) into a checkpoint
  directory next to the output, with the recipe's fingerprint; `resume=True` reloads finished columns
  instead of re-tracing them. The final file is written atomically by AppearanceMap.save.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
import zipfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Callable

import numpy as np

from trimeter.atomic import atomic_output, atomic_write
from trimeter.errors import InputError, MapFileError
from trimeter.forward.collimated import MEASURABLE_IC, collimated_transmittance
from trimeter.geometry import cover_slide_n
from trimeter.maps.appearance import AppearanceMap, background_response
from trimeter.maps.recipe import Recipe
from trimeter.maps.tracer import ColumnTally, Stack, k_max_for
from trimeter.maps.tracer import trace_column as trace_pair

BUILDER = "trimeter.maps.tracer: (k, m)-tally path tracer (detector + background paths), Dr.Jit LLVM symbolic loop"
_COLUMN_FIELDS = ("A", "B", "C", "std_b", "std_w")
_BATCH_QUANTUM = 4096


@dataclass
class Column:
    """One finished (σt_j, g_k) column: arrays over α plus its sampling record."""
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    std_b: np.ndarray
    std_w: np.ndarray
    n_paths: int
    truncated: int
    truncation_bound: float
    seconds: float
    path_events: int


def column_seed(seed: int, j: int, k: int, batch: int) -> int:
    return int(np.random.SeedSequence([seed, j, k, batch]).generate_state(1, np.uint64)[0] >> np.uint64(1))


def trace_column(recipe: Recipe, stack: Stack, j: int, k: int, tracer: Callable = trace_pair) -> Column:
    s = recipe.sampling
    k_max = k_max_for(float(recipe.alpha[-1]), s.truncation)
    sigma_t, g = float(recipe.sigma_t[j]), float(recipe.g[k])
    tally: ColumnTally | None = None
    batch, n_next = 0, s.min_paths
    while n_next > 0:
        part = tracer(stack, sigma_t, g, n_next, column_seed(recipe.seed, j, k, batch), k_max)
        if tally is None:
            tally = part
        else:
            tally += part
        batch += 1
        shortfall = _shortfall(tally, recipe, sigma_t)  # (std-error reached / target) for the worse criterion
        if shortfall <= 1.0 or tally.n_paths >= s.max_paths or batch >= 4:
            break
        wanted = paths_to_reach(tally.n_paths, shortfall, s.max_paths)
        n_next = math.ceil((wanted - tally.n_paths) / _BATCH_QUANTUM) * _BATCH_QUANTUM
    A, B, C = tally.abc(recipe.alpha)
    return Column(A=A, B=B, C=C, std_b=tally.stderr(recipe.alpha, recipe.reference_rho_b),
                  std_w=tally.stderr(recipe.alpha, recipe.reference_rho_w), n_paths=tally.n_paths,
                  truncated=tally.truncated, truncation_bound=tally.truncation_bound(float(recipe.alpha[-1])),
                  seconds=tally.seconds, path_events=tally.path_events)


def paths_to_reach(n_paths: int, shortfall: float, cap: int) -> int:
    """How many paths in all a column needs whose std-error is `shortfall` × its target after
    n_paths: std-error ∝ 1/√N, so n_paths·shortfall² (+10 %), within the cap."""
    return min(int(cap), math.ceil(n_paths * shortfall ** 2 * 1.1))


def _shortfall(tally: ColumnTally, recipe: Recipe, sigma_t: float) -> float:
    s = recipe.sampling
    worst = max(tally.stderr(recipe.alpha, recipe.reference_rho_b).max(),
                tally.stderr(recipe.alpha, recipe.reference_rho_w).max())
    ratio = float(worst / s.target_stderr)
    if s.target_alpha_stderr is not None and _measurable(recipe, sigma_t):
        ratio = max(ratio, worst_alpha_stderr(tally, recipe.alpha, recipe.reference_rho_b,
                                              recipe.reference_rho_w) / s.target_alpha_stderr)
    return ratio


def _measurable(recipe: Recipe, sigma_t: float) -> bool:
    """Whether the instrument sees this σt at all (I_c above its floor): denser columns are only
    reached by the table's edges, so α precision there buys nothing."""
    cover = cover_slide_n(recipe.geometry_params)
    return float(collimated_transmittance(sigma_t, recipe.thickness_mm, recipe.n, cover)) >= MEASURABLE_IC


def worst_alpha_stderr(tally: ColumnTally, alpha, rho_b: float, rho_w: float) -> float:
    """The column's largest α std-error over the albedos the instrument resolves (α ∈ [0.02, 0.99]:
    below, α is 0 within any noise; above, the nodes crowd towards 0.999 where ∂I/∂α is steepest)."""
    alpha = np.asarray(alpha, dtype=np.float64)
    scored = alpha[(alpha >= 0.02) & (alpha <= 0.99)]
    return float(np.max(tally.alpha_stderr(scored if len(scored) else alpha, rho_b, rho_w)))


def recipe_fingerprint(recipe: Recipe | dict) -> str:
    """SHA-256 of the recipe (a Recipe, or the dict a map stores) with every float rounded to 1e-10.
    Why rounded: the grid axes are generated (np.geomspace), and numpy releases differ in their
    last bit (numpy 2.4 vs the release the shipped maps were built with), which must not make a
    current map look stale. (Absolute, not significant digits: 0.0 and its 1-ulp neighbour 5e-324
    must agree too.)"""
    data = recipe.to_dict() if isinstance(recipe, Recipe) else recipe
    return hashlib.sha256(json.dumps(_canonical(data), sort_keys=True).encode()).hexdigest()


def _canonical(value):
    if isinstance(value, float):
        return round(value, 10) + 0.0  # + 0.0: -0.0 → 0.0
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    return value


class Checkpoint:
    """A directory of finished columns for one recipe (refuses a directory made for another)."""

    def __init__(self, directory: Path, recipe: Recipe, resume: bool):
        self.dir = Path(directory)
        self.recipe = recipe
        stamp = self.dir / "recipe.json"
        fingerprint = recipe_fingerprint(recipe)
        if self.dir.exists() and any(self.dir.glob("col_*.npz")):
            if not resume:
                raise InputError(f"checkpoint {self.dir} holds a previous build: pass --resume to continue it, "
                                 "or delete the directory to start over")
            try:
                stored = json.loads(stamp.read_text())["fingerprint"]
            except (OSError, ValueError, KeyError):
                raise MapFileError(f"checkpoint {self.dir}: recipe.json is missing or unreadable") from None
            if stored != fingerprint:
                raise InputError(f"checkpoint {self.dir} was made for a different recipe; delete it to start over")
        self.dir.mkdir(parents=True, exist_ok=True)
        atomic_write(stamp, json.dumps({"fingerprint": fingerprint, "recipe": recipe.to_dict()}).encode())

    def path(self, j: int, k: int) -> Path:
        return self.dir / f"col_{j:03d}_{k:03d}.npz"

    def load(self, j: int, k: int) -> Column | None:
        p = self.path(j, k)
        if not p.exists():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                col = Column(**{f: np.array(z[f]) for f in _COLUMN_FIELDS},
                             n_paths=int(z["n_paths"]), truncated=int(z["truncated"]),
                             truncation_bound=float(z["truncation_bound"]), seconds=float(z["seconds"]),
                             path_events=int(z["path_events"]))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None            # a damaged column is simply traced again (deterministically)
        if any(getattr(col, f).shape != (len(self.recipe.alpha),) for f in _COLUMN_FIELDS):
            return None
        return col

    def save(self, j: int, k: int, col: Column) -> None:
        with atomic_output(self.path(j, k), make_parents=False) as f:
            np.savez(f, **{name: getattr(col, name) for name in _COLUMN_FIELDS}, n_paths=col.n_paths,
                     truncated=col.truncated, truncation_bound=col.truncation_bound, seconds=col.seconds,
                     path_events=col.path_events)

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def default_checkpoint_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.checkpoint"


def build_map(recipe: Recipe, out: str | Path, *, checkpoint_dir: str | Path | None = None, resume: bool = False,
              progress: bool = True, keep_checkpoint: bool = False, tracer: Callable = trace_pair,
              on_column: Callable[[int, int], None] | None = None) -> AppearanceMap:
    """Build the map for `recipe` into `out` (atomically). `on_column(j, k)` is called after each
    column is traced (not for columns reloaded from the checkpoint) — used by tests to interrupt."""
    out = Path(out)
    ckpt = Checkpoint(Path(checkpoint_dir) if checkpoint_dir else default_checkpoint_dir(out), recipe, resume)
    stack = Stack.from_recipe(recipe.geometry, recipe.geometry_params, recipe.n, recipe.thickness_mm)
    na, ns, ng = recipe.shape
    arrays = {f: np.zeros(recipe.shape) for f in _COLUMN_FIELDS}
    n_paths = np.zeros((ns, ng), dtype=np.int64)
    trunc_bound = np.zeros((ns, ng))
    trace_seconds = np.zeros((ns, ng))
    jobs = [(j, k) for k in range(ng) for j in range(ns)]
    reused = traced = 0
    start = time.perf_counter()
    with _progress(progress, len(jobs), recipe.name) as advance:
        for j, k in jobs:
            col = ckpt.load(j, k) if resume else None
            if col is None:
                col = trace_column(recipe, stack, j, k, tracer)
                ckpt.save(j, k, col)
                traced += 1
                if on_column:
                    on_column(j, k)
            else:
                reused += 1
            for f in _COLUMN_FIELDS:
                arrays[f][:, j, k] = getattr(col, f)
            n_paths[j, k], trunc_bound[j, k], trace_seconds[j, k] = col.n_paths, col.truncation_bound, col.seconds
            advance()
    wall = time.perf_counter() - start
    provenance = {
        "builder": BUILDER,
        "drjit_version": _version("drjit"), "mitsuba_version": _version("mitsuba"),
        "trace_seconds": round(float(trace_seconds.sum()), 3),
        "wall_seconds_last_run": round(wall, 3), "columns_traced_last_run": traced, "columns_resumed": reused,
        "paths_per_column": {"min": int(n_paths.min()), "median": int(np.median(n_paths)), "max": int(n_paths.max()),
                             "total": int(n_paths.sum())},
        "truncation": {"k_max": k_max_for(float(recipe.alpha[-1]), recipe.sampling.truncation),
                       "max_error_bound": float(trunc_bound.max())},
        "recipe_fingerprint": recipe_fingerprint(recipe),
        "built_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    amap = AppearanceMap(recipe=recipe.to_dict(), alpha=recipe.alpha, sigma_t=recipe.sigma_t, g=recipe.g,
                         provenance=provenance, **arrays)
    amap.save(out)
    if not keep_checkpoint:
        ckpt.remove()
    return AppearanceMap.load(out)


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


class _progress:
    """A rich progress bar over columns (or nothing, for tests and pipes)."""

    def __init__(self, enabled: bool, total: int, label: str):
        self.enabled, self.total, self.label = enabled, total, label
        self._bar = None

    def __enter__(self):
        if not self.enabled:
            return lambda: None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

        self._bar = Progress("[bold]{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                             TimeRemainingColumn())
        self._bar.__enter__()
        task = self._bar.add_task(f"{self.label} (σt, g) columns", total=self.total)
        return lambda: self._bar.advance(task)

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False


def validation_report(amap: AppearanceMap) -> dict:
    """Physical checks the builder prints: energy conservation at the reference backgrounds, g has no
    effect at α = 0 (within MC error), and the largest std-errors."""
    I_b, I_w = (background_response(amap.A, amap.B, amap.C, rho) for rho in amap.reference_rhos)
    tol = 4 * np.maximum(amap.std_b, amap.std_w) + 1e-6
    report = {
        "max_I_w": float(I_w.max()),
        "energy_ok": bool(np.all(I_w <= 1 + tol)),
        "I_b_le_I_w": bool(np.all(I_b <= I_w + tol)),
    }
    if amap.alpha[0] == 0:
        # at α = 0 only unscattered paths count: every g column must agree within its MC noise
        a0, s0 = I_w[0], amap.std_w[0]                         # (σt, g)
        diff = np.abs(a0 - a0[:, :1])
        noise = 4 * np.hypot(s0, s0[:, :1]) + 1e-6
        report["g_effect_at_alpha0_max"] = float(diff.max())
        report["g_no_effect_at_alpha0"] = bool(np.all(diff <= noise))
    return report
