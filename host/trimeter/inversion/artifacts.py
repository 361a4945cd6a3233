"""A map and its children (`.tlut` device table, `.tins` in-scattering table, `.onnx` network) loaded into what
a fit needs (MapArtifacts, a trimeter.inversion.api.FitModel), kept in an explicit cache; and
`trimeter.fit`, which takes map names, paths or AppearanceMaps and fits through trimeter.inversion."""

from __future__ import annotations

import os
import stat
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.parameters import FitResult

from trimeter.domain.measurement import MapRef
from trimeter.errors import InputError, MapFileError
from trimeter.formats.appearance import AppearanceMap, find_map, map_model_variance
from trimeter.formats.container import read_bounded
from trimeter.formats.device_table import DeviceTable, table_path_for
from trimeter.formats.stages import rebuild_command
from trimeter.inversion.lut import TableInverter
from trimeter.inversion.mlp import MlpInverter
from trimeter.inversion.table_builder import build_from_map
from trimeter.inversion.table_model import DeviceTableModel
from trimeter.model.grid import ForwardGrid
from trimeter.model.sample_setup import SampleSetup

# what names a map to fit with: the map itself, its path, a shipped map's name, or a device table alone (a
# measurement's MapRef is one of the first two)
MapSpec = AppearanceMap | DeviceTable | MapRef | str | Path

MODEL_SUFFIX = ".onnx"
MAX_MODEL_BYTES = 64 * 2**20  # the shipped models are ~6 KB; onnxruntime would parse anything given


def model_path_for(map_path: str | Path) -> Path:
    """The MLP model that goes with a map: maps/<map-name>.onnx."""
    return Path(map_path).with_suffix(MODEL_SUFFIX)


class MapArtifacts:
    """One map as a fit takes it: the map, its table inverter (the table's guess and the polish's
    forward grid, with the map's in-scattering and model error attached), its MLP models on demand
    and the paper method's triangulations."""

    def __init__(self, amap: AppearanceMap, table: DeviceTable):
        self.map = amap
        self.name = amap.name
        self.reference_rhos = amap.reference_rhos
        self.inverter = TableInverter(table, inscatter=amap.inscatter, model_variance=map_model_variance(amap))
        self.paper_cache: OrderedDict = OrderedDict()
        self._mlps: dict = {}

    @property
    def setup(self) -> SampleSetup:
        """The sample set-up the fit works with: the table's (its f32 fields, as the device has them),
        which its forward grid carries; the map's own is amap.setup."""
        return self.inverter.grid.setup

    @property
    def grid(self) -> ForwardGrid:
        """The forward model every method polishes and propagates on: the table's forward map between
        its nodes (ForwardGrid.between_nodes)."""
        return self.inverter.grid

    def mlp(self, model: str | Path | None = None) -> MlpInverter:
        """The MLP for this map: `model` if given, else maps/<map-name>.onnx next to the map. A changed
        file (another mtime) is loaded again."""
        amap = self.map
        if model is None:
            if amap.path is None:
                raise MapFileError("method mlp needs a model file: pass mlp_model=… for a map without a path")
            model = model_path_for(amap.path)
        path = os.fspath(model)
        try:
            info = os.stat(path)  # one system call: exists, is a file, and its mtime
        except OSError:
            info = None
        if info is None or not stat.S_ISREG(info.st_mode):
            raise MapFileError(f"no MLP model {path} for map {amap.name}; train one with tools/train_mlp.py")
        key = (path, info.st_mtime_ns)
        if key not in self._mlps:
            self._mlps[key] = load_mlp(Path(path), amap)
        return self._mlps[key]


def load_mlp(path: Path, amap: AppearanceMap) -> MlpInverter:
    """An MLP model file checked against the map it must have been trained on."""
    return MlpInverter(read_bounded(path, MAX_MODEL_BYTES, "MLP model"), path, amap.checksum,
                       (float(np.log(amap.sigma_t[0])), float(np.log(amap.sigma_t[-1]))),
                       (float(amap.alpha[0]), float(amap.alpha[-1])), (float(amap.g[0]), float(amap.g[-1])))


def map_table(amap: AppearanceMap) -> DeviceTable:
    """The map's table: maps/<name>.tlut if it exists and was built from this very map; else built in
    memory from the map. A stale .tlut (built from an earlier version of the map) is never used: it is
    rebuilt in memory with a warning, since the map is the source of truth and the file only a cache."""
    if amap.path is not None and (path := table_path_for(amap.path)).is_file():
        table = DeviceTable.load(path)  # a damaged or format-1 file is a MapFileError, never ignored
        if not amap.checksum or table.parent_sha256 == amap.checksum:
            return table
        warnings.warn(f"{path} was built from map {table.parent_sha256[:12]}…, not from {amap.path.name} "
                      f"({amap.checksum[:12]}…): using a table rebuilt in memory; refresh the file with "
                      f"`{rebuild_command(amap, 'tlut')}`", stacklevel=3)
    return build_from_map(amap)


class ArtifactCache:
    """Loaded MapArtifacts by map identity (its checksum and its in-scattering table's), and device
    tables' fit models by their SHA-256. `tables` overrides a map's table by its name (e.g. the bench's
    small variant)."""

    def __init__(self, tables: dict[str, DeviceTable] | None = None):
        self._loaded: dict = {}
        self.tables = dict(tables or {})

    def get(self, spec: MapSpec) -> MapArtifacts | DeviceTableModel:
        """The artifacts of an AppearanceMap, a map path or a shipped map's name; a DeviceTable's fit model
        (the table alone)."""
        if isinstance(spec, DeviceTable):
            if spec.sha256 not in self._loaded:
                self._loaded[spec.sha256] = DeviceTableModel(spec)
            return self._loaded[spec.sha256]
        if not isinstance(spec, (AppearanceMap, str, Path)):
            raise InputError(f"{spec!r} is no map: give an appearance map, its path, a shipped map's name or a "
                             f"device table")
        amap = spec if isinstance(spec, AppearanceMap) else AppearanceMap.load(find_map(spec))
        inscatter = amap.inscatter
        key = (amap.checksum or id(amap), inscatter.checksum if inscatter is not None else None)
        if key not in self._loaded:
            table = self.tables.get(amap.name) or map_table(amap)
            self._loaded[key] = MapArtifacts(amap, table)
        return self._loaded[key]

    def clear(self) -> None:
        self._loaded.clear()


DEFAULT_CACHE = ArtifactCache()


def load_artifacts(spec: MapSpec, cache: ArtifactCache | None = None) -> MapArtifacts | DeviceTableModel:
    return (DEFAULT_CACHE if cache is None else cache).get(spec)


def fit(maps: MapSpec | Sequence[MapSpec], I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike,
        rho_b: ArrayLike | None = None, rho_w: ArrayLike | None = None, method: str = "lut", *,
        cache: ArtifactCache | None = None, **options: Any) -> FitResult:
    """`trimeter.fit`: trimeter.inversion.api.fit on maps given as AppearanceMaps, map paths, shipped
    maps' names or DeviceTables (one, or a list for several thicknesses), loaded through `cache` (default: this
    process's). Every other option: trimeter.inversion.api.fit's."""
    from trimeter.inversion.api import fit as solve

    if isinstance(maps, (list, tuple)):
        return solve([load_artifacts(m, cache) for m in maps], I_b, I_w, I_c, rho_b, rho_w, method, **options)
    if isinstance(maps, Sequence) and not isinstance(maps, str):
        raise InputError(f"several maps go in a list or a tuple, not a {type(maps).__name__}")
    return solve(load_artifacts(maps, cache), I_b, I_w, I_c, rho_b, rho_w, method, **options)


def open_map(name_or_path: str | Path, cache: ArtifactCache | None = None) -> AppearanceMap:
    """`trimeter.open_map`: an appearance map by the name of a shipped map (e.g. ``"device-n1.5-l0.4"``) or
    by path, loaded once per process into `cache` (default: the one `trimeter.fit` uses), so a fit with it
    afterwards does not load it again.

    Parameters
    ----------
    name_or_path : str or Path
        A shipped map's name (``trimeter map list``) or a ``.tmap`` file.
    cache : ArtifactCache, optional
        Where loaded maps are kept; default: this process's.

    Returns
    -------
    AppearanceMap
        Its name, thickness_mm, refractive index, checksum and grid; pass it to `trimeter.fit`.

    Raises
    ------
    trimeter.errors.InputError
        No shipped map of that name and no such file.
    trimeter.errors.MapFileError
        The file is damaged or of an unknown version.
    """
    artifacts = load_artifacts(name_or_path, cache)
    assert isinstance(artifacts, MapArtifacts)  # a name or a path is a map, never a bare device table
    return artifacts.map
