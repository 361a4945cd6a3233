"""The build documentation: bom.md and wiring.md up to date with their sources (like the register
map's --check), the low-cost build under its budget, every MCU pin of pinout.toml wired, and bad
source files refused with a message naming the item."""

import json
import tomllib

import pytest

from conftest import ROOT, gen_hardware

HW = ROOT / "hardware"


def test_rendered_tables_are_up_to_date():
    for path, text in gen_hardware.outputs().items():
        assert path.read_text(encoding="utf-8") == text, f"{path.name} is stale: run `make hardware`"
    assert gen_hardware.main(["--check"]) == 0


def test_check_names_a_stale_file(tmp_path, monkeypatch, capsys):
    stale = tmp_path / "bom.md"
    stale.write_text("old", encoding="utf-8")
    monkeypatch.setattr(gen_hardware, "OUT_BOM_MD", stale)
    assert gen_hardware.main(["--check"]) == 1
    assert "bom.md is stale" in capsys.readouterr().err


def test_low_cost_build_is_under_budget_and_totals_add_up():
    bom = gen_hardware.load_bom()
    assert bom.prices_as_of == "2026-12"
    assert set(bom.options) == {"as7341", "c12880ma", "seabreeze"}
    low_cost = bom.total_eur("as7341")
    assert low_cost < bom.budget_eur <= 300
    # the micro-spectrometer sits between the two: spectral at a fraction of the USB spectrometer's price
    assert low_cost < bom.total_eur("c12880ma") < bom.total_eur("seabreeze") / 3
    common = sum(p.qty * p.unit_eur for p in bom.parts if p.option is None)
    assert bom.total_eur("as7341") == pytest.approx(common + sum(p.qty * p.unit_eur for p in bom.parts
                                                                  if p.option == "as7341"))
    text = (HW / "bom.md").read_text(encoding="utf-8")
    assert f"**{low_cost:,.2f}**" in text and "estimates" in text


def test_every_mcu_pin_is_wired_to_a_declared_terminal():
    with open(HW / "pinout.toml", "rb") as fh:
        pinout = {k: v for k, v in tomllib.load(fh).items() if isinstance(v, dict)}
    wiring = gen_hardware.load_wiring(gen_hardware.load_bom())
    pinned = {w.a.split(".", 1)[1]: w.pin for w in wiring.wires if w.pin}
    assert pinned == {name: f"P{p['port']}{p['pin']}" for name, p in pinout.items()}
    table = (HW / "wiring.md").read_text(encoding="utf-8")
    for name, pin in pinned.items():
        assert f"| {pin} | `{name}` |" in table


def test_every_printed_part_of_the_bom_is_one_the_cad_makes():
    stls = {p.stl for p in gen_hardware.load_bom().parts if p.stl}
    assert {"slider", "holder_frame", "panel_mount", "led_mount", "detector_tube"} <= stls


@pytest.mark.parametrize("change, message", [
    (("qty = 3\ndescription = \"Micro servo", "qty = 0\ndescription = \"Micro servo"), "part servo: qty"),
    (("unit_eur = 18.0", "unit_eur = -1.0"), "part psu: unit_eur"),
    (("option = \"as7341\"\nqty = 1\ndescription = \"AS7341", "option = \"cheap\"\nqty = 1\ndescription = \"AS7341"),
     "option 'cheap'"),
    (("id = \"psu\"", "id = \"mcu\""), "id is used twice"),
])
def test_bad_bom_is_refused_by_item(tmp_path, change, message):
    text = (HW / "bom.toml").read_text(encoding="utf-8")
    assert change[0] in text
    path = tmp_path / "bom.toml"
    path.write_text(text.replace(change[0], change[1], 1), encoding="utf-8")
    with pytest.raises(gen_hardware.HardwareError, match=message):
        gen_hardware.load_bom(path)


def test_wiring_refuses_an_unwired_pin_and_an_unknown_terminal(tmp_path):
    bom = gen_hardware.load_bom()
    pinout = (HW / "pinout.toml").read_text(encoding="utf-8")
    extra_pin = tmp_path / "pinout.toml"
    extra_pin.write_text(pinout + "\n[spare_gpio]\nport = \"C\"\npin = 5\n", encoding="utf-8")
    with pytest.raises(gen_hardware.HardwareError, match="spare_gpio have no"):
        gen_hardware.load_wiring(bom, HW / "wiring.toml", extra_pin)
    wiring = tmp_path / "wiring.toml"
    wiring.write_text((HW / "wiring.toml").read_text(encoding="utf-8").replace('"driver.STEP"', '"driver.STP"'),
                      encoding="utf-8")
    with pytest.raises(gen_hardware.HardwareError, match=r"stepper_step.*driver\.STP"):
        gen_hardware.load_wiring(bom, wiring)


def test_cli_reports_a_bad_source_without_a_traceback(tmp_path, monkeypatch, capsys):
    bad = tmp_path / "bom.toml"
    bad.write_text("schema = 1\ncurrency = \"EUR\"\n[[part]]\nid = 3\n", encoding="utf-8")
    monkeypatch.setattr(gen_hardware, "BOM", bad)
    monkeypatch.setattr(gen_hardware.load_bom, "__defaults__", (bad,))
    assert gen_hardware.main(["--check"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gen_hardware: error:") and "Traceback" not in err


def _validation(alpha: float = 0.0031) -> dict:
    """The shape `trimeter bench report` writes to docs/validation.json (its stamp and bench sensor's runs)."""
    def row(build_id, build, a):
        return {"id": build_id, "build": build, "materials": "all", "alpha_p95": a, "sigma_t_rel_p95": 0.0114,
                "g_p95": 0.0084, "flagged": 4, "values": 54}
    runs = [{"noise": noise, "draws": draws, "material_count": 6,
             "builds": [row("seabreeze-slit", "seabreeze (slit)", 0.0019 + noise),
                        {**row("as7341-band-aware", "AS7341 band-aware", alpha + noise), "materials": "inks"},
                        row("as7341-band-aware", "AS7341 band-aware", alpha + noise),
                        row("c12880ma", "c12880ma", 0.0039 + noise)]}
            for noise, draws in ((0.0, 1), (0.005, 3))]
    return {"stamp": {"commit": "0123456789abcdef", "date_utc": "2026-12-06 04:30 UTC", "uncommitted_changes": False},
            "builds": {"thickness_mm": 0.4, "runs": runs}}


def test_accuracy_section_is_each_option_s_bench_build_with_where_and_when_it_was_measured():
    bom = gen_hardware.load_bom()
    text = gen_hardware.render_bom(bom, _validation()).split("## Accuracy of each build", 1)[1]
    assert "from commit `0123456789ab` on 2026-12-06 04:30 UTC" in text
    assert "(../docs/validation.md#each-build)" in text
    title = bom.options["as7341"]
    assert f"| {title} | AS7341 band-aware | none | 0.0031 | 1.14 % | 0.0084 | 4 of 54 |" in text
    assert f"| {title} | AS7341 band-aware | 0.5 % (3 draws) | 0.0081 |" in text
    assert f"| {bom.options['seabreeze']} | seabreeze (slit) | none | 0.0019 |" in text
    assert text.count("AS7341 band-aware") == 2  # the materials-set "all" rows only, one per noise level


def test_check_fails_when_bom_md_is_stale_against_the_measured_figures(tmp_path, monkeypatch, capsys):
    figures = tmp_path / "validation.json"
    figures.write_text(json.dumps(_validation()), encoding="utf-8")
    monkeypatch.setattr(gen_hardware, "VALIDATION_JSON", figures)
    bom_md = tmp_path / "bom.md"
    bom_md.write_text(gen_hardware.outputs()[gen_hardware.OUT_BOM_MD], encoding="utf-8")
    outputs = gen_hardware.outputs
    monkeypatch.setattr(gen_hardware, "outputs", lambda: {bom_md: outputs()[gen_hardware.OUT_BOM_MD]})
    assert gen_hardware.main(["--check"]) == 0
    figures.write_text(json.dumps(_validation(alpha=0.0042)), encoding="utf-8")  # a new bench report
    assert gen_hardware.main(["--check"]) == 1
    assert "bom.md is stale" in capsys.readouterr().err


def test_the_committed_bom_links_a_section_the_validation_page_has():
    text = (HW / "bom.md").read_text(encoding="utf-8")
    assert "../docs/validation.md#each-build" in text
    page = (ROOT / "docs" / "validation.md").read_text(encoding="utf-8")
    assert "\n## Each build\n" in page


@pytest.mark.parametrize("change, message", [
    (('accuracy_build = "as7341-band-aware"', 'accuracy = "α p95 0.003"'), "accuracy is measured, not typed"),
    (('accuracy_build = "as7341-band-aware"', "accuracy_build = 3"), "accuracy_build must name a build"),
])
def test_bad_accuracy_build_is_refused(tmp_path, change, message):
    text = (HW / "bom.toml").read_text(encoding="utf-8")
    assert change[0] in text
    path = tmp_path / "bom.toml"
    path.write_text(text.replace(change[0], change[1], 1), encoding="utf-8")
    with pytest.raises(gen_hardware.HardwareError, match=message):
        gen_hardware.load_bom(path)


def test_a_build_the_figures_lack_or_no_figures_are_refused_clearly(tmp_path):
    bom = gen_hardware.load_bom()
    doc = _validation()
    for run in doc["builds"]["runs"]:
        run["builds"] = [r for r in run["builds"] if r["id"] != "seabreeze-slit"]
    with pytest.raises(gen_hardware.HardwareError, match=r"\[options.seabreeze\] accuracy_build 'seabreeze-slit' is "
                                                         r"not a build of .*\(as7341-band-aware, c12880ma\)"):
        gen_hardware.render_bom(bom, doc)
    with pytest.raises(gen_hardware.HardwareError, match="run `trimeter bench report`"):
        gen_hardware.load_validation(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text('{"stamp": {}}', encoding="utf-8")
    with pytest.raises(gen_hardware.HardwareError, match="bad.json"):
        gen_hardware.load_validation(tmp_path / "bad.json")
