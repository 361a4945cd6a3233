"""`trimeter map build` as one pipeline: .tmap → .tins → .tlut → .onnx, each child stamped with its map's
SHA-256 and its producer's version; a child whose map was rebuilt is refused with the command that
rebuilds it; bad stages, recipes and option combinations are one clear error."""

import tomllib

import numpy as np
import pytest

from trimeter import __version__
from trimeter.cli import main
from trimeter.errors import MapFileError
from trimeter.maps import pipeline, stages
from trimeter.maps.appearance import AppearanceMap
from trimeter.maps.inscatter_file import load_inscatter, save_inscatter
from trimeter.maps.device_table import DeviceTable
from trimeter.maps.recipe import parse_recipe

from tiny_toml import tiny_toml

TINY_TOML = tiny_toml("pipe-tiny")
SMALL = pipeline.Options(inscatter_photons=1000, inscatter_shape=(4, 3, 3), mlp_hidden=(6,), mlp_samples=2000,
                         mlp_epochs=3)


def device_recipe(seed=1):
    return parse_recipe({"name": "pipe-device", "geometry": "device", "n": 1.5, "thickness_mm": 0.4, "seed": seed,
                         "grid": {"alpha": {"max": 0.99, "count": 5}, "sigma_t": [1.0, 2.0, 5.0, 10.0],
                                  "g": [0.0, 0.3, 0.5]},
                         "sampling": {"target_stderr": 1.0, "min_paths": 4096, "max_paths": 4096}})


def test_every_stage_stamps_its_child_and_a_rebuilt_map_refuses_the_old_one(tmp_path):
    out = tmp_path / "pipe-device.tmap"
    say = []
    pipeline.run([pipeline.Target(device_recipe(), None, out)], pipeline.STAGES, progress=False, options=SMALL,
                 say=say.append)
    amap = AppearanceMap.load(out)
    tins = load_inscatter(out.with_suffix(".tins"))
    assert tins.parent_sha256 == amap.checksum
    assert tins.producer == {"name": "trimeter map build --stages tins", "version": __version__}
    table = DeviceTable.load(out.with_suffix(".tlut"))  # the device table, carrying this run's .tins
    assert table.parent_sha256 == amap.checksum and table.inscatter_sha256 == tins.checksum
    assert table.inscatter.shape == (4, 3, 3)
    before = out.with_suffix(".tlut").read_bytes()  # the table again on its own: the same bytes
    pipeline.run([pipeline.Target(device_recipe(), None, out)], ("tlut",), progress=False, say=say.append)
    assert out.with_suffix(".tlut").read_bytes() == before
    import onnx

    meta = {p.key: p.value for p in onnx.load(out.with_suffix(".onnx")).metadata_props}
    assert meta["trimeter.map_sha256"] == amap.checksum and meta["trimeter.producer_version"] == __version__
    assert amap.inscatter is not None and amap.inscatter.L.shape == (4, 3, 3)
    assert any(line.startswith("tins: wrote") for line in say)

    # the map again with another seed, its children left as they were: the old table is refused
    say.clear()
    pipeline.run([pipeline.Target(device_recipe(seed=2), None, out)], ("tmap",), progress=False, say=say.append)
    assert any(f"{out.with_suffix('.tins')} was made from the previous map" in line for line in say)
    rebuilt = AppearanceMap.load(out)
    with pytest.raises(MapFileError) as err:
        rebuilt.inscatter
    message = str(err.value)
    assert f"made for map {amap.checksum[:12]}" in message and rebuilt.checksum[:12] in message
    assert f"trimeter map build RECIPE.toml --out {out}" in message and message.endswith("--stages tins")

    # that command's stage alone brings it back
    pipeline.run([pipeline.Target(device_recipe(seed=2), None, out)], ("tins",), progress=False, options=SMALL,
                 say=say.append)
    assert AppearanceMap.load(out).inscatter.parent_sha256 == rebuilt.checksum


def test_a_table_without_a_parent_stamp_is_refused(tmp_path):
    """A .tins from before tables were stamped cannot say which map it was made for."""
    from trimeter.paths import MAPS_DIR

    shipped = AppearanceMap.load(MAPS_DIR / "device-n1.5-l0.4.tmap")
    (tmp_path / "m.tmap").write_bytes(shipped.path.read_bytes())
    table = load_inscatter(shipped.path.with_suffix(".tins"))
    table.parent_sha256 = None
    save_inscatter(table, tmp_path / "m.tins")
    with pytest.raises(MapFileError, match="does not record the map it was made for.*"
                                           "trimeter map build maps/recipes/device-n1.5-l0.4.toml"):
        AppearanceMap.load(tmp_path / "m.tmap").inscatter


def test_cli_builds_the_default_stages_on_a_local_cluster(tmp_path, capsys):
    recipe = tmp_path / "r.toml"
    recipe.write_text(TINY_TOML)
    assert main(["map", "build", str(recipe), "--out-dir", str(tmp_path), "--workers", "1", "--quiet"]) == 0
    text = capsys.readouterr().out
    amap = AppearanceMap.load(tmp_path / "pipe-tiny.tmap")
    assert "dask (1 workers, 1 threads)" in text and amap.provenance["executor"] == "dask (1 workers, 1 threads)"
    assert "tins: skipped for pipe-tiny: in-scattering needs the device geometry" in text
    assert "tlut: skipped for pipe-tiny: a device table needs at least 4 α, 4 σt and 3 g nodes" in text
    assert not (tmp_path / "pipe-tiny.tlut").exists()
    assert not (tmp_path / "pipe-tiny.onnx").exists()           # opt-in


@pytest.mark.parametrize("args, named", [
    (["--stages", "tmap,lut"], "--stages: 'lut' is not a stage"),
    (["--stages", ","], "--stages: 'nothing' is not a stage"),
    (["--workers", "0"], "--workers must be 1…1024"),
    (["--retries", "-1"], "--retries must be 0…100"),
    (["--connect-timeout", "nan"], "--connect-timeout must be"),
    (["--stages", "tlut"], "does not exist: build it first"),
    (["--backend", "metal"], "--backend must be one of llvm, cuda, auto"),
])
def test_bad_options_are_one_clear_error(tmp_path, capsys, args, named):
    recipe = tmp_path / "r.toml"
    recipe.write_text(TINY_TOML)
    assert main(["map", "build", str(recipe), "--out", str(tmp_path / "m.tmap"), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: ") and named in err and err.count("\n") == 1


def test_several_recipes_refuse_one_out_and_stale_maps_refuse_children(tmp_path, capsys):
    recipe, other = tmp_path / "r.toml", tmp_path / "o.toml"
    recipe.write_text(TINY_TOML)
    other.write_text(TINY_TOML.replace('"pipe-tiny"', '"pipe-other"'))
    assert main(["map", "build", str(recipe), str(other), "--out", str(tmp_path / "m.tmap")]) == 2
    assert "with several recipes use --out-dir" in capsys.readouterr().err
    # a map built from another recipe: no child is made from it
    from trimeter.maps.builder import build_map

    build_map(parse_recipe({"name": "pipe-tiny", "geometry": "ideal", "n": 1.4, "thickness_mm": 0.5,
                            "grid": {"alpha": [0, 0.5], "sigma_t": [1, 2], "g": [0, 0.5]},
                            "sampling": {"min_paths": 4096, "max_paths": 4096}}),
              tmp_path / "pipe-tiny.tmap", progress=False)
    assert main(["map", "build", str(recipe), "--out-dir", str(tmp_path), "--stages", "tlut"]) == 2
    err = capsys.readouterr().err
    assert "was built from another recipe" in err and "--stages tmap,tlut" in err
    assert not (tmp_path / "pipe-tiny.tlut").exists()


@pytest.mark.parametrize("edit, named", [
    (("count = 5", 'count = "five"'), "grid.alpha.count"),
    (("min_paths = 4096", "min_paths = 10"), "sampling.min_paths"),
    (('geometry = "ideal"', 'geometry = "lab"'), "geometry must be one of"),
    (("[grid]", "colour = 1\n[grid]"), "unknown key 'colour'"),
])
def test_a_malformed_recipe_names_the_field(tmp_path, capsys, edit, named):
    recipe = tmp_path / "r.toml"
    recipe.write_text(TINY_TOML.replace(*edit))
    assert main(["map", "build", str(recipe), "--out-dir", str(tmp_path), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: ") and named in err and err.count("\n") == 1
    assert not list(tmp_path.glob("*.tmap"))


def test_stage_names_and_rebuild_command():
    assert stages.parse_stages("onnx, tmap") == ("tmap", "onnx")
    from trimeter.paths import MAPS_DIR

    amap = AppearanceMap.load(MAPS_DIR / "ideal-n1.5-l0.5.tmap")
    assert stages.rebuild_command(amap, "tlut").startswith("trimeter map build ")
    assert stages.rebuild_command(amap, "tlut").endswith("recipes/ideal-n1.5-l0.5.toml --out "
                                                           f"{stages._shown_path(amap.path)} --stages tlut")
    assert np.all(stages.SUFFIX[s].endswith(s) for s in stages.STAGES)


def test_cli_backend_cuda_without_a_gpu_is_a_clear_error_and_llvm_builds(tmp_path, capsys, monkeypatch):
    """--backend reaches the column tasks: cuda on a machine without one stops before any work (exit 2,
    one line), llvm builds, and the columns are traced with the backend asked for."""
    from trimeter.forward import transport

    if transport.resolve_backend("auto") == "cuda":
        pytest.skip("this machine has a CUDA device")
    recipe = tmp_path / "r.toml"
    recipe.write_text(TINY_TOML)
    assert main(["map", "build", str(recipe), "--out-dir", str(tmp_path), "--stages", "tmap", "--backend", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trimeter: error: --backend cuda: ") and err.count("\n") == 1
    assert not (tmp_path / "pipe-tiny.tmap").exists()

    seen = []
    real = transport.trace_column

    def spy(*args, backend="llvm", **kwargs):
        seen.append(backend)
        return real(*args, backend=backend, **kwargs)

    monkeypatch.setattr(transport, "trace_column", spy)
    pipeline.run([pipeline.Target(parse_recipe(tomllib.loads(TINY_TOML)), None, tmp_path / "p.tmap")], ("tmap",),
                 progress=False, options=pipeline.Options(tracer_backend="llvm"), say=lambda line: None)
    assert seen and set(seen) == {"llvm"}
    # and the CLI end to end, on a one-worker local cluster
    assert main(["map", "build", str(recipe), "--out-dir", str(tmp_path), "--stages", "tmap", "--backend", "llvm",
                 "--workers", "1", "--quiet"]) == 0
    assert "tracer backend: llvm" in capsys.readouterr().out
    AppearanceMap.load(tmp_path / "pipe-tiny.tmap")
