"""tools/gen_registers.py: the map's validation, the hash's meaning, --check, and that the C and
Python outputs agree with each other and with hardware/registers.toml."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("gen_registers", ROOT / "tools" / "gen_registers.py")
gen = importlib.util.module_from_spec(_spec)
sys.modules["gen_registers"] = gen
_spec.loader.exec_module(gen)

SOURCE_TEXT = gen.SOURCE.read_text(encoding="utf-8")


def load_with(tmp_path: Path, extra: str = "", replace: tuple[str, str] | None = None) -> dict:
    text = SOURCE_TEXT
    if replace:
        assert replace[0] in text
        text = text.replace(replace[0], replace[1], 1)
    path = tmp_path / "registers.toml"
    path.write_text(text + extra, encoding="utf-8")
    return gen.load(path)


def test_committed_outputs_match_the_map():
    from trimeter import registers

    m = gen.load()
    assert gen.regmap_hash(m) == registers.REGMAP_HASH
    header = (ROOT / "firmware" / "core" / "registers_gen.h").read_text()
    assert f"#define TRIMETER_REGMAP_HASH 0x{gen.regmap_hash(m):08X}u" in header
    assert len(registers.REGISTERS) == len(m["items"])
    # Every C address define agrees with the Python data.
    for name, address in re.findall(r"#define REG_(?:COIL|DI|IR|HR)_([A-Z0-9_]+?) (\d+)u\n", header):
        if name == "SPAN" or name.endswith(("_DEFAULT", "_MIN", "_MAX")):
            continue
        assert registers.BY_NAME[name.lower()].address == int(address)


@pytest.mark.parametrize("extra, message", [
    ('\n[[holding_register]]\nname = "clash"\naddress = 65\ntype = "u16"\naccess = "rw"\ndefault = 0\n',
     "address 65 already used by steps_per_mm"),
    ('\n[[holding_register]]\nname = "wide"\naddress = 63\ntype = "u32"\naccess = "rw"\ndefault = 0\n',
     "address 64 already used"),
    ('\n[[holding_register]]\nname = "steps_per_mm"\naddress = 200\ntype = "u16"\naccess = "rw"\ndefault = 0\n',
     "name already used"),
    ('\n[[holding_register]]\nname = "x"\naddress = 200\ntype = "u16"\naccess = "rw"\nmin = 5\n'
     'default = 2\n', "default 2 outside min..max 5..65535"),
    ('\n[[holding_register]]\nname = "x"\naddress = 200\ntype = "u16"\naccess = "rw"\n',
     "needs an explicit default"),
    ('\n[[holding_register]]\nname = "x"\naddress = 200\ntype = "u16"\nacess = "rw"\n',
     "unknown field 'acess'"),
    ('\n[[input_register]]\nname = "x"\naddress = 200\ntype = "u16"\naccess = "rw"\n',
     "access 'rw' not allowed"),
    ('\n[[holding_register]]\nname = "x"\naddress = 200\ntype = "u16"\naccess = "rw"\nmax = 70000\ndefault = 0\n',
     "max 70000 does not fit u16"),
    ('\n[[coil]]\nname = "x"\naddress = 60\ntype = "u16"\n', "type 'u16' not allowed"),
    ('\n[[holding_register]]\nname = "x"\naddress = 65535\ntype = "f32"\naccess = "rw"\ndefault = 0.0\n',
     "runs past address 65535"),
    ('\n[[holding_register]]\nname = "x"\naddress = 200\ntype = "u16"\naccess = "rw"\nenum = "state"\n'
     'default = 9\n', "default 9"),
])
def test_impossible_maps_are_refused_naming_the_item(tmp_path, extra, message):
    with pytest.raises(gen.MapError, match=re.escape(message)):
        load_with(tmp_path, extra)


def test_hash_follows_the_wire_not_the_prose(tmp_path):
    base = gen.regmap_hash(gen.load())
    reworded = load_with(tmp_path, replace=('description = "Cruise speed of the slider."',
                                            'description = "How fast the slider cruises."'))
    assert gen.regmap_hash(reworded) == base
    moved = load_with(tmp_path, replace=("max = 200.0\ndefault = 40.0", "max = 250.0\ndefault = 40.0"))
    assert gen.regmap_hash(moved) != base


def test_check_names_the_stale_file_and_writes_nothing(tmp_path, monkeypatch, capsys):
    outs = {name: tmp_path / Path(getattr(gen, name)).name
            for name in ("OUT_C_HEADER", "OUT_C_SOURCE", "OUT_PY", "OUT_MD")}
    monkeypatch.setattr(gen, "ROOT", tmp_path)
    for name, path in outs.items():
        monkeypatch.setattr(gen, name, path)
    assert gen.main([]) == 0
    assert gen.main(["--check"]) == 0
    stale = outs["OUT_PY"]
    stale.write_text(stale.read_text() + "# hand edit\n")
    capsys.readouterr()
    assert gen.main(["--check"]) == 1
    err = capsys.readouterr().err
    assert "registers.py is stale" in err and "registers_gen.h" not in err
    assert stale.read_text().endswith("# hand edit\n")  # --check never writes


def test_generated_python_is_plain_data():
    from trimeter import registers

    source = (ROOT / "host" / "trimeter" / "registers.py").read_text()
    assert "pymodbus" not in source
    reg = registers.BY_NAME["modbus_baud"]
    assert (reg.type, reg.words, reg.default, reg.allowed) == ("u32", 2, 19200, (9600, 19200, 38400, 57600, 115200))
    assert registers.HOLDING_REGISTERS["command"].enum == "command"
    assert registers.Command.HOME == 1 and registers.ENUMS["map_command"].ACTIVATE == 3
    with pytest.raises(AttributeError):
        reg.address = 0  # frozen
