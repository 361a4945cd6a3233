"""What a fit takes of one map (thickness): the FitModel protocol, apart from the fit itself so that the
methods (which the fit reaches through trimeter.inversion.methods) can name it."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from scipy.interpolate import LinearNDInterpolator

    from trimeter.formats.appearance import AppearanceMap
    from trimeter.inversion.lut import TableInverter
    from trimeter.inversion.mlp import MlpInverter
    from trimeter.model.grid import ForwardGrid
    from trimeter.model.sample_setup import SampleSetup


class FitModel(Protocol):
    """What a fit needs of one map (thickness): trimeter.inversion.artifacts.MapArtifacts is one."""
    # read-only: a fit never sets them (properties, so that a model may compute them)
    @property
    def name(self) -> str: ...

    @property
    def reference_rhos(self) -> tuple[float, float]: ...

    # the sample set-up every step of the fit uses (the polish grid's: grid.setup)
    @property
    def setup(self) -> SampleSetup: ...

    # the map table's guess and the polish's forward grid (inverter.grid)
    @property
    def inverter(self) -> TableInverter: ...

    # the appearance map's nodes, A, B, C and collimated_measured (paper)
    @property
    def map(self) -> AppearanceMap: ...

    # the paper method's triangulations of this map (None: none kept)
    @property
    def paper_cache(self) -> OrderedDict[tuple[float, float], LinearNDInterpolator] | None: ...

    @property
    def grid(self) -> ForwardGrid: ...

    def mlp(self, model: str | Path | None = None) -> MlpInverter: ...
