"""A fit from a device table alone (no appearance map, no network): the fit model trimeter.inversion.api.fit
takes for a `.tlut` file or an instrument's table."""

from __future__ import annotations

from pathlib import Path
from typing import NoReturn

import numpy as np

from trimeter.errors import MapFileError
from trimeter.formats.device_table import DeviceTable
from trimeter.inversion.lut import TableInverter
from trimeter.model.grid import ForwardGrid


class DeviceTableModel:
    """A fit's view of a device table alone (a trimeter.inversion.api.FitModel): the lut method's guess
    and polish, with the in-scattering correction and the map's node error it carries. It holds no
    appearance map and no network, so the paper and mlp methods are refused by name."""

    paper_cache = None

    def __init__(self, table: DeviceTable, inverter: TableInverter | None = None) -> None:
        """inverter: another guess-and-polish over this table (default: TableInverter on it, its
        forward model refined at load by ForwardGrid.between_nodes)."""
        self.table = table
        self.name = table.name
        self.reference_rhos = table.reference_rhos
        self.setup = table.setup
        axes = tuple(np.asarray(a, dtype=np.float64) for a in (table.alpha, table.log_sigma_t, table.g))
        self.inverter = inverter or TableInverter(table, inscatter=table.inscatter_table(),
                                                  model_variance=(table.model_variance(), axes))

    @property
    def grid(self) -> ForwardGrid:
        return self.inverter.grid

    @property
    def map(self) -> NoReturn:
        where = f" ({self.table.path})" if self.table.path else ""
        raise MapFileError(f"{self.name}: a device table{where} carries no appearance map; the paper method needs "
                           f"the map (.tmap): fit from the table with method lut")

    def mlp(self, model: str | Path | None = None) -> NoReturn:
        raise MapFileError(f"{self.name}: a device table carries no MLP model; fit from it with method lut")
