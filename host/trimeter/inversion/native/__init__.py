"""The compiled inversion kernel (the C sources next to this file and the inverse core it shares with the
firmware, fit_core/ at the repository's root), bound with ctypes.

`make native` (part of `make setup`, so of `make test` and `make demo`) compiles it into
libtrimeter_invert.so here. Its boundary is declared once, in invert.h: tools/gen_native.py generates
invert_h.py from it (ctypes structures, prototypes, flag bits, constants, the ABI hash), and a library
built from another header, or from sources older than these, is refused by name.

Which kernel runs is chosen by TRIMETER_KERNEL: `auto` (the default) runs the compiled one and, when
it is missing, stale or does not load, the numpy kernel (trimeter.inversion.kernel, the reference the
C code is tested against; same results, many times slower) with a NativeKernelWarning that says so and
names `make native`; `numpy` runs the numpy kernel on purpose, without a warning (TRIMETER_NATIVE=0
means the same); `native` requires the compiled one (NativeKernelError at import otherwise).
`status()` says which one runs (the benchmark prints it).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import warnings
import weakref
import zlib
from pathlib import Path
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from trimeter.errors import TrimeterError
from trimeter.paths import FIT_CORE_DIR
from trimeter.inversion.native import invert_h

if TYPE_CHECKING:
    from trimeter.model.grid import ForwardGrid

LIBRARY = Path(__file__).with_name("libtrimeter_invert.so")
ABI_HASH = invert_h.ABI_HASH
ABI_VERSION = ABI_HASH  # the name callers used before the hash replaced a hand-bumped number

# The polish and in-scattering constants the numpy kernel shares with C (invert.h)
STEP_RATIO = invert_h.STEP_RATIO
INSCATTER_ONCE = invert_h.INSCATTER_ONCE

_double_p = ctypes.POINTER(ctypes.c_double)
_ForwardGridC = invert_h.ForwardGridStruct
_InverseTableC = invert_h.InverseTableStruct
_FitOptionsC = invert_h.FitOptionsStruct
_OUTPUT_ROWS = invert_h.OUTPUT_ROWS

REBUILD = "run `make native`, or set TRIMETER_KERNEL=numpy to run the numpy kernel on purpose"


class NativeKernelError(TrimeterError):
    """TRIMETER_KERNEL=native, but the compiled kernel is missing, stale or does not load; or
    TRIMETER_KERNEL or TRIMETER_FIT_THREADS has a value it does not take."""


class NativeKernelWarning(UserWarning):
    """The compiled kernel is missing, stale or does not load: the numpy kernel runs instead."""


def source_hash(directories: tuple[Path, ...] = (LIBRARY.parent, FIT_CORE_DIR)) -> int | None:
    """The hash `make native` compiles into the library (tm_source_hash): 64 bits of SHA-256 over the
    kernel's .c and .h files, directory after directory (its own, then the inverse core it shares with
    the firmware), each in name order; None where the sources are not all there (an installed package)."""
    per_directory = [sorted(p for p in d.iterdir() if p.suffix in (".c", ".h")) if d.is_dir() else []
                     for d in directories]
    if not all(per_directory):
        return None
    files = [p for found in per_directory for p in found]
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in files)).hexdigest()
    return int(digest[:16], 16)


def choice() -> str:
    """The kernel TRIMETER_KERNEL asks for: 'auto', 'native' or 'numpy' (TRIMETER_NATIVE=0: 'numpy')."""
    if os.environ.get("TRIMETER_NATIVE") == "0":
        return "numpy"
    value = os.environ.get("TRIMETER_KERNEL", "auto").strip().lower() or "auto"
    if value not in ("auto", "native", "numpy"):
        raise NativeKernelError(f"TRIMETER_KERNEL must be auto, native or numpy, not {value!r}")
    return value


def _open() -> tuple[ctypes.CDLL | None, str]:
    """(the library, '') when it is current and loads, else (None, why not)."""
    if not LIBRARY.is_file():
        return None, f"{LIBRARY.name} is not built"
    try:
        lib = ctypes.CDLL(str(LIBRARY))
    except OSError as exc:
        return None, f"{LIBRARY.name} does not load ({exc})"
    try:
        built_for = lib.tm_abi_hash
    except AttributeError:
        return None, f"{LIBRARY.name} is stale (it has no tm_abi_hash: built before invert.h)"
    built_for.restype = ctypes.c_uint64
    if built_for() != ABI_HASH:
        return None, (f"{LIBRARY.name} is stale (built for another invert.h: ABI {built_for():016x}, "
                      f"expected {ABI_HASH:016x})")
    for name, (restype, argtypes) in invert_h.FUNCTIONS.items():
        function = getattr(lib, name)
        function.restype, function.argtypes = restype, argtypes
    expected = source_hash()
    if expected is not None and lib.tm_source_hash() != expected:
        return None, f"{LIBRARY.name} is stale (older than the C sources beside it)"
    return lib, ""


def _load() -> tuple[ctypes.CDLL | None, str]:
    """(the library or None, the status line); warns or raises as TRIMETER_KERNEL asks."""
    chosen = choice()
    if chosen == "numpy":
        return None, "numpy kernel (chosen by TRIMETER_KERNEL=numpy)"
    lib, why = _open()
    if lib is None:
        if chosen == "native":
            raise NativeKernelError(f"TRIMETER_KERNEL=native, but {why}: run `make native`")
        warnings.warn(f"{why}: the numpy kernel runs instead, many times slower; {REBUILD}", NativeKernelWarning,
                      stacklevel=2)
        return None, f"numpy kernel ({why}; {REBUILD})"
    lanes = "AVX2, 4 bins per Newton step" if lib.tm_set_simd(1) else "scalar"
    return lib, f"compiled ({LIBRARY.name}, {lanes})"


_LIB, _STATUS = _load()


def _library() -> ctypes.CDLL:
    """The loaded library; only the native kernel's paths reach here, chosen where it is available."""
    if _LIB is None:
        raise NativeKernelError(f"the compiled kernel is not loaded: {_STATUS}")
    return _LIB


def set_simd(enabled: bool) -> bool:
    """Let the polish, the σ check and two thicknesses' combination take four bins per step with AVX2
    (the default where the CPU has it) or only the scalar loops: the results are bit for bit the same
    (tests compare them). Returns whether the four-lane steps are in use."""
    return bool(_LIB.tm_set_simd(1 if enabled else 0)) if _LIB is not None else False


def available() -> bool:
    return _LIB is not None


def status() -> str:
    """'compiled (…)', or which numpy kernel runs and why."""
    return _STATUS


def _ptr(a: np.ndarray) -> Any:
    return a.ctypes.data_as(_double_p)


def _addr(a: np.ndarray) -> int:
    """The data address of a contiguous array: through ctypes' buffer protocol when the array is
    writable (the cheaper way; a fit takes a dozen), else its __array_interface__ (read-only or
    empty arrays)."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))  # type: ignore[arg-type]  # ndarray is a buffer
    except (TypeError, ValueError):
        return a.__array_interface__["data"][0]


def _f64(x: ArrayLike, n: int) -> np.ndarray:
    """A contiguous float64 array of n values (broadcast scalars), as the C loop reads it."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    return a if a.shape == (n,) else np.ascontiguousarray(np.broadcast_to(a, (n,)))


class NativeSolver:
    """One forward grid (and optionally one inverse table) handed to C once; arrays kept alive here."""

    def __init__(self, grid: ForwardGrid, inverse_cells: np.ndarray | None = None,
                 inverse_frame: np.ndarray | None = None, inverse_shape: tuple[int, int, int] | None = None,
                 inverse_log_sigma_t: np.ndarray | None = None) -> None:
        """grid: the forward grid the polish runs on; inverse_*: the table's guess slices, at its own σt
        nodes inverse_log_sigma_t (the forward grid may be finer in σt)."""
        keep = {name: np.ascontiguousarray(value, dtype=np.float64) for name, value in (
            ("alpha", grid.alpha), ("log_sigma_t", grid.log_sigma_t), ("g", grid.g), ("inv_da", grid._inv_da),
            ("inv_ds", grid._inv_ds), ("inv_dg", grid._inv_dg))}
        keep["poly"] = _cache_aligned(grid._poly)
        na, ns, ng = grid.shape
        self._grid = _ForwardGridC(na, ns, ng, *(_ptr(keep[k]) for k in ("alpha", "log_sigma_t", "g", "inv_da",
                                                                           "inv_ds", "inv_dg", "poly")),
                                   *grid.alpha_range, *grid.g_range, grid.thickness_mm, *grid.stack_constants[:2],
                                   _uniform_step(keep["log_sigma_t"]))
        if grid.inscatter_grid is not None:
            inscatter_L, inv_dt, tau_max = grid.inscatter_grid
            keep["inscatter_L"] = _cache_aligned(inscatter_L)
            self._grid.in_nt = keep["inscatter_L"].shape[1]
            self._grid.inscatter_L = _ptr(keep["inscatter_L"])
            self._grid.in_inv_dt, self._grid.in_tau_max = inv_dt, tau_max
        if grid.model_var is not None:
            keep["model_var"] = _cache_aligned(grid.model_var)
            self._grid.model_var = _ptr(keep["model_var"])
        for axis in ("alpha", "g"):
            index, scale = _cell_index(keep[axis])
            if index is not None:
                keep[axis + "_index"] = index
                setattr(self._grid, axis + "_index", index.ctypes.data_as(ctypes.POINTER(ctypes.c_uint16)))
                setattr(self._grid, axis + "_index_n", len(index))
                setattr(self._grid, axis + "_index_scale", scale)
        self._table = None
        if inverse_cells is not None:
            if inverse_frame is None or inverse_shape is None or inverse_log_sigma_t is None:
                raise ValueError("an inverse table needs its cells, frame, shape and σt nodes together")
            keep["cells"] = np.ascontiguousarray(inverse_cells, dtype=np.float64)
            keep["frame"] = np.ascontiguousarray(inverse_frame, dtype=np.float64)
            keep["table_log_sigma_t"] = np.ascontiguousarray(inverse_log_sigma_t, dtype=np.float64)
            keep["table_inv_ds"] = 1.0 / np.diff(keep["table_log_sigma_t"])
            if len(keep["table_log_sigma_t"]) != inverse_shape[0]:
                raise ValueError("the table's σt axis must have one node per slice")
            self._table = _InverseTableC(*inverse_shape, _ptr(keep["cells"]), _ptr(keep["frame"]),
                                         _ptr(keep["table_log_sigma_t"]), _ptr(keep["table_inv_ds"]),
                                         _uniform_step(keep["table_log_sigma_t"]))
        self._keep = keep
        self._fit_options: dict = {}
        self._grid_ref = ctypes.byref(self._grid)
        self._table_ref = ctypes.byref(self._table) if self._table is not None else None

    def solve(self, I_b: ArrayLike, I_w: ArrayLike, log_sigma_t: np.ndarray, rho_b: ArrayLike, rho_w: ArrayLike,
              iterations: int, alpha0: ArrayLike | None = None, g0: ArrayLike | None = None, step_tol: float = 0.0,
              step_var: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(α, g, residual, J (n, 3, 3)) as ForwardGrid.solve_alpha_g returns them. ln σt is clamped to
        the grid in C (NaN → lowest node). Initial guess from the inverse table, or alpha0/g0 when
        given (then the table is not used)."""
        n = len(log_sigma_t)
        args = [_f64(v, n) for v in (I_b, I_w, log_sigma_t, rho_b, rho_w)]
        use_table = alpha0 is None
        if use_table and self._table is None:
            raise ValueError("this solver has no inverse table: pass alpha0 and g0")
        if (alpha0 is None) != (g0 is None):
            raise ValueError("pass alpha0 and g0 together, or neither")
        alpha = np.zeros(n) if alpha0 is None else _f64(alpha0, n).copy()
        g = np.zeros(n) if g0 is None else _f64(g0, n).copy()
        residual = np.empty(n)
        J = np.empty((n, 3, 3))
        step_var = None if step_var is None else _f64(step_var, n)  # kept alive through the call
        rc = _library().tm_solve_alpha_g(self._grid_ref, self._table_ref if use_table else None, n,
                                   *(_addr(a) for a in args), int(iterations), float(step_tol),
                                   None if step_var is None else _addr(step_var), _addr(alpha),
                                   _addr(g), _addr(residual), _addr(J))
        _check(rc)
        return alpha, g, residual, J

    def _options(self, options: dict[str, Any]) -> Any:
        """A reference to the C options struct for fit()'s options (options_struct)."""
        return ctypes.byref(self.options_struct(options))

    def options_struct(self, options: dict[str, Any]) -> _FitOptionsC:
        """The C options struct for fit()'s options, built once per distinct set: building a ctypes
        struct costs more than the dict lookup, most of all in a cold cache (one press-button
        measurement)."""
        key = tuple(options.items())
        struct = self._fit_options.get(key)
        if struct is None:
            if len(self._fit_options) >= 64:  # a caller sweeping parameters: keep it bounded
                self._fit_options.clear()
            struct = self._fit_options[key] = _fit_options(**options)
        return struct

    def fit(self, I_b: np.ndarray, I_w: ArrayLike, I_c: ArrayLike, rho_b: ArrayLike, rho_w: ArrayLike, *,
            sd: ArrayLike | None = None, alpha0: ArrayLike | None = None, g0: ArrayLike | None = None,
            block: np.ndarray | None = None, threads: int = 1, **options: Any) -> dict[str, Any]:
        """One thickness's whole fit in one call (invert.h `tm_fit`, api._fit_one's reference path
        operation for operation): a dict of the FitResult columns and `steps`, the Newton steps taken.
        sd: the intensities' stds (n, 3), or None for the noise model of `options`
        (trimeter.inversion.api.native_options(…)). block: the output block to write (rows
        invert_h.OUTPUT_ROWS × n, float64, C-contiguous), else a new one. threads: from the table's guess,
        up to this many threads share the bins out (`tm_fit_thicknesses` of one thickness; the same
        results for any count)."""
        n = len(I_b)
        args = [_f64(v, n) for v in (I_b, I_w, I_c, rho_b, rho_w)]
        sd = _stds(sd, n)
        if (alpha0 is None) != (g0 is None):
            raise ValueError("pass alpha0 and g0 together, or neither")
        guess = [None, None] if alpha0 is None or g0 is None else [_f64(alpha0, n), _f64(g0, n)]
        if alpha0 is None and self._table is None:
            raise ValueError("this solver has no inverse table: pass alpha0 and g0")
        block, out = _fit_outputs(n, block)
        if alpha0 is None and threads > 1:
            steps = _library().tm_fit_thicknesses(1, self._grid_ref, self._table_ref, self._options(options), n,
                                                  *(_addr(a) for a in args), None if sd is None else _addr(sd),
                                                  0.0, 0.0, 0.0, _addr(block), None, _thread_count(threads))
        else:
            steps = _library().tm_fit(self._grid_ref, self._table_ref if alpha0 is None else None,
                                      self._options(options), n, *(_addr(a) for a in args),
                                      None if sd is None else _addr(sd),
                                      *(None if v is None else _addr(v) for v in guess), _addr(block))
        _check(steps)
        out["steps"] = int(steps)
        return out

    def fit_guessed(self, I_b: np.ndarray, I_w: ArrayLike, I_c: ArrayLike, rho_b: ArrayLike, rho_w: ArrayLike,
                    guess: Callable[[np.ndarray], ArrayLike], log_sigma_range: tuple[float, float], *,
                    sd: ArrayLike | None = None, block: np.ndarray | None = None, **options: Any) -> dict[str, Any]:
        """fit() with the initial (α, g) from guess(features) → (n, 2), e.g. the MLP: the bins are
        prepared once (invert.h `tm_fit_prepare`, which also writes the features, mlp.features with
        ln σt clamped to log_sigma_range), then solved from that guess (`tm_fit_solve`; where the
        guess is not finite, from the table's)."""
        n = len(I_b)
        args = [_f64(v, n) for v in (I_b, I_w, I_c, rho_b, rho_w)]
        sd = _stds(sd, n)
        block, out = _fit_outputs(n, block)
        scratch = np.empty(_library().tm_fit_scratch_size(n), dtype=np.uint8)
        features = np.empty((n, 5), dtype=np.float32)
        opts = self._options(options)
        _library().tm_fit_prepare(self._grid_ref, opts, n, *(_addr(a) for a in args), None if sd is None else _addr(sd),
                            _addr(scratch), _addr(block),
                            *map(float, log_sigma_range), _addr(features))
        guessed = np.asarray(guess(features))
        if guessed.shape != (n, 2):
            raise ValueError(f"the guess must be (n, 2) = ({n}, 2), got {guessed.shape}")
        alpha0, g0 = _f64(guessed[:, 0], n), _f64(guessed[:, 1], n)
        steps = _library().tm_fit_solve(self._grid_ref, self._table_ref, opts, n, _addr(alpha0), _addr(g0),
                                        _addr(scratch), _addr(block))
        _check(steps)
        out["steps"] = int(steps)
        out["features"] = features
        return out


_SIDE_BY_SIDE: dict[tuple[int, ...], tuple[list[Any], list[_FitOptionsC], tuple[Any, Any, Any]]] = {}


def _side_by_side(solvers: list[NativeSolver], options: list[_FitOptionsC]) -> tuple[Any, Any, Any]:
    """The solvers' grids, tables and the options as tm_fit_thicknesses takes them: k structs side by side
    (ctypes arrays of copies, which point into the solvers' arrays). Built once per set (building them
    costs a tenth of a small fit's glue); a set is found by its members' ids and taken only while each
    member is still that one (a solver that is gone can have passed its id on: its copies are not read)."""
    key = tuple(map(id, solvers)) + tuple(map(id, options))
    hit = _SIDE_BY_SIDE.get(key)
    if hit is not None and all(ref() is s for ref, s in zip(hit[0], solvers, strict=True)) \
            and all(a is b for a, b in zip(hit[1], options, strict=True)):
        return hit[2]
    k = len(solvers)
    tables = [s._table for s in solvers if s._table is not None]
    if len(tables) != k:
        raise ValueError("every thickness's solver needs its inverse table")
    arrays = ((_ForwardGridC * k)(*(s._grid for s in solvers)), (_InverseTableC * k)(*tables),
              (_FitOptionsC * k)(*options))
    if len(_SIDE_BY_SIDE) >= 64:  # a caller sweeping parameters: keep it bounded
        _SIDE_BY_SIDE.clear()
    _SIDE_BY_SIDE[key] = ([weakref.ref(s) for s in solvers], list(options), arrays)
    return arrays


def fit_thicknesses(solvers: list[NativeSolver], I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray,
                    rho_b: np.ndarray, rho_w: np.ndarray, *, sd: ArrayLike | None, options: list[dict[str, Any]],
                    underdetermined_std: tuple[float, float], disagree_sigmas: float, threads: int = 1
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """k thicknesses of the same n bins in one call (invert.h `tm_fit_thicknesses`): thickness j fitted as
    solvers[j].fit(row j of the (k, n) inputs, sd=sd[j], **options[j]) fits it (from its table's guess),
    then the k fits combined as combine() combines them. sd: the intensities' stds (k, n, 3), or None.
    threads: up to this many threads share the bins out, in parts (the results are the same for any count).
    Returns (the k fits' output blocks (k, rows, n), the combined block (rows, n), the Newton steps)."""
    k = len(solvers)
    if k < 1 or len(options) != k:
        raise ValueError("give one solver and one set of options per thickness")
    inputs = [np.ascontiguousarray(x, dtype=np.float64) for x in (I_b, I_w, I_c, rho_b, rho_w)]
    n = inputs[0].shape[-1]
    if any(x.shape != (k, n) for x in inputs):
        raise ValueError(f"the inputs must be ({k}, n), got {[x.shape for x in inputs]}")
    if sd is not None:
        sd = np.ascontiguousarray(sd, dtype=np.float64)
        if sd.shape != (k, n, 3):
            raise ValueError(f"the intensities' stds must be (k, n, 3) = ({k}, {n}, 3), got {sd.shape}")
    grids, tables, opts = _side_by_side(solvers, [s.options_struct(o) for s, o in zip(solvers, options, strict=True)])
    fits = np.empty((k, len(_OUTPUT_ROWS), n))
    combined = np.empty((len(_OUTPUT_ROWS), n))
    steps = _library().tm_fit_thicknesses(k, grids, tables, opts, n, *(_addr(x) for x in inputs),
                                          None if sd is None else _addr(sd), *underdetermined_std, disagree_sigmas,
                                          _addr(fits), _addr(combined), _thread_count(threads))
    _check(steps)
    return fits, combined, int(steps)


def expect_fit(k: int, n: int, threads: int) -> None:
    """A fit_thicknesses (or a fit from the table's guess) of k thicknesses of n bins in `threads` threads is to
    come: `tm_expect_fit` wakes the helpers it will use, to wait for it awake (a millisecond at most)."""
    _library().tm_expect_fit(k, n, _thread_count(threads))


def _thread_count(threads: int) -> int:
    """A thread count as the C int takes it (the library uses at most as many as it has helpers and parts)"""
    return max(1, min(int(threads), 1 << 16))


def threads_from_environment() -> int | None:
    """TRIMETER_FIT_THREADS: how many threads a fit shares its bins out to (unset or empty: None)."""
    value = os.environ.get("TRIMETER_FIT_THREADS", "").strip()
    if not value:
        return None
    if not value.isdigit() or int(value) < 1:
        raise NativeKernelError(f"TRIMETER_FIT_THREADS must be a whole number ≥ 1, not {value!r}")
    return int(value)


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity, where the OS has one; else all of them)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity API (macOS)
        return os.cpu_count() or 1


def _fit_outputs(n: int, block: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """tm_fit's output block (rows invert_h.OUTPUT_ROWS; flags int64): one allocation, one address (or
    the caller's `block`, checked); and the FitResult columns as its rows."""
    if block is None:
        block = np.empty((len(_OUTPUT_ROWS), n))
    elif block.shape != (len(_OUTPUT_ROWS), n) or block.dtype != np.float64 or not block.flags.c_contiguous \
            or not block.flags.writeable:
        raise ValueError(f"the output block must be a writeable C-contiguous float64 array of shape "
                         f"({len(_OUTPUT_ROWS)}, {n}), got {block.dtype} {block.shape}")
    out = dict(zip(_OUTPUT_ROWS, block, strict=True))
    out["flags"] = out["flags"].view(np.int64)
    return block, out


def _fit_options(*, noise_rel: float, noise_abs: float, mc_stderr: float, ic_floor: float, alpha_min_g: float,
                 input_tolerance: float, ref_rho: tuple[float, float], t_max: float, t_valid: float, iterations: int,
                 step_tol: float, step_tol_std: float, underdetermined_std: tuple[float, float],
                 thickness_rel_std: float, inscatter_rel_std: float,
                 std_check: tuple[float, float, float, float]) -> _FitOptionsC:
    """std_check: (α std, g std, σs, tolerance) of the STD_APPROXIMATE check (finish.STD_CHECK_*)."""
    return _FitOptionsC(noise_rel, noise_abs, mc_stderr, ic_floor, alpha_min_g, input_tolerance, *ref_rho, t_max,
                        t_valid, step_tol, step_tol_std, *underdetermined_std, thickness_rel_std, inscatter_rel_std,
                        *std_check, iterations)


def _stds(sd: ArrayLike | None, n: int) -> np.ndarray | None:
    """The intensities' stds as the C side reads them (n × 3, contiguous), or None."""
    if sd is None:
        return None
    sd = np.ascontiguousarray(sd, dtype=np.float64)
    if sd.shape != (n, 3):
        raise ValueError(f"the intensities' stds must be (n, 3) = ({n}, 3), got {sd.shape}")
    return sd


CACHE_LINE = 64


def _cache_aligned(x: ArrayLike) -> np.ndarray:
    """A C-ordered float64 copy of x starting on a cache line: a forward cell's polynomial (24 values,
    three lines) then spans three lines, not four, and the three the kernel prefetches are all of it."""
    a = np.asarray(x, dtype=np.float64)
    raw = np.empty(a.nbytes + CACHE_LINE, dtype=np.uint8)
    start = -raw.ctypes.data % CACHE_LINE
    out = raw[start:start + a.nbytes].view(np.float64).reshape(a.shape)
    out[...] = a
    return out


def _uniform_step(axis: np.ndarray) -> float:
    """1 / the step of an evenly spaced axis (the C side then finds cells without a search), else 0.
    "Evenly" to 1e-4: the stored axes are float32, and the C side corrects the estimated index by
    walking, so this only decides speed, never the cell."""
    d = np.diff(axis)
    return float(1.0 / d.mean()) if len(d) and np.all(np.abs(d - d.mean()) <= 1e-4 * abs(d.mean())) else 0.0


# At most this many buckets in an axis's cell index (tm_forward_grid's alpha_index): 8 KB, a quarter of
# a core's L1 data cache.
CELL_INDEX_MAX = 4096


def _cell_index(axis: np.ndarray) -> tuple[np.ndarray | None, float]:
    """An axis's cell index for the C side's search (invert.h, alpha_index): buckets of equal width from
    its first node, each holding the cell of its start; enough of them (up to CELL_INDEX_MAX) that the
    narrowest cell spans two. (None, 0) for an axis the C side searches as well without one."""
    n = len(axis)
    span = float(axis[-1] - axis[0])
    if n < 4 or n - 2 > np.iinfo(np.uint16).max or not span > 0:
        return None, 0.0
    narrowest = float(np.diff(axis).min())
    buckets = CELL_INDEX_MAX if not narrowest > 0 else int(min(CELL_INDEX_MAX, max(n, np.ceil(2 * span / narrowest))))
    scale = buckets / span
    starts = axis[0] + np.arange(buckets) / scale
    cells = np.clip(np.searchsorted(axis, starts, side="right") - 1, 0, n - 2)
    return np.ascontiguousarray(cells, dtype=np.uint16), scale


def _check(rc: int) -> None:
    if rc == -2:
        raise MemoryError("native kernel: out of memory for its scratch arrays")
    if rc < 0:
        raise ValueError("native kernel refused the grid (fewer than 2 nodes on an axis, or table/grid mismatch)")


def propagate(J: np.ndarray, sigma_I: np.ndarray,
              sigma_t_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """(std α, std σt, std g) — ForwardGrid.propagate in C."""
    n = len(J)
    J = np.ascontiguousarray(J, dtype=np.float64)
    sigma_I = np.ascontiguousarray(sigma_I, dtype=np.float64)
    extra = None if sigma_t_var is None else _f64(sigma_t_var, n)
    out = [np.empty(n) for _ in range(3)]
    _library().tm_propagate(n, _addr(J), _addr(sigma_I), None if extra is None else _addr(extra),
                            *(_addr(o) for o in out))
    return tuple(out)


def combine(fits: np.ndarray, underdetermined_std: tuple[float, float], disagree_sigmas: float) -> np.ndarray:
    """tm_combine: several thicknesses' fits (k, rows, n), laid out as tm_fit's output blocks, into one
    (rows, n) block — trimeter.inversion.finish.combine in C, bit for bit."""
    k, _, n = fits.shape
    fits = np.ascontiguousarray(fits, dtype=np.float64)
    out = np.empty(fits.shape[1:])
    _library().tm_combine(k, n, _addr(fits), *underdetermined_std, disagree_sigmas, _addr(out))
    return out


class TableFitter:
    """The fit from a self-sufficient device table (.tlut v2) alone, in C (fit_core/table_fit.c: the
    source the firmware links as tr_fit_bins, here in double precision): the lut fit with fit()'s defaults, bin by
    bin, from the table's bytes and nothing else. Returns α, σt, g and the FitFlag bits (NaN where a
    bin is unusable); STD_APPROXIMATE is never set (the fit returns no stds: trimeter.inversion.table_std adds
    them on the host from the same table).

    table_bytes: the file's bytes; its CRC-32 is checked here, every other field by the C reader.
    library: another build of the kernel (a path; e.g. the single-precision one a test compiles),
    else the package's library."""

    def __init__(self, table_bytes: bytes, library: str | Path | None = None) -> None:
        from trimeter.errors import MapFileError

        lib = _LIB if library is None else _bind(ctypes.CDLL(str(library)))
        if lib is None:
            raise NativeKernelError(f"the table fit needs the compiled kernel: {_STATUS}")
        data = bytes(table_bytes)
        if len(data) < 8 or zlib.crc32(data[:-4]) != int.from_bytes(data[-4:], "little"):
            raise MapFileError("device table: crc32 mismatch or truncated: the table is corrupt")
        # a fresh numpy buffer: aligned, as the C reader reads its float sections in place
        self._table = np.frombuffer(data, dtype=np.uint8).copy()
        self._fit = lib.tm_table_fit
        if self._fit(_addr(self._table), len(data), None, 0, None, None) != 0:
            raise MapFileError("device table: not a format-2 table the C fit reads (magic, version, sizes, "
                               "section directory, axes or scales)")
        self.reference_rhos = tuple(float(x) for x in np.frombuffer(data, dtype="<f4", count=2, offset=92))

    def fit(self, I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike, rho_b: ArrayLike | None = None,
            rho_w: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(α, σt [1/mm], g, flags (int64)) per bin; rho_b, rho_w default to the table's reference
        backgrounds. Arrays broadcast against each other."""
        rb, rw = self.reference_rhos
        rho_b, rho_w = rb if rho_b is None else rho_b, rw if rho_w is None else rho_w
        columns = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (I_b, I_w, I_c, rho_b, rho_w)))
        shape = columns[0].shape
        inputs = np.ascontiguousarray(np.stack([c.ravel() for c in columns], axis=-1))
        n = len(inputs)
        out = np.empty((n, 3))
        flags = np.empty(n, dtype=np.int64)
        if n and self._fit(_addr(self._table), len(self._table), _addr(inputs), n, _addr(out), _addr(flags)) != 0:
            raise NativeKernelError("the table fit refused a table it took before")  # cannot happen: no state
        alpha, sigma_t, g = (np.array(out[:, k]).reshape(shape) for k in range(3))
        return alpha, sigma_t, g, flags.reshape(shape)


class TableModel:
    """A device table's compact forward model evaluated in C (tm_table_eval: tr_compact_eval, what the table
    fit's polish evaluates), in place of trimeter.model.compact.CompactForward.evaluate where the kernel is
    loaded: the host's stds of the table fit take their Jacobian from it (trimeter.inversion.table_std).

    table_bytes: a table's bytes as DeviceTable.to_bytes gives them (checked by the C reader here)."""

    def __init__(self, table_bytes: bytes) -> None:
        from trimeter.errors import MapFileError

        self._table = np.frombuffer(bytes(table_bytes), dtype=np.uint8).copy()  # aligned, as the reader wants
        self._eval = _library().tm_table_eval
        if self._eval(_addr(self._table), len(self._table), 0, None, None, None, None) != 0:
            raise MapFileError("device table: not a format-2 table the C reader reads")

    def evaluate(self, alpha: ArrayLike, log_sigma_t: ArrayLike, g: ArrayLike
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """As CompactForward.evaluate: A, B, C (3, N) and their derivatives in α, ln σt and g, each (3, N),
        at points clamped to the map's box (a NaN coordinate reads as the box's lower end)."""
        a, s, g_ = (np.ascontiguousarray(np.ravel(x), dtype=np.float64)
                    for x in np.broadcast_arrays(*(np.atleast_1d(np.asarray(x, dtype=np.float64))
                                                   for x in (alpha, log_sigma_t, g))))
        n = len(a)
        out = np.empty((n, 12))
        if n and self._eval(_addr(self._table), len(self._table), n, _addr(a), _addr(s), _addr(g_), _addr(out)) != 0:
            raise NativeKernelError("the table's model refused a table it took before")  # cannot happen: no state
        t = out.T
        return t[0:3], t[3:6], t[6:9], t[9:12]


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    """`lib` with the table fit's prototype, refused unless built from this invert.h."""
    lib.tm_abi_hash.restype = ctypes.c_uint64
    if lib.tm_abi_hash() != ABI_HASH:
        raise NativeKernelError(f"{lib._name} was built for another invert.h")
    function: Any = lib.tm_table_fit  # the prototype comes from the generated table, typed as data there
    function.restype, function.argtypes = invert_h.FUNCTIONS["tm_table_fit"]
    return lib
