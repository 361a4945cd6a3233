"""`trimeter bench fit`'s memory columns: the files each variant reads, its model in memory and the heap
peak of one fit, per variant of the method table."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trimeter.bench import fit_variants
from trimeter.bench.timing import peak_bytes
from trimeter.formats.appearance import AppearanceMap
from trimeter.inversion.artifacts import ArtifactCache
from trimeter.inversion.table_builder import build_from_map

DATA = Path(__file__).resolve().parents[1] / "inversion" / "data"


def test_each_variant_counts_the_files_it_reads_and_the_model_it_solves_on():
    amap = AppearanceMap.load(DATA / "ideal-l0.5.tmap")
    small = ArtifactCache(tables={amap.name: build_from_map(amap, n_inverse=fit_variants.SMALL_INVERSE)})
    variants = {v[0]: v for v in fit_variants.variants_of(amap, ArtifactCache(), small)}
    assert {"paper", "lut p0", "lut p≤8", "lut-small p0", "mlp p0", "mlp p2", "mlp p≤8"} <= set(variants)
    sizes = {name: fit_variants.variant_bytes(v) for name, v in variants.items()}
    onnx_bytes = (DATA / "ideal-l0.5.onnx").stat().st_size
    table_bytes = variants["lut p≤8"][3].inverter.table.size_bytes
    assert sizes["paper"][0] == (DATA / "ideal-l0.5.tmap").stat().st_size
    assert sizes["lut p≤8"][0] == table_bytes  # no .tins next to this map
    assert sizes["mlp p≤8"][0] == table_bytes + onnx_bytes
    assert sizes["mlp p≤8"][1] == sizes["lut p≤8"][1] + onnx_bytes
    assert sizes["lut-small p0"][0] < table_bytes and sizes["lut-small p0"][1] < sizes["lut p0"][1]
    assert sizes["lut p0"][1] > 10 * table_bytes  # the refined forward grid the polish runs on


def test_the_heap_peak_is_the_calls_own():
    assert peak_bytes(lambda: np.ones(1 << 20)) >= 8 << 20
    held = np.ones(1 << 20)  # allocated before: not counted
    assert peak_bytes(lambda: held.sum()) < 1 << 16
