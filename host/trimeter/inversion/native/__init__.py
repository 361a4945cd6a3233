"""The compiled inversion kernel (invert.c next to this file), bound with ctypes.

`make native` (part of `make setup`, so of `make test` and `make demo`) compiles it into
libtrimeter_invert.so here. Without it — no C compiler, a plain `pip install`, or
TRIMETER_NATIVE=0 in the environment — every caller falls back to the numpy kernel
(trimeter.inversion.kernel), which is the reference the C code is tested against; results agree to
~1e-9 (flags bit for bit), only the speed differs. `status()` says which one runs (the benchmark
prints it).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

import numpy as np

LIBRARY = Path(__file__).with_name("libtrimeter_invert.so")
ABI_VERSION = 15

_double_p = ctypes.POINTER(ctypes.c_double)


class _ForwardGridC(ctypes.Structure):
    _fields_ = [("na", ctypes.c_int32), ("ns", ctypes.c_int32), ("ng", ctypes.c_int32),
                ("alpha", _double_p), ("log_sigma_t", _double_p), ("g", _double_p),
                ("inv_da", _double_p), ("inv_ds", _double_p), ("inv_dg", _double_p),
                ("poly", _double_p),
                ("alpha_lo", ctypes.c_double), ("alpha_hi", ctypes.c_double),
                ("g_lo", ctypes.c_double), ("g_hi", ctypes.c_double),
                ("thickness_mm", ctypes.c_double), ("stack_a", ctypes.c_double), ("stack_b", ctypes.c_double),
                ("uniform_ds", ctypes.c_double),
                # in-scattering into I_c on this grid's α and g nodes (ForwardGrid.inscatter_grid), or NULL
                ("in_nt", ctypes.c_int32), ("inscatter_L", _double_p), ("in_inv_dt", ctypes.c_double),
                ("in_tau_max", ctypes.c_double),
                # the map's error variances of I_b, I_w on the grid's nodes (ForwardGrid.model_var), or NULL
                ("model_var", _double_p)]


class _InverseTableC(ctypes.Structure):
    _fields_ = [("ns", ctypes.c_int32), ("ny", ctypes.c_int32), ("nx", ctypes.c_int32),
                ("cells", _double_p), ("frame", _double_p), ("log_sigma_t", _double_p), ("inv_ds", _double_p),
                ("uniform_ds", ctypes.c_double)]


class _FitOptionsC(ctypes.Structure):
    _fields_ = [(name, ctypes.c_double) for name in (
        "noise_rel", "noise_abs", "mc_stderr", "ic_floor", "alpha_min_g", "input_tolerance", "ref_rho_b",
        "ref_rho_w", "t_max", "t_valid", "step_tol", "step_tol_std", "underdetermined_alpha_std",
        "underdetermined_g_std", "thickness_rel_std", "inscatter_rel_std", "std_check_alpha", "std_check_g",
        "std_check_sigmas", "std_check_tol")] + [
        ("iterations", ctypes.c_int32)]


# The rows of tm_fit's output block (invert.c tm_fit_outputs), in order; flags are int64.
_OUTPUT_ROWS = ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "sigma_t_beer", "flags",
                "conditioning_alpha_std", "conditioning_g_std")


# A polish step at most this fraction of the one before it also ends a bin's polish when the next
# step, extrapolated at that rate, would be below κ of the noise std (kernel.step_is_small, invert.c
# STEP_RATIO; the library is refused if its value differs).
STEP_RATIO = 0.25
# The in-scattering correction takes L = ln(1 + r) a second time, at the moved σt, only where the first
# is above this (ForwardGrid.correct_inscatter, invert.c INSCATTER_ONCE; checked like STEP_RATIO).
INSCATTER_ONCE = 1e-3

# tm_flag_bits order; the library is refused if its bits differ from FitFlag's
_FLAG_ORDER = ("NONFINITE_INPUT", "NEGATIVE_INPUT", "ABOVE_ONE", "BLACK_NOT_BELOW_WHITE", "IC_BELOW_FLOOR",
               "G_UNDEFINED", "OUTSIDE_MAP", "NOT_CONVERGED", "BAD_BACKGROUND", "UNDERDETERMINED", "STD_APPROXIMATE")


def _load():
    if os.environ.get("TRIMETER_NATIVE", "1") == "0":
        return None, "disabled by TRIMETER_NATIVE=0"
    if not LIBRARY.is_file():
        return None, f"{LIBRARY.name} not built (run `make native`)"
    try:
        lib = ctypes.CDLL(str(LIBRARY))
    except OSError as exc:
        return None, f"{LIBRARY.name} does not load ({exc})"
    if lib.tm_abi_version() != ABI_VERSION:
        return None, f"{LIBRARY.name} is stale (ABI {lib.tm_abi_version()}, expected {ABI_VERSION}; run `make native`)"
    size_t, vp = ctypes.c_size_t, ctypes.c_void_p  # arrays go in as raw addresses (see _addr)
    lib.tm_solve_alpha_g.restype = ctypes.c_int
    lib.tm_solve_alpha_g.argtypes = [ctypes.POINTER(_ForwardGridC), ctypes.POINTER(_InverseTableC), size_t,
                                     vp, vp, vp, vp, vp, ctypes.c_int, ctypes.c_double, vp, vp, vp, vp, vp]
    lib.tm_propagate.restype = None
    lib.tm_propagate.argtypes = [size_t, vp, vp, vp, vp, vp, vp]
    lib.tm_fit_scratch_size.restype = size_t
    lib.tm_fit_scratch_size.argtypes = [size_t]
    lib.tm_fit_prepare.restype = None
    lib.tm_fit_prepare.argtypes = [ctypes.POINTER(_ForwardGridC), ctypes.POINTER(_FitOptionsC), size_t,
                                   vp, vp, vp, vp, vp, vp, vp, vp, ctypes.c_double,
                                   ctypes.c_double, vp]
    lib.tm_fit_solve.restype = ctypes.c_longlong
    lib.tm_fit_solve.argtypes = [ctypes.POINTER(_ForwardGridC), ctypes.POINTER(_InverseTableC),
                                 ctypes.POINTER(_FitOptionsC), size_t, vp, vp, vp, vp]
    lib.tm_fit.restype = ctypes.c_longlong
    lib.tm_fit.argtypes = [ctypes.POINTER(_ForwardGridC), ctypes.POINTER(_InverseTableC),
                           ctypes.POINTER(_FitOptionsC), size_t, vp, vp, vp, vp, vp, vp, vp, vp,
                           vp]
    from trimeter.inversion.flags import FitFlag

    bits = (ctypes.c_int64 * len(_FLAG_ORDER))()
    lib.tm_flag_bits(bits)
    if list(bits) != [int(FitFlag[name]) for name in _FLAG_ORDER]:
        return None, f"{LIBRARY.name} declares other flag bits than trimeter.inversion.flags (run `make native`)"
    lib.tm_set_simd.restype = ctypes.c_int
    lib.tm_set_simd.argtypes = [ctypes.c_int]
    lib.tm_step_ratio.restype = ctypes.c_double
    if lib.tm_step_ratio() != STEP_RATIO:
        return None, f"{LIBRARY.name} stops the polish at another step ratio than trimeter (run `make native`)"
    lib.tm_inscatter_once.restype = ctypes.c_double
    if lib.tm_inscatter_once() != INSCATTER_ONCE:
        return None, f"{LIBRARY.name} corrects in-scattering otherwise than trimeter (run `make native`)"
    lanes = "AVX2, 4 bins per Newton step" if lib.tm_set_simd(1) else "scalar"
    return lib, f"compiled ({LIBRARY.name}, {lanes})"


_LIB, _STATUS = _load()


def set_simd(enabled: bool) -> bool:
    """Let the polish take four bins per Newton step with AVX2 (the default where the CPU has it) or
    only the scalar loop: the results are bit for bit the same (tests compare them). Returns whether
    the four-lane step is in use."""
    return bool(_LIB.tm_set_simd(1 if enabled else 0)) if _LIB is not None else False


def available() -> bool:
    return _LIB is not None


def status() -> str:
    """'compiled (…)' or why the numpy kernel runs instead."""
    return _STATUS


def _ptr(a: np.ndarray):
    return a.ctypes.data_as(_double_p)


def _addr(a: np.ndarray) -> int:
    """The data address of a contiguous array. Through ctypes' buffer protocol (0.2 µs) when the
    array is writable, else its __array_interface__ (0.8 µs; read-only or empty arrays): ~12 of
    these per fit, against 20-30 µs of Python around a ~0.2 ms kernel call."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):
        return a.__array_interface__["data"][0]


def _f64(x, n) -> np.ndarray:
    """A contiguous float64 array of n values (broadcast scalars), as the C loop reads it."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    return a if a.shape == (n,) else np.ascontiguousarray(np.broadcast_to(a, (n,)))


class NativeSolver:
    """One forward grid (and optionally one inverse table) handed to C once; arrays kept alive here."""

    def __init__(self, grid, inverse_cells: np.ndarray | None = None, inverse_frame: np.ndarray | None = None,
                 inverse_shape: tuple[int, int, int] | None = None, inverse_log_sigma_t: np.ndarray | None = None):
        """grid: the forward grid the polish runs on; inverse_*: the table's guess slices, at its own σt
        nodes inverse_log_sigma_t (the forward grid may be finer in σt)."""
        keep = {name: np.ascontiguousarray(value, dtype=np.float64) for name, value in (
            ("alpha", grid.alpha), ("log_sigma_t", grid.log_sigma_t), ("g", grid.g), ("inv_da", grid._inv_da),
            ("inv_ds", grid._inv_ds), ("inv_dg", grid._inv_dg), ("poly", grid._poly))}
        na, ns, ng = grid.shape
        self._grid = _ForwardGridC(na, ns, ng, *(_ptr(keep[k]) for k in ("alpha", "log_sigma_t", "g", "inv_da",
                                                                           "inv_ds", "inv_dg", "poly")),
                                   *grid.alpha_range, *grid.g_range, grid.thickness_mm, *grid.stack_constants[:2],
                                   _uniform_step(keep["log_sigma_t"]))
        if grid.inscatter_grid is not None:
            keep["inscatter_L"], inv_dt, tau_max = grid.inscatter_grid
            self._grid.in_nt = keep["inscatter_L"].shape[1]
            self._grid.inscatter_L = _ptr(keep["inscatter_L"])
            self._grid.in_inv_dt, self._grid.in_tau_max = inv_dt, tau_max
        if grid.model_var is not None:
            keep["model_var"] = np.ascontiguousarray(grid.model_var, dtype=np.float64)
            self._grid.model_var = _ptr(keep["model_var"])
        self._table = None
        if inverse_cells is not None:
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

    def solve(self, I_b, I_w, log_sigma_t, rho_b, rho_w, iterations, alpha0=None, g0=None, step_tol=0.0,
              step_var=None):
        """(α, g, residual, J (n, 3, 3)) as ForwardGrid.solve_alpha_g returns them. ln σt is clamped to
        the grid in C (NaN → lowest node). Initial guess from the inverse table, or alpha0/g0 when
        given (then the table is not used)."""
        n = len(log_sigma_t)
        args = [_f64(v, n) for v in (I_b, I_w, log_sigma_t, rho_b, rho_w)]
        use_table = alpha0 is None
        if use_table and self._table is None:
            raise ValueError("this solver has no inverse table: pass alpha0 and g0")
        alpha = np.zeros(n) if use_table else _f64(alpha0, n).copy()
        g = np.zeros(n) if use_table else _f64(g0, n).copy()
        residual = np.empty(n)
        J = np.empty((n, 3, 3))
        step_var = None if step_var is None else _f64(step_var, n)  # kept alive through the call
        rc = _LIB.tm_solve_alpha_g(self._grid_ref, self._table_ref if use_table else None, n,
                                   *(_addr(a) for a in args), int(iterations), float(step_tol),
                                   None if step_var is None else _addr(step_var), _addr(alpha),
                                   _addr(g), _addr(residual), _addr(J))
        _check(rc)
        return alpha, g, residual, J

    def _options(self, options: dict):
        """The C options struct for fit()'s options, built once per distinct set: a ctypes struct
        costs ~1 µs to build warm, ~10 µs right after the caches were flushed (one press-button
        measurement), where a dict lookup costs neither."""
        key = tuple(options.items())
        ref = self._fit_options.get(key)
        if ref is None:
            if len(self._fit_options) >= 64:  # a caller sweeping parameters: keep it bounded
                self._fit_options.clear()
            ref = self._fit_options[key] = ctypes.byref(_fit_options(**options))
        return ref

    def fit(self, I_b, I_w, I_c, rho_b, rho_w, *, sd=None, alpha0=None, g0=None, **options):
        """One thickness's whole fit in one call (invert.c `tm_fit`, api._fit_one's reference path
        operation for operation): a dict of the FitResult columns and `steps`, the Newton steps taken.
        sd: the intensities' stds (n, 3), or None for the noise model of `options`
        (trimeter.inversion.api.native_options(…))."""
        n = len(I_b)
        args = [_f64(v, n) for v in (I_b, I_w, I_c, rho_b, rho_w)]
        sd = _stds(sd, n)
        guess = [None, None] if alpha0 is None else [_f64(alpha0, n), _f64(g0, n)]
        if alpha0 is None and self._table is None:
            raise ValueError("this solver has no inverse table: pass alpha0 and g0")
        block, out = _fit_outputs(n)
        steps = _LIB.tm_fit(self._grid_ref, self._table_ref if alpha0 is None else None, self._options(options), n,
                            *(_addr(a) for a in args), None if sd is None else _addr(sd),
                            *(None if v is None else _addr(v) for v in guess), _addr(block))
        _check(steps)
        out["steps"] = int(steps)
        return out

    def fit_guessed(self, I_b, I_w, I_c, rho_b, rho_w, guess, log_sigma_range, *, sd=None, **options):
        """fit() with the initial (α, g) from guess(features) → (n, 2), e.g. the MLP: the bins are
        prepared once (invert.c `tm_fit_prepare`, which also writes the features, mlp.features with
        ln σt clamped to log_sigma_range), then solved from that guess (`tm_fit_solve`; where the
        guess is not finite, from the table's)."""
        n = len(I_b)
        args = [_f64(v, n) for v in (I_b, I_w, I_c, rho_b, rho_w)]
        sd = _stds(sd, n)
        block, out = _fit_outputs(n)
        scratch = np.empty(_LIB.tm_fit_scratch_size(n), dtype=np.uint8)
        features = np.empty((n, 5), dtype=np.float32)
        opts = self._options(options)
        _LIB.tm_fit_prepare(self._grid_ref, opts, n, *(_addr(a) for a in args), None if sd is None else _addr(sd),
                            _addr(scratch), _addr(block),
                            *map(float, log_sigma_range), _addr(features))
        guessed = np.asarray(guess(features))
        if guessed.shape != (n, 2):
            raise ValueError(f"the guess must be (n, 2) = ({n}, 2), got {guessed.shape}")
        alpha0, g0 = _f64(guessed[:, 0], n), _f64(guessed[:, 1], n)
        steps = _LIB.tm_fit_solve(self._grid_ref, self._table_ref, opts, n, _addr(alpha0), _addr(g0), _addr(scratch),
                                  _addr(block))
        _check(steps)
        out["steps"] = int(steps)
        out["features"] = features
        return out


def _fit_outputs(n: int):
    """tm_fit's output block (rows _OUTPUT_ROWS; flags int64 in the last): one allocation, one
    address; and the FitResult columns as its rows."""
    block = np.empty((len(_OUTPUT_ROWS), n))
    out = dict(zip(_OUTPUT_ROWS, block, strict=True))
    out["flags"] = out["flags"].view(np.int64)
    return block, out


def _fit_options(*, noise_rel, noise_abs, mc_stderr, ic_floor, alpha_min_g, input_tolerance, ref_rho, t_max, t_valid,
                 iterations, step_tol, step_tol_std, underdetermined_std, thickness_rel_std,
                 inscatter_rel_std, std_check) -> _FitOptionsC:
    """std_check: (α std, g std, σs, tolerance) of the STD_APPROXIMATE check (api.STD_CHECK_*)."""
    return _FitOptionsC(noise_rel, noise_abs, mc_stderr, ic_floor, alpha_min_g, input_tolerance, *ref_rho, t_max,
                        t_valid, step_tol, step_tol_std, *underdetermined_std, thickness_rel_std, inscatter_rel_std,
                        *std_check, iterations)


def _stds(sd, n):
    """The intensities' stds as the C side reads them (n × 3, contiguous), or None."""
    if sd is None:
        return None
    sd = np.ascontiguousarray(sd, dtype=np.float64)
    if sd.shape != (n, 3):
        raise ValueError(f"the intensities' stds must be (n, 3) = ({n}, 3), got {sd.shape}")
    return sd


def _uniform_step(axis: np.ndarray) -> float:
    """1 / the step of an evenly spaced axis (the C side then finds cells without a search), else 0.
    "Evenly" to 1e-4: the stored axes are float32, and the C side corrects the estimated index by
    walking, so this only decides speed, never the cell."""
    d = np.diff(axis)
    return float(1.0 / d.mean()) if len(d) and np.all(np.abs(d - d.mean()) <= 1e-4 * abs(d.mean())) else 0.0


def _check(rc: int) -> None:
    if rc == -2:
        raise MemoryError("native kernel: out of memory for its scratch arrays")
    if rc < 0:
        raise ValueError("native kernel refused the grid (fewer than 2 nodes on an axis, or table/grid mismatch)")


def propagate(J: np.ndarray, sigma_I: np.ndarray, sigma_t_var: np.ndarray | None = None):
    """(std α, std σt, std g) — ForwardGrid.propagate in C."""
    n = len(J)
    J = np.ascontiguousarray(J, dtype=np.float64)
    sigma_I = np.ascontiguousarray(sigma_I, dtype=np.float64)
    extra = None if sigma_t_var is None else _f64(sigma_t_var, n)
    out = [np.empty(n) for _ in range(3)]
    _LIB.tm_propagate(n, _addr(J), _addr(sigma_I), None if extra is None else _addr(extra), *(_addr(o) for o in out))
    return tuple(out)
