"""The library: add → export → import into another data directory reproduces a material exactly; tags,
notes, list, show, remove; renderer exports of a library material; one clear error per bad input."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from library_support import WL, fit_result, write_member
from trimeter.cli import main
from trimeter.errors import InputError, OutputError
from trimeter.library.format import COLUMN_NAMES, MANIFEST_FILE, SPECTRA_FILE, read_material, schema, validate
from trimeter.library.store import Library


@pytest.fixture
def members(tmp_path):
    root = tmp_path / "results"
    alpha = 0.9 - 0.1 * (WL - 420) / 260
    std = (np.full(len(WL), 0.01), np.full(len(WL), 0.1), np.full(len(WL), 0.05))
    std[0][5] = np.nan   # one member without an α std in one bin
    return [write_member(root, fit_result(alpha, 2.0, 0.5)),
            write_member(root, fit_result(alpha + 0.005, 2.1, 0.52)),
            write_member(root, fit_result(alpha - 0.004, 1.95, 0.49, std=std))]


def _same(a, b):
    """Two materials equal exactly (NaN where NaN)."""
    da, db = a.document, b.document
    assert (da.name, da.notes, da.tags, da.created_utc, da.combination, da.members) == \
           (db.name, db.notes, db.tags, db.created_utc, db.combination, db.members)
    for name in COLUMN_NAMES:
        x, y = da.columns[name], db.columns[name]
        assert np.array_equal(x, y, equal_nan=True), name


def test_round_trip_into_another_data_directory(tmp_path, members):
    here = Library(tmp_path / "a" / "library.sqlite")
    m = here.add("cyan batch 3", members, notes="three repeats", tags=["ink", "cyan"])
    assert m.document.tags == ["cyan", "ink"] and len(m.document.members) == 3
    out = here.export("cyan batch 3", tmp_path / "cyan.material")
    doc = json.loads((out / MANIFEST_FILE).read_text())
    assert not validate(doc, schema())
    there = Library(tmp_path / "b" / "library.sqlite")
    imported = there.import_(out)
    _same(m, imported)
    assert imported.origin == "imported"
    # and again out of the second library: the same files
    again = there.export("cyan batch 3", tmp_path / "again")
    assert (again / SPECTRA_FILE).read_bytes() == (out / SPECTRA_FILE).read_bytes()
    assert json.loads((again / MANIFEST_FILE).read_text()) == doc


def test_cli_add_list_show_tag_export_import_remove(tmp_path, members, capsys, monkeypatch):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    assert main(["library", "add", "cyan", *members, "--tag", "ink"]) == 0
    assert "3 member(s), inverse-variance" in capsys.readouterr().out
    assert (tmp_path / "data" / "library.sqlite").is_file()   # beside the history
    assert main(["library", "list"]) == 0 and "cyan" in capsys.readouterr().out
    assert main(["library", "tag", "cyan", "--add", "batch3", "--notes", "shaken"]) == 0
    capsys.readouterr()
    assert main(["library", "show", "cyan", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["tags"] == ["batch3", "ink"] and shown["notes"] == "shaken" and shown["member_problems"] == []
    assert main(["library", "export", "cyan", "-o", str(tmp_path / "x")]) == 0
    assert main(["library", "--db", str(tmp_path / "other.sqlite"), "import", str(tmp_path / "x"), "--as",
                 "cyan copy"]) == 0
    assert main(["library", "remove", "cyan"]) == 0
    assert main(["library", "show", "cyan"]) == 2
    assert "no material 'cyan'" in capsys.readouterr().err
    for p in members:
        assert Path(p).is_dir()   # removing a material never touches its measurements


@pytest.mark.parametrize("fmt,file", [("mitsuba", "medium.xml"), ("pbrt", "medium.pbrt"), ("rgb", "rgb.json"),
                                      ("blender", "blender.json")])
def test_every_renderer_export_works_on_a_library_material(tmp_path, members, fmt, file):
    lib = Library(tmp_path / "library.sqlite")
    m = lib.add("cyan", members)
    provenance = m.export(fmt, tmp_path / fmt)
    assert (tmp_path / fmt / file).is_file()
    assert provenance["source"]["library_material"] == "cyan"
    assert [x["measurement"] for x in provenance["source"]["members"]] == [Path(p).name for p in members]


def test_the_library_material_exports_its_combined_parameters(tmp_path, members):
    lib = Library(tmp_path / "library.sqlite")
    m = lib.add("cyan", members)
    material = m.material()
    assert np.allclose(material.alpha, m.document.columns["alpha"])
    assert np.allclose(material.sigma_t, m.document.columns["sigma_t"])


# ----------------------------------------------------------------------------------- bad input
@pytest.fixture
def exported(tmp_path, members):
    lib = Library(tmp_path / "a.sqlite")
    lib.add("cyan", members)
    return lib.export("cyan", tmp_path / "cyan.material")


def _edit_manifest(path, **changes):
    doc = json.loads((path / MANIFEST_FILE).read_text())
    doc.update(changes)
    (path / MANIFEST_FILE).write_text(json.dumps(doc))


def test_wrong_version(exported, tmp_path):
    _edit_manifest(exported, version=2)
    lib = Library(tmp_path / "b.sqlite")
    with pytest.raises(InputError, match="format version 2; .* reads version 1 only"):
        lib.import_(exported)
    assert lib.names() == []


def test_missing_spectra(exported, tmp_path):
    (exported / SPECTRA_FILE).unlink()
    with pytest.raises(InputError, match=r"the spectra \(spectra.csv\) are missing"):
        Library(tmp_path / "b.sqlite").import_(exported)


def test_nan_in_a_value(exported, tmp_path):
    lines = (exported / SPECTRA_FILE).read_text().splitlines()
    cells = lines[3].split(",")
    cells[COLUMN_NAMES.index("sigma_t")] = "nan"
    lines[3] = ",".join(cells)
    (exported / SPECTRA_FILE).write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="sigma_t is NaN or empty in data row 3"):
        Library(tmp_path / "b.sqlite").import_(exported)


def test_changed_spectra_are_refused(exported, tmp_path):
    text = (exported / SPECTRA_FILE).read_text()
    (exported / SPECTRA_FILE).write_text(text.replace("0.5", "0.6", 1))
    with pytest.raises(InputError, match="SHA-256 is not the manifest's"):
        Library(tmp_path / "b.sqlite").import_(exported)


def test_manifest_against_the_schema(exported, tmp_path):
    _edit_manifest(exported, members=[])
    with pytest.raises(InputError, match="members: needs at least 1 item"):
        read_material(exported)
    _edit_manifest(exported, colour="blue")
    with pytest.raises(InputError, match="unknown key 'colour'"):
        read_material(exported)


def test_a_member_that_no_longer_exists(tmp_path, members):
    lib = Library(tmp_path / "a.sqlite")
    before = lib.add("cyan", members)
    shutil.rmtree(members[1])
    with pytest.raises(InputError, match=r"member .* no longer exists; the library keeps the material"):
        lib.export("cyan", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    _same(lib.get("cyan"), before)      # nothing lost
    assert lib.get("cyan").missing_members()


def test_a_member_that_does_not_exist_when_added(tmp_path, members):
    lib = Library(tmp_path / "a.sqlite")
    with pytest.raises(InputError, match="no such results directory"):
        lib.add("cyan", [members[0], str(tmp_path / "gone")])
    assert lib.names() == []


def test_names_tags_and_collisions(tmp_path, members):
    lib = Library(tmp_path / "a.sqlite")
    with pytest.raises(InputError, match="material name"):
        lib.add("../evil", members)
    with pytest.raises(InputError, match="tag"):
        lib.add("cyan", members, tags=["a b"])
    lib.add("cyan", members[:1])
    with pytest.raises(InputError, match="already has a material 'cyan'"):
        lib.add("cyan", members)
    assert len(lib.get("cyan").document.members) == 1
    assert len(lib.add("cyan", members, replace=True).document.members) == 3


def test_export_never_overwrites(exported, tmp_path):
    lib = Library(tmp_path / "a.sqlite")
    with pytest.raises(OutputError, match="exists"):
        lib.export("cyan", exported)


def test_values_are_exact_in_the_file(exported):
    doc = read_material(exported)
    assert all(math.isfinite(v) for v in doc.columns["alpha"])
    assert np.isnan(doc.columns["alpha_std"][5])   # the member without a std there: unknown, an empty cell


def test_schema_uses_only_the_keywords_the_validator_knows():
    known = {"$schema", "$id", "title", "description", "type", "const", "enum", "required", "properties",
             "additionalProperties", "items", "minItems", "minLength", "pattern", "minimum", "maximum",
             "exclusiveMinimum"}

    def walk(rule):
        if isinstance(rule, dict):
            assert set(rule) <= known | set(), set(rule) - known
            for key in ("properties",):
                for sub in rule.get(key, {}).values():
                    walk(sub)
            for key in ("items", "additionalProperties"):
                if isinstance(rule.get(key), dict):
                    walk(rule[key])
    walk(schema())


def test_schema_file_with_jsonschema_when_installed(exported):
    jsonschema = pytest.importorskip("jsonschema")
    doc = json.loads((exported / MANIFEST_FILE).read_text())
    jsonschema.Draft202012Validator.check_schema(schema())
    jsonschema.validate(doc, schema())
    bad = {**doc, "version": 2}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema())


def test_a_library_material_is_a_material_for_predictions_and_mixtures(tmp_path, members):
    from trimeter.prediction import _as_material

    m = Library(tmp_path / "a.sqlite").add("cyan", members)
    material = _as_material(m)
    assert np.array_equal(material.wavelengths_nm, m.document.columns["wavelength_nm"])


def test_a_damaged_library_file_is_one_clear_error(tmp_path, capsys):
    db = tmp_path / "library.sqlite"
    db.write_bytes(b"not a database at all" * 100)
    with pytest.raises(InputError, match="not a usable library database"):
        Library(db)
    assert main(["library", "--db", str(db), "list"]) == 2
    assert "not a usable library database" in capsys.readouterr().err
    assert db.read_bytes().startswith(b"not a database")   # left as it was
