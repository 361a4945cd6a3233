"""One interface to the solve, in numpy or in C: chosen once (default_kernel) and handed to the fit.

NumpyKernel is the reference (trimeter.inversion.newton); NativeKernel runs the same algorithm in the
compiled library (trimeter.inversion.native, tested to agree to ~1e-9, flags bit for bit) and also
fuses one thickness's whole fit into one call, and combines several thicknesses (bit for bit
finish.combine's), or fits and combines them all in one call. A method never asks which one it has.
"""

from __future__ import annotations

import weakref
from typing import Any, Protocol

import numpy as np

from trimeter.domain.parameters import FitResult
from trimeter.inversion import native, newton
from trimeter.inversion.native import invert_h
from trimeter.inversion.lut import TableInverter
from trimeter.model.grid import ForwardGrid, SigmaCell


_ROWS = invert_h.OUTPUT_ROWS  # the FitResult columns, in the order of tm_fit's output block
_CONDITIONING = {"conditioning_alpha_std": "alpha_std", "conditioning_g_std": "g_std"}


class Guesser(Protocol):
    """A per-bin initial (α, g) from the fit's features (trimeter.inversion.mlp.features), e.g. a network."""
    log_sigma_range: tuple[float, float]

    def run(self, x: np.ndarray) -> np.ndarray: ...

    def predict(self, I_b: np.ndarray, I_w: np.ndarray, sigma_t: np.ndarray, rho_b: np.ndarray,
                rho_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class Kernel(Protocol):
    name: str

    def expect_fit(self, k: int, n: int) -> None:
        """A fit of k thicknesses of n bins from the tables' guesses is on its way (the caller still checks its
        inputs): what it will run on gets ready meanwhile, where the kernel has anything to ready."""

    def solve_alpha_g(self, grid: ForwardGrid, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell, rho_b: np.ndarray,
                      rho_w: np.ndarray, alpha0: np.ndarray, g0: np.ndarray, *, iterations: int, step_tol: float = 0.0,
                      step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """(α, g, residual, J) polished from (alpha0, g0) (newton.solve_alpha_g)."""

    def invert(self, inverter: TableInverter, I_b: np.ndarray, I_w: np.ndarray, sigma_t: np.ndarray, rho_b: np.ndarray,
               rho_w: np.ndarray, *, iterations: int, step_tol: float = 0.0,
               step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """(α, g, residual, J) from the table's guess, polished on its grid."""

    def propagate(self, J: np.ndarray, sigma_I: np.ndarray,
                  sigma_t_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """First-order stds of (α, σt, g) (newton.propagate)."""

    def fused_fit(self, inverter: TableInverter, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
                  rho_w: np.ndarray, *, sd: Any, guesser: Guesser | None, options: dict[str, Any],
                  block: np.ndarray | None = None) -> dict[str, Any] | None:
        """One thickness's whole fit in one call (FitResult columns), or None where the kernel has no
        fused path and the fit runs its steps one by one. block: where to write it, one of
        output_blocks' (its columns are then views of it)."""

    def output_blocks(self, k: int, n: int) -> np.ndarray | None:
        """Room for k thicknesses' fused fits of n bins, laid out as combine reads them (None: the
        kernel has no such layout)."""

    def combine(self, results: list[FitResult], method: str, *, underdetermined_std: tuple[float, float],
                disagree_sigmas: float, blocks: np.ndarray | None = None) -> FitResult | None:
        """Several thicknesses' fits combined (finish.combine, whose thresholds are passed in), or None where
        the kernel has no such path and finish.combine runs. blocks: output_blocks' array where the results
        were fused into it, read as it is."""

    def fit_thicknesses(self, inverters: list[TableInverter], inputs: tuple[np.ndarray, ...], *, sd: np.ndarray | None,
                        options: list[dict[str, Any]], method: str, underdetermined_std: tuple[float, float],
                        disagree_sigmas: float) -> FitResult | None:
        """Several thicknesses of the same bins, each fitted from its table's guess as fused_fit fits it and
        then combined as combine() combines them, all in one call; or None where the kernel has no such
        path. inputs: I_b, I_w, I_c, ρ_b, ρ_w, each (k, n); sd: the intensities' stds (k, n, 3) or None."""


class NumpyKernel:
    name = "numpy"

    def expect_fit(self, k: int, n: int) -> None:
        pass

    def solve_alpha_g(self, grid: ForwardGrid, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell, rho_b: np.ndarray,
                      rho_w: np.ndarray, alpha0: np.ndarray, g0: np.ndarray, *, iterations: int, step_tol: float = 0.0,
                      step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        return newton.solve_alpha_g(grid, I_b, I_w, cell, rho_b, rho_w, alpha0, g0, iterations=max(int(iterations), 0),
                                    step_tol=step_tol, step_var=step_var)

    def invert(self, inverter: TableInverter, I_b: np.ndarray, I_w: np.ndarray, sigma_t: np.ndarray, rho_b: np.ndarray,
               rho_w: np.ndarray, *, iterations: int, step_tol: float = 0.0,
               step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        alpha, g = inverter.initial_guess(I_b, I_w, inverter.table_grid.sigma_cell(sigma_t))
        return self.solve_alpha_g(inverter.grid, I_b, I_w, inverter.grid.sigma_cell(sigma_t), rho_b, rho_w, alpha, g,
                                  iterations=iterations, step_tol=step_tol, step_var=step_var)

    def propagate(self, J: np.ndarray, sigma_I: np.ndarray,
                  sigma_t_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        return newton.propagate(J, sigma_I, sigma_t_var)

    def fused_fit(self, inverter: TableInverter, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
                  rho_w: np.ndarray, *, sd: Any, guesser: Guesser | None, options: dict[str, Any],
                  block: np.ndarray | None = None) -> dict[str, Any] | None:
        return None

    def output_blocks(self, k: int, n: int) -> np.ndarray | None:
        return None

    def combine(self, results: list[FitResult], method: str, *, underdetermined_std: tuple[float, float],
                disagree_sigmas: float, blocks: np.ndarray | None = None) -> FitResult | None:
        return None

    def fit_thicknesses(self, inverters: list[TableInverter], inputs: tuple[np.ndarray, ...], *, sd: np.ndarray | None,
                        options: list[dict[str, Any]], method: str, underdetermined_std: tuple[float, float],
                        disagree_sigmas: float) -> FitResult | None:
        return None


class NativeKernel:
    """The compiled kernel; one NativeSolver per grid or table inverter, made on first use and kept as
    long as the grid or inverter lives. threads: how many threads share out a fit's bins from the table's
    guess (None: TRIMETER_FIT_THREADS where set, e.g. 1 for a process among others that share the CPUs, else
    as many as the process may use CPUs, at each fit); the results are the same for any count."""
    name = "native"

    def __init__(self, threads: int | None = None) -> None:
        if not native.available():
            raise RuntimeError(f"the native kernel is not available: {native.status()}")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise ValueError(f"threads must be a whole number ≥ 1 or None, not {threads!r}")
        self.threads = native.threads_from_environment() if threads is None else threads
        self._solvers: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def fit_threads(self) -> int:
        """How many threads a fit from the table's guess uses now."""
        return self.threads or native.usable_cpus()

    def expect_fit(self, k: int, n: int) -> None:
        """The threads that will share the fit out are woken now: their CPUs may have gone idle, and
        waking one takes longer than checking the inputs does."""
        threads = self.fit_threads()
        if threads > 1:
            native.expect_fit(k, n, threads)

    def _grid_solver(self, grid: ForwardGrid) -> native.NativeSolver:
        solver = self._solvers.get(grid)
        if solver is None:
            solver = self._solvers[grid] = native.NativeSolver(grid)
        return solver

    def _table_solver(self, inverter: TableInverter) -> native.NativeSolver:
        solver = self._solvers.get(inverter)
        if solver is None:
            solver = self._solvers[inverter] = native.NativeSolver(inverter.grid, *inverter.inverse_cells)
        return solver

    def solve_alpha_g(self, grid: ForwardGrid, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell, rho_b: np.ndarray,
                      rho_w: np.ndarray, alpha0: np.ndarray, g0: np.ndarray, *, iterations: int, step_tol: float = 0.0,
                      step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        return self._grid_solver(grid).solve(I_b, I_w, cell.log_sigma_t, rho_b, rho_w, max(int(iterations), 0),
                                             alpha0, g0, step_tol=step_tol, step_var=step_var)

    def invert(self, inverter: TableInverter, I_b: np.ndarray, I_w: np.ndarray, sigma_t: np.ndarray, rho_b: np.ndarray,
               rho_w: np.ndarray, *, iterations: int, step_tol: float = 0.0,
               step_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        with np.errstate(divide="ignore", invalid="ignore"):
            log_sigma_t = np.log(sigma_t)  # C clamps ln σt to the grid itself
        return self._table_solver(inverter).solve(I_b, I_w, log_sigma_t, rho_b, rho_w, max(int(iterations), 0),
                                                  step_tol=step_tol, step_var=step_var)

    def propagate(self, J: np.ndarray, sigma_I: np.ndarray,
                  sigma_t_var: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        return native.propagate(J, sigma_I, sigma_t_var)

    def fused_fit(self, inverter: TableInverter, I_b: np.ndarray, I_w: np.ndarray, I_c: np.ndarray, rho_b: np.ndarray,
                  rho_w: np.ndarray, *, sd: Any, guesser: Guesser | None, options: dict[str, Any],
                  block: np.ndarray | None = None) -> dict[str, Any] | None:
        solver = self._table_solver(inverter)
        if guesser is None:
            out = solver.fit(I_b, I_w, I_c, rho_b, rho_w, sd=sd, block=block, threads=self.fit_threads(), **options)
        else:  # the guesser reads the features C prepares; tm_fit_solve clamps its guess to the map's box
            broken: list[int] = []

            def guess(features: np.ndarray) -> np.ndarray:
                y = np.asarray(guesser.run(features))
                broken.append(int(np.count_nonzero(~np.isfinite(y).all(axis=-1))))  # tm_fit_solve: the table's
                return y

            out = solver.fit_guessed(I_b, I_w, I_c, rho_b, rho_w, guess, guesser.log_sigma_range, sd=sd, block=block,
                                     **options)
            out.pop("features")
            out["guess_fallback_bins"] = sum(broken)
        out.pop("steps")
        return out

    def output_blocks(self, k: int, n: int) -> np.ndarray | None:
        return np.empty((k, len(_ROWS), n))

    def combine(self, results: list[FitResult], method: str, *, underdetermined_std: tuple[float, float],
                disagree_sigmas: float, blocks: np.ndarray | None = None) -> FitResult | None:
        """tm_combine over the fits' columns, laid out as tm_fit's output blocks, one per thickness:
        `blocks` where the fits were written there (their conditioning rows are then the stds where a
        result has none, as tm_fit writes them), else gathered from the results."""
        fits = blocks if blocks is not None else self._gathered(results)
        out = native.combine(fits, underdetermined_std, disagree_sigmas)
        columns = dict(zip(_ROWS, out, strict=True))
        columns["flags"] = columns["flags"].view(np.int64)
        return FitResult(**columns, method=method, per_thickness=results)

    def fit_thicknesses(self, inverters: list[TableInverter], inputs: tuple[np.ndarray, ...], *, sd: np.ndarray | None,
                        options: list[dict[str, Any]], method: str, underdetermined_std: tuple[float, float],
                        disagree_sigmas: float) -> FitResult | None:
        """tm_fit_thicknesses: the per-thickness results are views of its fits' blocks, as fused_fit's
        written into output_blocks' are; a thickness without stds of its own has no conditioning stds."""
        fits, combined, _ = native.fit_thicknesses([self._table_solver(t) for t in inverters], *inputs, sd=sd,
                                                   options=options, underdetermined_std=underdetermined_std,
                                                   disagree_sigmas=disagree_sigmas,
                                                   threads=self.fit_threads())
        return FitResult(**self._columns(combined), method=method,
                         per_thickness=[FitResult(**self._columns(block, own_conditioning=sd is not None),
                                                  method=method) for block in fits])

    @staticmethod
    def _columns(block: np.ndarray, own_conditioning: bool = True) -> dict[str, Any]:
        """An output block's rows as FitResult's columns (flags as int64)."""
        columns: dict[str, Any] = dict(zip(_ROWS, block, strict=True))
        columns["flags"] = block[_ROWS.index("flags")].view(np.int64)
        if not own_conditioning:  # the noise model's stds: the conditioning stds are the stds themselves
            columns["conditioning_alpha_std"] = columns["conditioning_g_std"] = None
        return columns

    @staticmethod
    def _gathered(results: list[FitResult]) -> np.ndarray:
        k, n = len(results), len(results[0])
        fits = np.empty((k, len(_ROWS), n))
        for block, result in zip(fits, results, strict=True):
            for row, name in zip(block, _ROWS, strict=True):
                column = getattr(result, name)
                if column is None:  # no conditioning stds of its own: its stds stand
                    column = getattr(result, _CONDITIONING[name])
                if name == "flags":
                    row.view(np.int64)[:] = column
                else:
                    row[:] = column
        return fits


_DEFAULT: list[Kernel] = []


def default_kernel() -> Kernel:
    """The compiled kernel where it is built, else numpy — chosen once per process, as TRIMETER_KERNEL
    asks (trimeter.inversion.native says out loud, once, why numpy runs when it was not asked for)."""
    if not _DEFAULT:
        _DEFAULT.append(NativeKernel() if native.available() else NumpyKernel())
    return _DEFAULT[0]
