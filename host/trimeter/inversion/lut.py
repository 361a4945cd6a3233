"""`lut`: the map table's inverse grid for the initial guess, then an optional Newton polish on the
table's own forward map (refined between its nodes at load) at the bins' true ρ_b(λ), ρ_w(λ).

σt comes from I_c directly (exact Beer-Lambert with Fresnel), and where the map has an in-scattering
table, is corrected at the end for the light scattered into the detector's aperture (to first order,
ForwardGrid.correct_inscatter); the inverse grid is looked up bilinearly in (√I_b, √I_w) on the two σt
nodes bracketing it and blended. The grid was built at the reference backgrounds; when a bin's ρ's
differ, the polish (a few vectorised Gauss-Newton steps, each bin stopping once converged) moves the
guess to the exact solution of that forward map.

Guess and polish run on the kernel the fit was handed (trimeter.inversion.kernel: numpy or C, the
same algorithm); initial_guess below is the numpy reference of the C guess.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from trimeter.inversion.strategy import Method
from trimeter.model.grid import ForwardGrid, SigmaCell

if TYPE_CHECKING:
    from trimeter.formats.device_table import DeviceTable
    from trimeter.model.inscatter_table import InscatterTable


class TableInverter:
    def __init__(self, table: DeviceTable, inscatter: InscatterTable | None = None,
                 model_variance: tuple[np.ndarray, tuple[np.ndarray, ...]] | None = None) -> None:
        """table: a device table (trimeter.formats.device_table.DeviceTable: its forward model, inverse slices and
        set-up); inscatter: the map's in-scattering table (trimeter.model.inscatter_table.InscatterTable), or
        None; model_variance: the map's own error at its nodes ((variances, axes) as
        ForwardGrid.attach_model_variance takes them), or None."""
        self.table = table
        self.table_grid = ForwardGrid.from_table(table)  # the table's own nodes: its guess slices
        # the polish model: the table's forward map between its nodes as everywhere (model.grid.BETWEEN_NODES_*)
        self.grid = self.table_grid.between_nodes()
        self.grid.attach_inscatter(inscatter)
        if model_variance is not None:
            self.grid.attach_model_variance(model_variance[0], *model_variance[1])
        ns, ny, nx = table.inv_alpha_q.shape
        self._shape = (ns, ny, nx)
        v = np.stack([table.inverse_alpha, table.inverse_g], -1)  # (ns, ny, nx, 2)
        v00, v01, v10, v11 = v[:, :-1, :-1], v[:, :-1, 1:], v[:, 1:, :-1], v[:, 1:, 1:]
        # Per inverse cell the bilinear polynomial q0 + q1·fu + q2·fv + q3·fu·fv (for α and g): one
        # gather per slice, then component-major rows.
        self._cells = np.ascontiguousarray(
            np.stack([v00, v01 - v00, v10 - v00, v11 - v10 - v01 + v00], axis=-2).reshape(-1, 8))
        f = table.inv_frame.astype(np.float64)
        self._ox, self._oy = f[:, 0].copy(), f[:, 1].copy()
        self._m = [f[:, 2] * (nx - 1), f[:, 3] * (nx - 1), f[:, 4] * (ny - 1), f[:, 5] * (ny - 1)]

    @property
    def inverse_cells(self) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int], np.ndarray]:
        """(cells, frames, shape, the table's ln σt nodes): the guess slices as the C kernel takes them."""
        return (self._cells, np.column_stack([self._ox, self._oy, *self._m]), self._shape,
                self.table_grid.log_sigma_t)

    def initial_guess(self, I_b: np.ndarray, I_w: np.ndarray, cell: SigmaCell) -> tuple[np.ndarray, np.ndarray]:
        """The table's (α, g) guess; `cell` on the table's own σt nodes (self.table_grid.sigma_cell)."""
        ns, ny, nx = self._shape
        # a NaN intensity counts as 0 here (it would index outside the table); the polish then returns NaN
        x = np.sqrt(np.minimum(np.where(I_b > 0.0, I_b, 0.0), 1.0))
        y = np.sqrt(np.minimum(np.where(I_w > 0.0, I_w, 0.0), 1.0))
        blended = []
        m00, m01, m10, m11 = self._m
        for dk, wk in ((0, 1.0 - cell.weight), (1, cell.weight)):  # the two bracketing σt nodes
            k = cell.index + dk
            dx, dy = x - self._ox[k], y - self._oy[k]
            u = np.minimum(np.maximum(m00[k] * dx + m01[k] * dy, 0.0), nx - 1.0)
            v = np.minimum(np.maximum(m10[k] * dx + m11[k] * dy, 0.0), ny - 1.0)
            iu = np.minimum(u.astype(np.intp), nx - 2)
            iv = np.minimum(v.astype(np.intp), ny - 2)
            fu, fv = u - iu, v - iv
            q = self._cells[(k * (ny - 1) + iv) * (nx - 1) + iu].T.copy().reshape(4, 2, -1)
            blended.append((q[0] + q[1] * fu + (q[2] + q[3] * fu) * fv) * wk)
        out = blended[0] + blended[1]
        return out[0], out[1]


METHOD = Method("lut", "the map table's inverse grid as the guess, then the Newton polish on the forward map",
                # p0/p2: the raw table and two fixed Newton steps; p≤8: fit()'s default, up to 8 steps, a bin
                # stopping once its steps are small (the adaptive polish, newton.step_is_small)
                bench_variants=(("p0", dict(polish=0, polish_tol=0.0)), ("p2", dict(polish=2, polish_tol=0.0)),
                                ("p≤8", {})))
