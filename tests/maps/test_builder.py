"""The builder: deterministic, checkpointed (an interrupted build resumes without re-tracing finished
columns and gives the same map), refuses a foreign checkpoint, and the map it writes is self-describing."""

import json

import numpy as np
import pytest

from trimeter.errors import InputError
from trimeter.formats.appearance import AppearanceMap
from trimeter.maps.builder import build_map, default_checkpoint_dir, validation_report
from trimeter.maps.recipe import parse_recipe
from trimeter.forward.transport import trace_column

FIELDS = ("A", "B", "C", "std_b", "std_w")


class Interrupt(Exception):
    pass


def counting_tracer(calls):
    def tracer(stack, sigma_t, g, n_paths, seed, k_max):
        calls.append((sigma_t, g, seed))
        return trace_column(stack, sigma_t, g, n_paths, seed, k_max)
    return tracer


@pytest.fixture(scope="module")
def reference_build(tmp_path_factory, tiny_recipe):
    return build_map(tiny_recipe, tmp_path_factory.mktemp("ref") / "tiny.tmap", progress=False)


def test_same_recipe_same_map_and_self_describing(tmp_path, tiny_recipe, reference_build):
    again = build_map(tiny_recipe, tmp_path / "again.tmap", progress=False)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(again, f), getattr(reference_build, f))
    assert again.recipe == tiny_recipe.to_dict()
    prov = again.provenance
    assert prov["mitsuba_version"] and prov["drjit_version"] and prov["trace_seconds"] > 0
    assert prov["paths_per_column"]["min"] == 8192
    assert len(again.checksum) == 64
    assert not default_checkpoint_dir(tmp_path / "again.tmap").exists()   # removed after success


def test_other_seed_gives_another_map(tmp_path, tiny_data, reference_build):
    other = build_map(parse_recipe({**tiny_data(), "seed": 4}), tmp_path / "o.tmap", progress=False)
    assert not np.array_equal(other.A, reference_build.A)


def test_interrupted_build_resumes_without_retracing(tmp_path, tiny_recipe, reference_build):
    out = tmp_path / "tiny.tmap"
    first = []

    def stop_after_two(j, k):
        first.append((j, k))
        if len(first) == 2:
            raise Interrupt

    with pytest.raises(Interrupt):
        build_map(tiny_recipe, out, progress=False, on_column=stop_after_two)
    assert not out.exists()
    ckpt = default_checkpoint_dir(out)
    assert len(list(ckpt.glob("col_*.npz"))) == 2

    with pytest.raises(InputError, match="--resume"):
        build_map(tiny_recipe, out, progress=False)          # never silently discards finished work

    calls = []
    resumed = build_map(tiny_recipe, out, progress=False, resume=True, tracer=counting_tracer(calls))
    n_columns = len(tiny_recipe.sigma_t) * len(tiny_recipe.g)
    assert len(calls) == n_columns - 2                         # only the unfinished columns traced
    assert resumed.provenance["columns_resumed"] == 2
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(resumed, f), getattr(reference_build, f))


def test_checkpoint_of_another_recipe_is_refused(tmp_path, tiny_recipe, tiny_data):
    out = tmp_path / "m.tmap"
    with pytest.raises(Interrupt):
        build_map(tiny_recipe, out, progress=False, on_column=lambda j, k: (_ for _ in ()).throw(Interrupt()))
    other = parse_recipe({**tiny_data(), "n": 1.4})
    with pytest.raises(InputError, match="different recipe"):
        build_map(other, out, progress=False, resume=True)


def test_damaged_checkpoint_column_is_traced_again(tmp_path, tiny_recipe, reference_build):
    out = tmp_path / "m.tmap"
    with pytest.raises(Interrupt):
        build_map(tiny_recipe, out, progress=False, on_column=lambda j, k: (_ for _ in ()).throw(Interrupt()))
    col = next(default_checkpoint_dir(out).glob("col_*.npz"))
    col.write_bytes(col.read_bytes()[:50])
    calls = []
    resumed = build_map(tiny_recipe, out, progress=False, resume=True, tracer=counting_tracer(calls))
    assert len(calls) == len(tiny_recipe.sigma_t) * len(tiny_recipe.g)
    np.testing.assert_array_equal(resumed.A, reference_build.A)


def test_validation_report_on_a_built_map(reference_build):
    report = validation_report(reference_build)
    assert report["energy_ok"] and report["I_b_le_I_w"] and report["g_no_effect_at_alpha0"]
    assert json.dumps(report)
    assert isinstance(reference_build, AppearanceMap)


def test_alpha_target_spends_paths_where_alpha_is_noisy(tmp_path, tiny_data):
    """target_alpha_stderr: the thin column (σt·ℓ = 0.25, I barely changes with α) is traced with
    more paths than the dense one (2.5) and ends nearer its α target; without the option every
    column stops at min_paths, as before."""
    from trimeter.maps.builder import worst_alpha_stderr
    from trimeter.forward.transport import Stack

    paths = {}

    def tracer(stack, sigma_t, g, n_paths, seed, k_max):
        paths[(sigma_t, g)] = paths.get((sigma_t, g), 0) + n_paths
        return trace_column(stack, sigma_t, g, n_paths, seed, k_max)

    plain = parse_recipe(tiny_data(max_paths=1 << 18))
    build_map(plain, tmp_path / "plain.tmap", progress=False, tracer=tracer)
    assert set(paths.values()) == {8192}
    paths.clear()
    recipe = parse_recipe(tiny_data(max_paths=1 << 18, target_alpha_stderr=0.004))
    amap = build_map(recipe, tmp_path / "alpha.tmap", progress=False, tracer=tracer)
    thin, dense = paths[(0.5, 0.0)], paths[(5.0, 0.0)]
    assert thin > 2 * dense, paths
    assert amap.recipe["sampling"]["target_alpha_stderr"] == 0.004
    # the criterion the builder used, re-measured on fresh traces of the path counts it chose
    stack = Stack.from_recipe(recipe.geometry, recipe.geometry_params, recipe.n, recipe.thickness_mm)
    for (s, g), n in paths.items():
        t = trace_column(stack, s, g, n, 77, 200)
        got = worst_alpha_stderr(t, recipe.alpha, recipe.reference_rho_b, recipe.reference_rho_w)
        assert got < 0.004 * 1.3 or n >= recipe.sampling.max_paths, (s, g, n, got)


def test_alpha_target_is_validated_and_absent_by_default(tiny_data):
    with pytest.raises(InputError, match="target_alpha_stderr"):
        parse_recipe(tiny_data(target_alpha_stderr=-1))
    assert "target_alpha_stderr" not in parse_recipe(tiny_data()).to_dict()["sampling"]


def test_a_non_finite_checkpoint_column_is_quarantined_and_traced_again(tmp_path, tiny_recipe, reference_build):
    from trimeter.maps.builder import quarantine_dir

    out = tmp_path / "m.tmap"
    with pytest.raises(Interrupt):
        build_map(tiny_recipe, out, progress=False, on_column=lambda j, k: (_ for _ in ()).throw(Interrupt()))
    ckpt = default_checkpoint_dir(out)
    col = next(ckpt.glob("col_*.npz"))
    with np.load(col) as z:
        data = {name: np.array(z[name]) for name in z.files}
    data["A"][0] = np.nan
    with open(col, "wb") as f:
        np.savez(f, **data)
    calls = []
    resumed = build_map(tiny_recipe, out, progress=False, resume=True, tracer=counting_tracer(calls))
    assert len(calls) == len(tiny_recipe.sigma_t) * len(tiny_recipe.g)     # the NaN column traced again
    np.testing.assert_array_equal(resumed.A, reference_build.A)
    kept = list(quarantine_dir(ckpt).iterdir())
    assert [p.name.split(".npz")[0] for p in kept] == [col.stem]            # kept aside, not deleted
    assert np.isnan(np.load(kept[0])["A"][0])


def test_a_column_traced_to_nan_writes_no_map_and_keeps_the_checkpoint(tmp_path, tiny_recipe, monkeypatch):
    from trimeter.errors import BuildError
    from trimeter.maps import builder

    traced = builder.trace_column

    def nan_at_first(recipe, stack, j, k, tracer):
        col = traced(recipe, stack, j, k, tracer)
        if (j, k) == (0, 0):
            col.A[...] = np.nan
        return col

    monkeypatch.setattr(builder, "trace_column", nan_at_first)
    out = tmp_path / "m.tmap"
    with pytest.raises(BuildError, match=r"column\(s\) \(0, 0\) traced to a non-finite value"):
        build_map(tiny_recipe, out, progress=False)
    assert not out.exists()
    assert len(list(default_checkpoint_dir(out).glob("col_*.npz"))) == len(tiny_recipe.sigma_t) * len(tiny_recipe.g)


def test_a_build_without_a_terminal_says_what_it_traces_and_how_long_is_left(tmp_path, tiny_recipe, capsys):
    build_map(tiny_recipe, tmp_path / "tiny.tmap", progress=True)
    err = capsys.readouterr().err.splitlines()
    assert err[0] == ("tiny: tracing 4 of 4 (σt, g) columns (0 from the checkpoint), 8,192 photon paths each "
                      "(up to 32,768 paths in all)")
    assert err[-1].startswith("tiny: 4/4 columns, 0:00:") and err[-1].endswith("elapsed, the build is done")


def test_progress_lines_come_at_most_every_interval_with_an_estimate_from_the_pace():
    import io

    from trimeter.maps.builder import ProgressLines, work_line

    now, out = [0.0], io.StringIO()
    lines = ProgressLines([("a", 10, 2), ("b", 4, 0)], every_s=30.0, clock=lambda: now[0], out=out)
    for t in (10.0, 40.0, 50.0):  # one column each: 10 s apart, then 30 s, then 10 s
        now[0] = t
        lines.advance(0)
    # at 40 s: 2 columns traced, 10 + 4 − 4 = 10 left at 20 s a column; none at 10 s or 50 s (within 30 s)
    assert out.getvalue() == "a: 4/10 columns, 0:00:40 elapsed, about 0:03:20 left\n"
    huge = parse_recipe({"name": "huge", "geometry": "ideal", "n": 1.5, "thickness_mm": 0.5, "seed": 1,
                         "grid": {"alpha": {"max": 0.99, "count": 6}, "sigma_t": [0.5, 5.0], "g": [0.0, 0.5]},
                         "sampling": {"min_paths": 1_000_000_000, "max_paths": 1_000_000_000}})
    assert "1,000,000,000 photon paths each (up to 4,000,000,000 paths in all)" in work_line(huge, 4, 0)
