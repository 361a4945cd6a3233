"""Standard deviations for the instrument's fit from a device table (`trimeter fit --table`, `--on-device`).

That fit (table_fit.c, here through native.TableFitter or on the MCU) returns α, σt, g and flags only. Its
stds are computed here, on the host, from the same table, as trimeter.inversion.finish.finish computes a
map fit's: first-order propagation of the intensities' stds (given, else the fit's noise model) and of the
map's own error that the table carries at its nodes (its model_std section: the MC std-error and the
leave-one-out interpolation error at the LEAVE_ONE_OUT_SCALE it was built with), interpolated as the C fit
does (tr_model_variance), through the Jacobian of the table's compact model — the model the fit's Newton
polish evaluates — at the fit's (α, g) on σt's Beer-Lambert cell; σt's std from I_c's, the in-scattering
correction's (INSCATTER_REL_STD of the σt it added) and the thickness's. UNDERDETERMINED is judged on the
stds at no less than the noise model, as finish does, and STD_APPROXIMATE marks where the compact model
bends within ±STD_CHECK_SIGMAS σ (finish.std_approximate).

The Jacobian is evaluated at the fit's final (α, g), after the in-scattering correction's step; the C fit's
own polish ended at the (α, g) before it: the two differ by that step, a first-order term in the stds.
Where g is undefined (G_UNDEFINED) the fit returns no g, and the Jacobian is taken at g = 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.inversion.api import shape_stds
from trimeter.inversion.finish import conditioning_stds, sanitize, std_approximate, underdetermined
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.inversion.kernel import Kernel, default_kernel
from trimeter.inversion import native
from trimeter.inversion.native import invert_h
from trimeter.model.compact import CompactForward
from trimeter.model.grid import ForwardGrid, SigmaCell

if TYPE_CHECKING:
    from trimeter.formats.device_table import DeviceTable

# the instrument's fit's own settings (fit()'s defaults, compiled into table_fit.c)
NOISE_REL, NOISE_ABS = invert_h.TABLE_FIT_NOISE_REL, invert_h.TABLE_FIT_NOISE_ABS
IC_FLOOR = invert_h.TABLE_FIT_IC_FLOOR
INSCATTER_REL_STD = invert_h.TABLE_FIT_INSCATTER_REL_STD


class CompactGrid(ForwardGrid):
    """A device table's forward model as its C fit evaluates it: A, B, C and their derivatives from the
    compact model's splines at any point (not trilinear between nodes), on the table's own nodes for σt's
    cell, the box and the map's error variances (attached from the table's model_std section)."""

    def __init__(self, table: DeviceTable) -> None:
        super().__init__(table.alpha, table.log_sigma_t, table.g, table.coefficients_grid, setup=table.setup,
                         mc_stderr=table.mc_stderr)
        # the C evaluation where the kernel is loaded (the numpy one, CompactForward, is its reference)
        self.compact: native.TableModel | CompactForward = \
            native.TableModel(table.to_bytes()) if native.available() else table.forward()
        self.attach_model_variance(table.model_variance(), self.alpha, self.log_sigma_t, self.g)

    def coefficients(self, alpha: np.ndarray, cell: SigmaCell, g: np.ndarray,
                     with_sigma_derivative: bool = False) -> tuple[np.ndarray, ...]:
        value, d_alpha, d_log_sigma, d_g = self.compact.evaluate(alpha, cell.log_sigma_t, g)
        return (value, d_alpha, d_g, d_log_sigma) if with_sigma_derivative else (value, d_alpha, d_g)


class TableStds:
    """The stds of the instrument's fit from one device table (build once, use per chunk of bins)."""

    def __init__(self, table: DeviceTable, kernel: Kernel | None = None) -> None:
        self.table = table
        self.grid = CompactGrid(table)
        self.kernel = default_kernel() if kernel is None else kernel

    def result(self, fitted: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], I_b: ArrayLike, I_w: ArrayLike,
               I_c: ArrayLike, rho_b: ArrayLike, rho_w: ArrayLike, *, I_b_std: ArrayLike | None = None,
               I_w_std: ArrayLike | None = None, I_c_std: ArrayLike | None = None, thickness_rel_std: float = 0.0,
               method: str = "lut") -> FitResult:
        """The fit `fitted` = (α, σt, g, flags) of these bins (as TableFitter.fit or Device.fit return it)
        with its stds: a FitResult as trimeter.inversion.api.fit returns for a map. I_*_std: the
        intensities' stds (NaN or None: the fit's noise model there); thickness_rel_std: the sample
        thickness's std over the table's thickness."""
        grid, kernel = self.grid, self.kernel
        ib, iw, ic, rb, rw = (np.atleast_1d(np.asarray(x, dtype=np.float64)) for x in (I_b, I_w, I_c, rho_b, rho_w))
        alpha, sigma_t, g = (np.asarray(x, dtype=np.float64) for x in fitted[:3])
        flags = np.asarray(fitted[3], dtype=np.int64).copy()
        if len({x.shape for x in (ib, iw, ic, rb, rw, alpha, sigma_t, g, flags)}) != 1 or ib.ndim != 1:
            raise InputError("table stds: the fit's α, σt, g, flags and the bins' I_b, I_w, I_c, rho_b, rho_w must "
                             "be arrays over the same bins")
        usable = (flags & int(UNUSABLE)) == 0
        ib, iw, ic = sanitize(ib, 0.0, 1.0, 0.0), sanitize(iw, 0.0, 1.0, 1.0), sanitize(ic, 0.0, 1.0, 1.0)
        rb = np.where(usable, rb, self.table.rho_b_ref)
        rw = np.where(usable, rw, self.table.rho_w_ref)
        floor_sd = np.column_stack([NOISE_REL * x + NOISE_ABS for x in (ib, iw, ic)])
        given = (I_b_std, I_w_std, I_c_std)
        sd = floor_sd if all(v is None for v in given) else \
            shape_stds(1, [(ib, iw, ic, rb, rw)], given, NOISE_REL, NOISE_ABS)[0]
        assert sd is not None  # stds were given
        # σt's Beer-Lambert cell, where the fit solved (α, g); what the in-scattering correction added to it
        t_max = grid.transmittance_limits[0]
        sigma_solved = grid.setup.beer_lambert_sigma_t(np.minimum(np.maximum(ic, IC_FLOOR), t_max))
        with np.errstate(invalid="ignore"):
            inscatter_ds = np.where(usable & (sigma_t > sigma_solved), sigma_t - sigma_solved, 0.0)
        a0, g0 = np.where(np.isfinite(alpha), alpha, grid.alpha_range[0]), np.where(np.isfinite(g), g, 0.0)
        J = grid.jacobian(a0, sigma_solved, g0, rb, rw)
        model = grid.model_variance(a0, grid.sigma_cell(sigma_solved), g0)
        var_in = sd * sd
        sigma_I = np.column_stack([np.sqrt(var_in[:, 0] + model[0]), np.sqrt(var_in[:, 1] + model[1]), sd[:, 2]])
        inscatter_var = (INSCATTER_REL_STD * inscatter_ds) ** 2
        std_a, std_s, std_g = kernel.propagate(J, sigma_I, inscatter_var)
        std_s = np.sqrt(std_s * std_s + (thickness_rel_std * sigma_t) ** 2)
        std_s = np.where((flags & int(FitFlag.IC_BELOW_FLOOR)) != 0, np.inf, std_s)
        g_undef = (flags & int(FitFlag.G_UNDEFINED)) != 0
        std_g = np.where(g_undef, np.nan, std_g)
        cond_a, cond_g = conditioning_stds(kernel, J, sd, floor_sd, model, inscatter_var, std_a, std_g, g_undef)
        flags |= np.where(usable & underdetermined(cond_a, cond_g), int(FitFlag.UNDERDETERMINED), 0)
        flags |= np.where(std_approximate(grid, flags, a0, sigma_solved, g0, ib, iw, rb, rw, J, sigma_I, std_a,
                                          std_g), int(FitFlag.STD_APPROXIMATE), 0)
        blank, nan = ~usable, np.nan
        return FitResult(alpha=alpha, sigma_t=sigma_t, g=g, alpha_std=np.where(blank, nan, std_a),
                         sigma_t_std=np.where(blank, nan, std_s), g_std=np.where(blank, nan, std_g), flags=flags,
                         sigma_t_beer=grid.setup.beer_lambert_sigma_t(np.asarray(I_c, dtype=np.float64)),
                         method=method,
                         conditioning_alpha_std=None if cond_a is std_a else np.where(blank, nan, cond_a),
                         conditioning_g_std=None if cond_g is std_g else np.where(blank, nan, cond_g))
