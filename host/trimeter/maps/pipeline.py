"""One artifact pipeline: a recipe → `.tmap` → `.tins` → `.tlut` → `.onnx`, all made by `trimeter map build`.

| stage | file | made from the map by | needs |
|---|---|---|---|
| tmap | `<name>.tmap` | trimeter.maps.builder (the columns, on Dask or here) | the recipe |
| tins | `<name>.tins` | trimeter.forward.transport.inscatter_tracer.build_inscatter_table | device geometry only |
| tlut | `<name>.tlut` | trimeter.maps.device_table.build_from_map | the .tins where the map has one |
| onnx | `<name>.onnx` | trimeter.maps.mlp_training (scikit-learn → ONNX) | opt-in: minutes of training |

Every child is derived from the `.tmap` alone, so each records the map's SHA-256 as its parent (the
.tins and .onnx metadata, the .tlut's fixed header, which also names its .tins's SHA-256) and its producer
(name and trimeter version; the .tlut's fixed C layout has no room for it: its format version stands
for it). The tlut stage therefore runs after tins. A child whose map changed
is refused where it is loaded, with `rebuild_command` (trimeter.maps.stages) naming the command that rebuilds it.

With a Dask client the children's computations run on the cluster too (one task per map and stage);
the files are always written here, next to the map.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from trimeter.errors import BuildError, InputError
from trimeter.maps.mlp_training import DEFAULTS as MLP_DEFAULTS
from trimeter.maps.stages import STAGES, SUFFIX, rebuild_command, stage_producer

if TYPE_CHECKING:
    from trimeter.maps.appearance import AppearanceMap
    from trimeter.maps.recipe import Recipe

@dataclass(frozen=True)
class Options:
    """The map's and the children's settings (the defaults are what the shipped files were made with).
    `tracer_backend`: the Dr.Jit backend the map's columns are traced on, "llvm" or "cuda" (resolved
    from "auto" by trimeter.forward.transport.resolve_backend before it gets here)."""
    tracer_backend: str = "llvm"
    inscatter_photons: int = 30_000
    inscatter_seed: int = 0
    inscatter_shape: tuple[int, int, int] = (25, 21, 13)   # α × σt·ℓ × g nodes
    table_n_xy: int | None = None
    mlp_hidden: tuple[int, ...] = MLP_DEFAULTS["hidden"]
    mlp_samples: int = MLP_DEFAULTS["samples"]
    mlp_epochs: int = MLP_DEFAULTS["epochs"]
    mlp_seed: int = MLP_DEFAULTS["seed"]
    mlp_activation: str = MLP_DEFAULTS["activation"]


# ------------------------------------------------------------------ the children, one stage each
def applies(stage: str, amap) -> str | None:
    """Why `stage` does not apply to this map (None when it does)."""
    if stage == "tins" and (amap.recipe.get("geometry") != "device"
                            or "collimated" not in amap.recipe.get("geometry_params", {})):
        return "in-scattering needs the device geometry's collimated set-up"
    if stage == "tlut":
        from trimeter.maps.device_table import too_coarse

        return too_coarse(amap)
    return None


def compute(stage: str, amap, options: Options):
    """The stage's product for `amap`, in memory (runs on a Dask worker or here)."""
    if stage == "tins":
        from trimeter.forward.transport.inscatter_tracer import build_inscatter_table

        return build_inscatter_table(amap.n, amap.thickness_mm, amap.recipe["geometry_params"],
                                     photons=options.inscatter_photons, seed=options.inscatter_seed,
                                     shape=options.inscatter_shape)
    if stage == "tlut":
        from trimeter.maps.device_table import build_from_map

        return build_from_map(amap, n_inverse=options.table_n_xy)
    if stage == "onnx":
        from trimeter.maps.mlp_training import train

        return train(amap, options.mlp_hidden, options.mlp_samples, options.mlp_epochs, options.mlp_seed,
                     options.mlp_activation)
    raise ValueError(f"no child stage {stage!r}")


def write(stage: str, amap, product, options: Options, out: Path | None = None) -> tuple[Path, str]:
    """Stamp the product with its parent (the map's SHA-256) and producer, write it next to the map (or
    to `out`), read it back; returns (path, one-line description)."""
    out = Path(out) if out else amap.path.with_suffix(SUFFIX[stage])
    if stage == "tins":
        from trimeter.maps.inscatter_file import load_inscatter, save_inscatter

        product.parent_sha256, product.producer = amap.checksum, stage_producer(stage)
        checksum = save_inscatter(product, out)
        load_inscatter(out)
        return out, (f"{product.L.shape} grid, {options.inscatter_photons} photons per column, largest ln(1 + r) "
                     f"{product.L.max():.3f}, sha256 {checksum[:12]}…")
    if stage == "tlut":
        from trimeter.maps.device_table import describe_table

        product.save(out)
        info = describe_table(out)  # read back: every check of the reader
        return out, (f"device table format {info['format_version']}, {info['size_bytes']} bytes (slot "
                     f"{info['slot_capacity_bytes']}), sha256 {info['sha256'][:12]}…, inverse "
                     f"{info['inverse_grid']['x']}×{info['inverse_grid']['y']} per σt node, in-scattering "
                     f"{'none' if info['inscatter_grid'] is None else '×'.join(map(str, info['inscatter_grid']))}")
    if stage == "onnx":
        from trimeter.maps.mlp_training import export

        model, stats = product
        export(model, amap, out, options.mlp_hidden, stats, stage_producer(stage))
        return out, (f"hidden {options.mlp_hidden}, raw network on fresh map samples: α abs p95 "
                     f"{stats['alpha_abs_p95']:.4f}, g abs p95 {stats['g_abs_p95']:.4f}")
    raise ValueError(f"no child stage {stage!r}")


def make_child(stage: str, amap, options: Options = Options(), out: Path | None = None,
               say: Callable[[str], None] = print) -> Path:
    """One child of one map, here (e.g. `trimeter map inscatter`)."""
    if why := applies(stage, amap):
        raise InputError(f"map {amap.name}: {why}")
    t0 = time.perf_counter()
    path, text = write(stage, amap, compute(stage, amap, options), options, out)
    say(f"{stage}: wrote {path} in {time.perf_counter() - t0:.1f} s: {text}")
    return path


# ------------------------------------------------------------------ the whole pipeline for a library
@dataclass(frozen=True)
class Target:
    """One map of a build: its recipe, where the recipe came from (for messages) and the .tmap path."""
    recipe: Recipe
    recipe_path: Path | None
    out: Path


def run(targets: list[Target], stages: tuple[str, ...], *, client=None, resume: bool = False, progress: bool = True,
        keep_checkpoint: bool = False, checkpoint_dir: Path | None = None, retries: int = 2,
        options: Options = Options(), say: Callable[[str], None] = print) -> list:
    """Run `stages` for every target: the maps (all their columns at once), then each map's children.
    Without the tmap stage the maps must exist and be current against their recipes."""
    from trimeter.maps.builder import MapJob, build_maps, recipe_fingerprint, validation_report
    from trimeter.forward.transport import trace_column as trace_pair

    if "tmap" in stages:
        jobs = [MapJob(t.recipe, t.out, checkpoint_dir) for t in targets]
        # A partial of a module-level function: pickles to Dask workers like the function itself.
        tracer = functools.partial(trace_pair, backend=options.tracer_backend)
        maps = build_maps(jobs, client=client, resume=resume, progress=progress, keep_checkpoint=keep_checkpoint,
                          retries=retries, tracer=tracer)
        for amap in maps:
            _report_map(amap, validation_report(amap), say)
            for stage in STAGES[1:]:
                child = _saved_path(amap).with_suffix(SUFFIX[stage])
                if stage not in stages and child.exists():
                    say(f"note: {child} was made from the previous map and will be refused; rebuild it: "
                        f"{rebuild_command(amap, stage)}")
    else:
        maps = []
        for t in targets:
            amap = _existing_map(t.out)
            if recipe_fingerprint(amap.recipe) != recipe_fingerprint(t.recipe):
                raise BuildError(f"map {t.out} was built from another recipe than {t.recipe_path or t.recipe.name} "
                                 f"(or another geometry): rebuild it first, with --stages tmap,"
                                 f"{','.join(stages)}")
            maps.append(amap)
    children = [(amap, stage) for amap in maps for stage in stages if stage != "tmap"]
    runnable = []
    for amap, stage in children:
        if why := applies(stage, amap):
            say(f"{stage}: skipped for {amap.name}: {why}")
        else:
            runnable.append((amap, stage))
    # the table carries the in-scattering table: it is built once this run's .tins are written, from the
    # map read again (a loaded map keeps the .tins it first saw)
    _write_all([c for c in runnable if c[1] != "tlut"], client, options, say)
    _write_all([(_existing_map(_saved_path(amap)), stage) for amap, stage in runnable if stage == "tlut"],
               client, options, say)
    return maps


def _write_all(runnable, client, options: Options, say: Callable[[str], None]) -> None:
    for (amap, stage), (product, seconds) in zip(runnable, _compute_all(runnable, client, options), strict=True):
        path, text = write(stage, amap, product, options)
        say(f"{stage}: wrote {path} ({seconds:.1f} s): {text}")


def _existing_map(path: Path) -> AppearanceMap:
    from trimeter.maps.appearance import AppearanceMap

    if not path.is_file():
        raise InputError(f"map {path} does not exist: build it first (--stages tmap, the default includes it)")
    return AppearanceMap.load(path)


def _saved_path(amap: AppearanceMap) -> Path:
    """The file a map of this build was written to or read from (only an in-memory map has none)."""
    if amap.path is None:
        raise BuildError(f"map {amap.name} has no file: the build writes every map before its children")
    return amap.path


def _timed(stage: str, amap, options: Options):
    t0 = time.perf_counter()
    return compute(stage, amap, options), time.perf_counter() - t0


def _compute_all(runnable, client, options: Options):
    """(product, seconds) per (map, stage), in order: on the cluster all at once, else one after another."""
    if client is None:
        for amap, stage in runnable:
            yield _timed(stage, amap, options)
        return
    futures = [client.submit(_timed, stage, amap, options, pure=False) for amap, stage in runnable]
    try:
        for (amap, stage), future in zip(runnable, futures, strict=True):
            try:
                yield future.result()
            except Exception as exc:  # noqa: BLE001 - whatever the task raised, named with its map and stage
                raise BuildError(f"map {amap.name}: the {stage} stage failed on the cluster "
                                 f"({type(exc).__name__}: {(str(exc) or '-').splitlines()[0]}); the map itself is "
                                 f"written: {rebuild_command(amap, stage)}") from None
    finally:
        client.cancel(futures)


def _report_map(amap, report: dict, say) -> None:
    info, prov = amap.info(), amap.provenance
    say(f"tmap: wrote {amap.path} ({amap.path.stat().st_size / 1e6:.2f} MB, sha256 {amap.checksum[:16]}…)")
    say(f"  trace time {prov['trace_seconds']:.1f} s (this run: {prov['wall_seconds_last_run']:.1f} s wall on "
        f"{prov.get('executor', 'this process')}, {prov['columns_traced_last_run']} columns traced, "
        f"{prov['columns_resumed']} resumed)")
    say(f"  MC std-error of I: median {info['mc_stderr']['median']:.2e}, max {info['mc_stderr']['max']:.2e}; "
        f"paths per column {prov['paths_per_column']['min']}…{prov['paths_per_column']['max']}; "
        f"truncation error ≤ {prov['truncation']['max_error_bound']:.1e} (K = {prov['truncation']['k_max']})")
    say(f"  validation: {report}")
