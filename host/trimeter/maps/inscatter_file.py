"""`<map>.tins`: the in-scattering table (trimeter.model.inscatter.InscatterTable) as a trimeter
container next to its map."""

from __future__ import annotations

from pathlib import Path

from trimeter.errors import MapFileError
from trimeter.maps.container import read_container, write_container
from trimeter.maps.schema import (GEOMETRY_PARAMS, PARENT_SHA256, PRODUCER, PROVENANCE, SAMPLE_N, THICKNESS_MM,
                                  ArraySpec, ContainerSchema, Number, Table)
from trimeter.model.inscatter import InscatterTable

INSCATTER_KIND = "inscatter-table"
INSCATTER_FORMAT_VERSION = 1
INSCATTER_SUFFIX = ".tins"
_EXTENT = Number(lo=0.0, lo_open=True, hi=50.0)  # u_max, v_max: −ln(1 − 0.999) ≈ 6.9; τ_max: TAU_MAX
# What an in-scatter table file must hold, checked before it is used (trimeter.maps.schema).
INSCATTER_SCHEMA = ContainerSchema(
    version=("format_version", "in-scatter table format version", INSCATTER_FORMAT_VERSION),
    meta=Table({"u_max": _EXTENT, "tau_max": _EXTENT, "v_max": _EXTENT, "n": SAMPLE_N, "thickness_mm": THICKNESS_MM,
                "geometry_params": GEOMETRY_PARAMS, "provenance": PROVENANCE, "parent_sha256": PARENT_SHA256,
                "producer": PRODUCER},
               required=("format_version", "u_max", "tau_max", "v_max", "n", "thickness_mm", "geometry_params")),
    arrays={"L": ArraySpec(("n_u", "n_tau", "n_g"), min_len=2, lo=0.0, hi=50.0)})


def inscatter_path_for(map_path: str | Path) -> Path:
    return Path(map_path).with_suffix(INSCATTER_SUFFIX)


def save_inscatter(table: InscatterTable, path: str | Path) -> str:
    """Write the table; returns (and sets table.checksum to) the file's SHA-256."""
    meta = {"format_version": INSCATTER_FORMAT_VERSION, "u_max": table.u_max, "tau_max": table.tau_max,
            "v_max": table.v_max, "n": table.n, "thickness_mm": table.thickness_mm,
            "geometry_params": table.geometry_params, "provenance": table.provenance}
    if table.parent_sha256 is not None:
        meta.update(parent_sha256=table.parent_sha256, producer=table.producer)
    table.checksum = write_container(path, INSCATTER_KIND, meta, {"L": table.L})
    return table.checksum


def load_inscatter(path: str | Path) -> InscatterTable:
    """Read and check a `.tins` file (a damaged or incomplete one is a MapFileError)."""
    meta, arrays, checksum = read_container(path, INSCATTER_KIND, INSCATTER_SCHEMA)
    try:
        table = InscatterTable(arrays["L"], **{k: meta[k] for k in ("u_max", "tau_max", "v_max", "n", "thickness_mm",
                                                                    "geometry_params")},
                               provenance=meta.get("provenance"), parent_sha256=meta.get("parent_sha256"),
                               producer=meta.get("producer"))
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFileError(f"{path}: in-scatter table header incomplete ({exc})") from None
    except MapFileError as exc:
        raise MapFileError(f"{path}: {exc}") from None
    table.checksum = checksum
    return table
