"""tools/model_effect_check.py: the held-out columns traced in pairs from one seed, the difference added and fitted."""

import importlib.util
import json

import pytest

from trimeter.formats.appearance import AppearanceMap
from trimeter.paths import MAPS_DIR, REPO_ROOT

DEVICE_MAP = MAPS_DIR / "device-n1.5-l0.8.tmap"


def _tool():
    spec = importlib.util.spec_from_file_location("model_effect_check", REPO_ROOT / "tools" / "model_effect_check.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    return tool


@pytest.mark.skipif(not DEVICE_MAP.exists(), reason="needs the shipped device map and its held-out set")
def test_the_series_pair_differs_only_through_c_and_resumes(tmp_path, capsys, monkeypatch):
    import trimeter.forward.transport as transport

    options = []
    traced = transport.trace_column

    def recording(*args, **kwargs):
        options.append(kwargs)
        return traced(*args, **kwargs)

    monkeypatch.setattr(transport, "trace_column", recording)
    tool, out = _tool(), tmp_path / "effect.json"
    args = [str(DEVICE_MAP), "--model", "series", "--paths", "8192", "--columns", "1", "--out", str(out)]
    assert tool.main(args) == 0
    # both traces of the pair model the faces as the map was traced (the shipped device maps: polarisation)
    polarised = AppearanceMap.load(DEVICE_MAP).recipe["polarisation"]
    assert polarised and options == [{"polarisation": True}, {"polarisation": True, "background_orders": 5}]
    doc = json.loads(out.read_text())
    (column,) = doc["columns"].values()
    # A and B bit for bit the same: the pair differs through C alone, which black (ρ 0.02) barely sees
    assert column["AB_same"] and doc["summary"]["AB_same_everywhere"]
    assert max(map(abs, column["dIb"])) < 0.05 * max(map(abs, column["dIw"]))
    assert doc["summary"]["materials"] == len(column["idx"]) < doc["summary"]["set_materials"]
    assert "A and B the same in both traces: True" in capsys.readouterr().out
    column["dIw"] = [0.0] * len(column["dIw"])  # a column already in --out is not traced again
    column["dIb"] = [0.0] * len(column["dIb"])
    out.write_text(json.dumps(doc))
    assert tool.main(args) == 0
    summary = json.loads(out.read_text())["summary"]
    assert summary["shift"]["alpha_95"] == 0.0 and summary["scores"]["as_traced"] == summary["scores"]["with_model"]


def test_refuses_what_it_cannot_compare(tmp_path, capsys):
    tool = _tool()
    assert tool.main([str(MAPS_DIR / "ideal-n1.5-l0.5.tmap"), "--out", str(tmp_path / "x.json")]) == 1
    assert "a device map" in capsys.readouterr().err
    assert tool.main([str(DEVICE_MAP), "--paths", "10", "--out", str(tmp_path / "x.json")]) == 1
    other = str(MAPS_DIR / "device-n1.5-l0.4.tmap")
    assert tool.main([str(DEVICE_MAP), "--fit-map", other, "--out", str(tmp_path / "x.json")]) == 1
    assert "not the same set-up" in capsys.readouterr().err
    assert AppearanceMap.load(DEVICE_MAP).recipe["polarisation"]  # the shipped device maps track it already
    assert tool.main([str(DEVICE_MAP), "--model", "polarisation", "--out", str(tmp_path / "x.json")]) == 1
    assert "traced with polarisation already" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
