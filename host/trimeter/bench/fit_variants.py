"""The variants `bench fit` compares: every inversion method's bench variants from the method table (one per
artifact file it needs), the lut on a small table; how each fits, its kernel alone, and the bytes it reads
and holds."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

if TYPE_CHECKING:
    from trimeter.domain.parameters import FitResult
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.artifacts import ArtifactCache
    from trimeter.inversion.fit_model import FitModel
    from trimeter.inversion.kernel import Kernel

    # (label, method name, fit options, the map's loaded artifacts)
    Variant = tuple[str, str, dict[str, Any], FitModel]


class PolishOptions(TypedDict):
    polish: int
    polish_tol: float


DEFAULT_POLISH = PolishOptions(polish=8, polish_tol=1e-6)  # trimeter.fit's defaults
SMALL_INVERSE = 8  # the lut-small variant's inverse grid side: a half-slot device table


def variants_of(amap: AppearanceMap, cache: ArtifactCache, small_cache: ArtifactCache) -> list[Variant]:
    """(label, method, fit options, artifacts) per variant, from the method table: each method's
    bench variants, one set per artifact file a method needs (e.g. every <map>*.onnx for mlp), and the
    lut on the small table (the same fit with another table injected)."""
    from trimeter.errors import MapFileError
    from trimeter.inversion.methods import METHODS

    artifacts, small = cache.get(amap), small_cache.get(amap)
    variants: list[Variant] = []
    for method in sorted(METHODS.values(), key=lambda m: not m.joint):  # the paper baseline first
        sets: list[tuple[str, dict[str, Any]]] = [(method.name, {})]
        if method.needs:
            sets = []
            for suffix in method.needs:
                stem = amap.path.stem if amap.path is not None else ""
                files = sorted(amap.path.parent.glob(f"{stem}*{suffix}")) if amap.path is not None else []
                for model in files:
                    tag = model.stem[len(stem):].lstrip("-.")
                    try:
                        artifacts.mlp(model)
                    except MapFileError as exc:  # e.g. the map was rebuilt since: report it, bench the rest
                        print(f"   skipping {model.name}: {exc}")
                        continue
                    sets.append((f"{method.name}-{tag}" if tag else method.name, {"mlp_model": model}))
        for label, extra in sets:
            for suffix, options in method.bench_variants:
                name = f"{label}{suffix}" if suffix.startswith("-") or not suffix else f"{label} {suffix}"
                polish: dict[str, Any] = {} if method.joint else dict(DEFAULT_POLISH)
                variants.append((name, method.name, {**polish, **options, **extra}, artifacts))
        if method.name == "lut":
            variants += [("lut-small p0", "lut", dict(polish=0, polish_tol=0.0), small),
                         ("lut-small p≤8", "lut", dict(DEFAULT_POLISH), small)]
    return variants


def _array_bytes(*objects: object) -> int:
    """Bytes of the numpy arrays held by objects (their attributes one level down, tuples and lists too)."""
    seen: set[int] = set()
    total = 0
    for obj in objects:
        for value in vars(obj).values():
            for v in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(v, np.ndarray) and id(v) not in seen:
                    seen.add(id(v))
                    total += v.nbytes
    return total


def variant_bytes(variant: Variant) -> tuple[int, int]:
    """(bytes of the files the variant reads, bytes of the model it solves on in memory)."""
    from trimeter.inversion.methods import get_method

    _, method, kw, artifacts = variant
    amap = artifacts.map
    path = amap.path
    if get_method(method).joint:  # the paper method interpolates the map's nodes
        paths = [path] if path is not None else []
        return sum(p.stat().st_size for p in paths), _array_bytes(amap)
    inverter = artifacts.inverter
    files = sum(path.with_suffix(suffix).stat().st_size for suffix in (".tins",)
                if path is not None and path.with_suffix(suffix).is_file())
    files += inverter.table.size_bytes
    model = _array_bytes(inverter, inverter.grid, inverter.table_grid)
    if "mlp_model" in kw:
        files += Path(kw["mlp_model"]).stat().st_size
        model += Path(kw["mlp_model"]).stat().st_size  # onnxruntime holds the weights, about the file's size
    return files, model



def fit_variant(variant: Variant, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray | None = None,
                 rho_w: np.ndarray | None = None) -> FitResult:
    """The variant's whole fit on one core (its figures set methods side by side, the paper's in one thread)"""
    from trimeter.inversion.api import fit

    _, method, kw, artifacts = variant
    return fit(artifacts, I_b, I_w, I_c, rho_b, rho_w, method=method, kernel=one_core_kernel(), **kw)


@functools.cache
def one_core_kernel() -> Kernel:
    """The default kernel, in one thread where it would use several (one instance: it keeps its solvers)"""
    from trimeter.inversion.kernel import NativeKernel, default_kernel

    return NativeKernel(threads=1) if isinstance(default_kernel(), NativeKernel) else default_kernel()


def kernel_call(variant: Variant, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rb: float,
          rw: float) -> Callable[[], object] | None:
    """The inversion kernel alone, without input validation, flags and uncertainty: paper = the
    scipy interpolator call; a guess-and-polish method = σt from I_c + its guess (the table's, or its
    guesser's: the network for mlp) + polish. None for another whole-fit method (not timed)."""
    import trimeter.inversion.api as api
    from trimeter.inversion.kernel import default_kernel
    from trimeter.inversion.methods import get_method
    from trimeter.inversion.newton import polish_step_var
    from trimeter.inversion.paper import coordinates, interpolator

    _, method, kw, artifacts = variant
    strategy = get_method(method)
    if method == "paper":
        interp = interpolator(artifacts.map, round(rb, 3), round(rw, 3), artifacts.paper_cache)
        return lambda: interp(coordinates(I_b, I_w, I_c))
    if strategy.joint:
        return None
    kernel = default_kernel()
    n = len(I_b)
    rho_b, rho_w = np.full(n, rb), np.full(n, rw)
    inv, grid = artifacts.inverter, artifacts.grid
    polish, tol = kw["polish"], kw["polish_tol"]
    sigma = lambda: artifacts.setup.beer_lambert_sigma_t(I_c)  # noqa: E731
    # the polish stops bins as fit() does: step_tol, or a step below POLISH_TOL_STD of the noise std
    # under fit()'s default noise model
    fit_defaults = {k: p.default for k, p in inspect.signature(api.fit).parameters.items()}
    step_var = lambda: polish_step_var(I_b, I_w, fit_defaults["noise_rel"], fit_defaults["noise_abs"],  # noqa: E731
                                       grid.mc_stderr, api._polish_tol_std(tol))
    if strategy.guesser is None:
        return lambda: kernel.invert(inv, I_b, I_w, sigma(), rho_b, rho_w, iterations=polish, step_tol=tol,
                                     step_var=step_var())
    net = strategy.guesser(artifacts, kw)

    def run() -> tuple[np.ndarray, ...]:
        s = sigma()
        a0, g0 = net.predict(I_b, I_w, s, rho_b, rho_w)
        return kernel.solve_alpha_g(grid, I_b, I_w, grid.sigma_cell(s), rho_b, rho_w, a0, g0, iterations=polish,
                                    step_tol=tol, step_var=step_var())
    return run
