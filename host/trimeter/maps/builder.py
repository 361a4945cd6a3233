"""The map builder: a recipe → an AppearanceMap, one (k, m)-tally trace per (σt, g) column.

- Deterministic: the random stream of column (j, k) batch b is seeded from (recipe seed, j, k, b) only,
  so the same recipe gives the same map whatever the order, interruptions or thread count (the
  shipped device maps' columns re-trace to within 1.5e-8, not bit for bit: see the git history of maps/README.md).
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
import logging
import math
import os
import shutil
import sys
import time
import zipfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from trimeter.atomic import atomic_output, atomic_write
from trimeter.errors import BuildError, InputError, MapFileError
from trimeter.geometry import cover_slide_n
from trimeter.formats.appearance import AppearanceMap
from trimeter.maps.recipe import Recipe
from trimeter.forward.transport import ColumnTally, Stack, k_max_for
from trimeter.forward.transport import trace_column as trace_pair
from trimeter.model.collimated import MEASURABLE_IC, collimated_transmittance
from trimeter.model.response import background_response

if TYPE_CHECKING:
    from rich.progress import Progress

BUILDER = ("trimeter.forward.transport: (k, m)-tally path tracer (detector + background paths; B = UT1·UTU where the "
           "geometry factorises), Dr.Jit LLVM symbolic loop")
_COLUMN_FIELDS = ("A", "B", "C", "std_b", "std_w")
log = logging.getLogger("trimeter.maps")
_BATCH_QUANTUM = 4096
PROGRESS_EVERY_S = 30.0  # without a terminal (a log, a pipe): a progress line at most this often, and at the end


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
    options = {"polarisation": True} if recipe.polarisation else {}   # only when on: any tracer without it still serves
    while n_next > 0:
        part = tracer(stack, sigma_t, g, n_next, column_seed(recipe.seed, j, k, batch), k_max, **options)
        if tally is None:
            tally = part
        else:
            tally += part
        batch += 1
        shortfall = criterion_shortfall(tally, recipe, sigma_t)  # (std-error reached / target) for the worse criterion
        if shortfall <= 1.0 or tally.n_paths >= s.max_paths or batch >= 4:
            break
        wanted = paths_to_reach(tally.n_paths, shortfall, s.max_paths)
        n_next = math.ceil((wanted - tally.n_paths) / _BATCH_QUANTUM) * _BATCH_QUANTUM
    if tally is None:
        raise BuildError(f"recipe {recipe.name}: sampling.min_paths is {s.min_paths}, no paths were traced")
    A, B, C = tally.abc(recipe.alpha)
    return Column(A=A, B=B, C=C, std_b=tally.stderr(recipe.alpha, recipe.reference_rho_b),
                  std_w=tally.stderr(recipe.alpha, recipe.reference_rho_w), n_paths=tally.n_paths,
                  truncated=tally.truncated, truncation_bound=tally.truncation_bound(float(recipe.alpha[-1])),
                  seconds=tally.seconds, path_events=tally.path_events)


def paths_to_reach(n_paths: int, shortfall: float, cap: int) -> int:
    """How many paths in all a column needs whose std-error is `shortfall` × its target after
    n_paths: std-error ∝ 1/√N, so n_paths·shortfall² (+10 %), within the cap."""
    return min(int(cap), math.ceil(n_paths * shortfall ** 2 * 1.1))


def criterion_shortfall(tally: ColumnTally, recipe: Recipe, sigma_t: float) -> float:
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
    """A directory of finished columns for one recipe (refuses a directory made for another). The
    columns in it are the build's source of truth: whoever traces a column writes it here, and the map
    is assembled from what is here, so a killed worker or a killed build loses at most its running columns."""

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
        return column_path(self.dir, j, k)

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
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            self.quarantine(j, k, f"unreadable ({exc})")   # traced again (deterministically)
            return None
        if any(getattr(col, f).shape != (len(self.recipe.alpha),) for f in _COLUMN_FIELDS):
            self.quarantine(j, k, "another shape than the recipe's")
            return None
        if not all(np.isfinite(getattr(col, f)).all() for f in _COLUMN_FIELDS):
            self.quarantine(j, k, "not finite (NaN or inf)")
            return None
        return col

    def quarantine(self, j: int, k: int, why: str) -> None:
        """Move a column that cannot be used aside (into the directory beside the checkpoint named by
        quarantine_dir, which a finished build does not remove: it is evidence of what went wrong), so that it
        is traced again."""
        target = quarantine_dir(self.dir) / f"{self.path(j, k).name}.{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
        try:
            target.parent.mkdir(exist_ok=True)
            os.replace(self.path(j, k), target)
        except OSError as exc:
            raise BuildError(f"checkpoint column {self.path(j, k)} is {why} and cannot be moved aside ({exc}); "
                             f"move it out of the way by hand") from None
        log.warning("checkpoint column %s is %s: moved to %s, traced again", self.path(j, k).name, why, target)

    def save(self, j: int, k: int, col: Column) -> None:
        save_column(self.dir, j, k, col)

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def quarantine_dir(checkpoint: Path) -> Path:
    return checkpoint.parent / f"{checkpoint.name}.quarantine"


def column_path(directory: Path, j: int, k: int) -> Path:
    return Path(directory) / f"col_{j:03d}_{k:03d}.npz"


def save_column(directory: Path, j: int, k: int, col: Column) -> None:
    with atomic_output(column_path(directory, j, k), make_parents=False) as f:
        np.savez(f, **{name: getattr(col, name) for name in _COLUMN_FIELDS}, n_paths=col.n_paths,
                 truncated=col.truncated, truncation_bound=col.truncation_bound, seconds=col.seconds,
                 path_events=col.path_events)


def column_task(recipe: Recipe, checkpoint_dir: str, j: int, k: int, tracer: Callable = trace_pair,
                drjit_threads: int | None = None) -> tuple[Column, bool]:
    """One column as a task, wherever it runs (this process or a Dask worker): trace it, write it to the
    checkpoint, return (column, written). A pure function of (recipe, j, k) — its seeds come from the
    column's identity (column_seed) — so a retry, another worker or another order gives the same bits.
    `written` is False on a worker that does not see the checkpoint directory (no shared file system):
    the caller then writes the column it receives."""
    if drjit_threads:
        from trimeter.forward.transport.backend import set_drjit_threads

        set_drjit_threads(drjit_threads)
    stack = Stack.from_recipe(recipe.geometry, recipe.geometry_params, recipe.n, recipe.thickness_mm)
    col = trace_column(recipe, stack, j, k, tracer)
    if not Path(checkpoint_dir).is_dir():
        return col, False
    save_column(Path(checkpoint_dir), j, k, col)
    return col, True


def default_checkpoint_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.checkpoint"


@dataclass(frozen=True)
class MapJob:
    """One map of a build: its recipe, its output file and (default: next to it) its checkpoint."""
    recipe: Recipe
    out: Path
    checkpoint_dir: Path | None = None

    @property
    def checkpoint(self) -> Path:
        return Path(self.checkpoint_dir) if self.checkpoint_dir else default_checkpoint_dir(Path(self.out))


class _MapState:
    """The columns of one map as they arrive (from the checkpoint or from a task)."""

    def __init__(self, index: int, job: MapJob, resume: bool):
        self.index, self.job, self.recipe = index, job, job.recipe
        self.ckpt = Checkpoint(job.checkpoint, job.recipe, resume)
        self.arrays = {f: np.zeros(job.recipe.shape) for f in _COLUMN_FIELDS}
        ns, ng = job.recipe.shape[1:]
        self.n_paths = np.zeros((ns, ng), dtype=np.int64)
        self.trunc_bound = np.zeros((ns, ng))
        self.trace_seconds = np.zeros((ns, ng))
        self.done = np.zeros((ns, ng), dtype=bool)
        self.traced = self.reused = 0

    def columns(self) -> list[tuple[int, int]]:
        ns, ng = self.recipe.shape[1:]
        return [(j, k) for k in range(ng) for j in range(ns)]

    def add(self, j: int, k: int, col: Column, traced: bool) -> None:
        for f in _COLUMN_FIELDS:
            self.arrays[f][:, j, k] = getattr(col, f)
        self.n_paths[j, k], self.trunc_bound[j, k], self.trace_seconds[j, k] = (col.n_paths, col.truncation_bound,
                                                                              col.seconds)
        self.done[j, k] = True
        self.traced += traced
        self.reused += not traced

    def finish(self, wall: float, executor: str, keep_checkpoint: bool) -> AppearanceMap:
        recipe, n_paths = self.recipe, self.n_paths
        provenance = {
            "builder": BUILDER, "executor": executor,
            "drjit_version": _version("drjit"), "mitsuba_version": _version("mitsuba"),
            "trace_seconds": round(float(self.trace_seconds.sum()), 3),
            "wall_seconds_last_run": round(wall, 3), "columns_traced_last_run": self.traced,
            "columns_resumed": self.reused,
            "paths_per_column": {"min": int(n_paths.min()), "median": int(np.median(n_paths)),
                                 "max": int(n_paths.max()), "total": int(n_paths.sum())},
            "truncation": {"k_max": k_max_for(float(recipe.alpha[-1]), recipe.sampling.truncation),
                           "max_error_bound": float(self.trunc_bound.max())},
            "recipe_fingerprint": recipe_fingerprint(recipe),
            "built_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        arrays = self.arrays
        broken = sorted({(int(j), int(k)) for f in _COLUMN_FIELDS for _, j, k in np.argwhere(~np.isfinite(arrays[f]))})
        if broken:  # never written as a map nobody can load; the checkpoint stays for a --resume
            raise BuildError(f"{self.job.out}: column(s) {', '.join(f'({j}, {k})' for j, k in broken[:5])}"
                             f"{' …' if len(broken) > 5 else ''} traced to a non-finite value; nothing was written, "
                             f"the checkpoint {self.ckpt.dir} is kept")
        amap = AppearanceMap(recipe=recipe.to_dict(), alpha=recipe.alpha, sigma_t=recipe.sigma_t, g=recipe.g,
                             A=arrays["A"], B=arrays["B"], C=arrays["C"], std_b=arrays["std_b"],
                             std_w=arrays["std_w"], provenance=provenance)
        amap.save(self.job.out)
        loaded = AppearanceMap.load(self.job.out)   # the checkpoint goes only once the map reads back
        if not keep_checkpoint:
            self.ckpt.remove()
        return loaded


def build_map(recipe: Recipe, out: str | Path, *, checkpoint_dir: str | Path | None = None, resume: bool = False,
              progress: bool = True, keep_checkpoint: bool = False, tracer: Callable = trace_pair,
              on_column: Callable[[int, int], None] | None = None, client=None) -> AppearanceMap:
    """Build the map for `recipe` into `out` (atomically): build_maps with one map."""
    job = MapJob(recipe, Path(out), Path(checkpoint_dir) if checkpoint_dir else None)
    return build_maps([job], resume=resume, progress=progress, keep_checkpoint=keep_checkpoint, tracer=tracer,
                      on_column=None if on_column is None else (lambda name, j, k: on_column(j, k)),
                      client=client)[0]


def build_maps(jobs: list[MapJob], *, client=None, resume: bool = False, progress: bool = True,
               keep_checkpoint: bool = False, tracer: Callable = trace_pair, retries: int = 2,
               on_column: Callable[[str, int, int], None] | None = None) -> list[AppearanceMap]:
    """Build every map of `jobs` (a library build): every unfinished (map, σt, g) column is one task.
    `client`: a dask.distributed Client (trimeter.maps.distributed) to run the tasks on its cluster,
    `retries` times more after a failure; None: one after another in this process. `on_column(name,
    j, k)` is called after each traced column (not for those reloaded from the checkpoint) — used by
    tests to interrupt. Whatever the executor, the maps hold the same bits (seeds from column identity)."""
    outs = [Path(job.out).resolve() for job in jobs]
    if len(set(outs)) != len(outs):
        raise InputError("two recipes would write the same map file: give them different names or outputs")
    states = [_MapState(i, job, resume) for i, job in enumerate(jobs)]
    pending = []
    for state in states:
        for j, k in state.columns():
            col = state.ckpt.load(j, k) if resume else None
            if col is None:
                pending.append((state, j, k))
            else:
                state.add(j, k, col, traced=False)
    start = time.perf_counter()
    if progress:  # before the first column, which on a large recipe alone takes long: what the build will do
        for state in states:
            print(work_line(state.recipe, len(state.columns()), state.reused), file=sys.stderr, flush=True)
    with _progress(progress, [(s.recipe.name, len(s.columns()), s.reused) for s in states]) as advance:
        if client is None:
            executor = "in-process"
            results = _run_here(pending, tracer)
        else:
            from trimeter.maps.distributed import describe_cluster, run_on_cluster

            executor = describe_cluster(client)
            results = run_on_cluster(client, pending, column_task, tracer, retries)
        for state, j, k, col in results:
            state.add(j, k, col, traced=True)
            advance(state.index)
            if on_column:
                on_column(state.recipe.name, j, k)
    wall = time.perf_counter() - start
    return [state.finish(wall, executor, keep_checkpoint) for state in states]


def _run_here(pending, tracer):
    """The tasks one after another in this process (the tests' and library default executor)."""
    stacks = {}
    for state, j, k in pending:
        r = state.recipe
        if id(state) not in stacks:
            stacks[id(state)] = Stack.from_recipe(r.geometry, r.geometry_params, r.n, r.thickness_mm)
        col = trace_column(r, stacks[id(state)], j, k, tracer)
        state.ckpt.save(j, k, col)
        yield state, j, k, col


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def work_line(recipe: Recipe, columns: int, reused: int) -> str:
    """What a map's build will trace: its columns and the photon paths each takes (up to the cap)."""
    s = recipe.sampling
    todo = columns - reused
    each = f"{s.min_paths:,} photon paths each" if s.max_paths == s.min_paths else \
        f"{s.min_paths:,} to {s.max_paths:,} photon paths each"
    return (f"{recipe.name}: tracing {todo} of {columns} (σt, g) columns ({reused} from the checkpoint), {each} "
            f"(up to {todo * s.max_paths:,} paths in all)")


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class ProgressLines:
    """Progress without a terminal: a line per map at most every `every_s` seconds and when it is done,
    with the columns traced, the time elapsed and an estimate of the time left (from this run's pace)."""

    def __init__(self, maps: list[tuple[str, int, int]], every_s: float = PROGRESS_EVERY_S,
                 clock: Callable[[], float] = time.monotonic, out=None):
        self.maps, self.every_s, self.clock = maps, every_s, clock
        self.out = out if out is not None else sys.stderr
        self.start = clock()
        self.done = [reused for _, _, reused in maps]
        self.last = [self.start] * len(maps)

    def advance(self, index: int) -> None:
        name, total, reused = self.maps[index]
        self.done[index] += 1
        now = self.clock()
        if now - self.last[index] < self.every_s and self.done[index] < total:
            return
        self.last[index] = now
        elapsed = now - self.start
        # the pace over every map of the build (their columns interleave): the time left for all of them
        traced = sum(done - m[2] for done, m in zip(self.done, self.maps, strict=True))
        left = sum(m[1] for m in self.maps) - sum(self.done)
        mine = "this map is done, " if self.done[index] >= total else ""
        state = f"{mine}about {_duration(left * elapsed / traced)} left" if left else "the build is done"
        print(f"{name}: {self.done[index]}/{total} columns, {_duration(elapsed)} elapsed, {state}", file=self.out,
              flush=True)


class _progress:
    """One progress view over every map of a build: a bar per map and, for several, one for all columns
    on a terminal; ProgressLines otherwise (a log, a pipe); nothing for tests. Entering returns
    advance(map index)."""

    def __init__(self, enabled: bool, maps: list[tuple[str, int, int]]):
        self.enabled, self.maps = enabled, maps
        self._bar: Progress | None = None

    def __enter__(self):
        if not self.enabled:
            return lambda index: None
        if not sys.stderr.isatty():
            return ProgressLines(self.maps).advance
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

        bar = self._bar = Progress("[bold]{task.description}", BarColumn(), MofNCompleteColumn(),
                                   TimeElapsedColumn(), TimeRemainingColumn())
        bar.__enter__()
        tasks = [bar.add_task(f"{name} (σt, g) columns", total=total, completed=done)
                 for name, total, done in self.maps]
        overall = None
        if len(self.maps) > 1:
            overall = bar.add_task(f"all {len(self.maps)} maps", total=sum(m[1] for m in self.maps),
                                   completed=sum(m[2] for m in self.maps))

        def advance(index: int) -> None:
            bar.advance(tasks[index])
            if overall is not None:
                bar.advance(overall)
        return advance

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
