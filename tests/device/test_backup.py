"""Configuration backups: TOML by name, read back to the same register words; what a backup may not
hold is one clear error, names another register map had are returned, not fatal."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from trimeter import registers as regs
from trimeter.device.backup import config_source_warning, dump_config, parse_config
from trimeter.device.client import CONFIG_NAMES, Identity, encode
from trimeter.errors import InputError

IDENTITY = Identity(regs.VENDOR_ID, regs.MODEL_ID, regs.FIRMWARE_VERSION, regs.REGMAP_HASH)


def _values():
    values = {}
    for name in CONFIG_NAMES:
        reg = regs.BY_NAME[name]
        # f32 defaults off their default; a tiny one (a wavelength polynomial's high-order coefficient) scaled,
        # since 0.1 + 9e-9 is 0.10000001 in its shortest form
        tiny = reg.type == "f32" and 0 < abs(reg.default) < 1e-3
        off = 0.1 if reg.max is None or reg.default + 0.1 <= reg.max else -0.1  # within the range (a reflectance)
        values[name] = (1.5 * reg.default if tiny else off + reg.default) if reg.type == "f32" else int(reg.default)
    return values


@pytest.mark.parametrize("legacy_printing", [False, True])
def test_dump_then_parse_gives_the_same_register_words(legacy_printing):
    """Also where another module set numpy's print options for the whole process (importing colour-science sets
    its 1.13 legacy mode, which prints six digits of an f32)."""
    values = _values()
    if legacy_printing:
        with np.printoptions(legacy="1.13"):
            text = dump_config(values, IDENTITY, "/dev/ttyUSB0")
    else:
        text = dump_config(values, IDENTITY, "/dev/ttyUSB0")
    assert "0.1000000" not in text  # f32 values in their shortest form
    parsed, unknown = parse_config(text, "backup.toml")
    assert unknown == [] and list(parsed) == list(CONFIG_NAMES)
    for name in CONFIG_NAMES:
        reg = regs.BY_NAME[name]
        assert encode(reg, parsed[name]) == encode(reg, values[name]), name


@pytest.mark.parametrize("text, message", [
    ("steps_per_mm = ", "not a configuration backup"),
    ("[host]\nmap = 'x'\n", "no [device] table"),
    ("[device]\n", "no [device] table"),
    ("[device]\nuptime_s = 5\n", "uptime_s is not a configuration item"),
    ("[device]\ncommand = 1\n", "command is not a configuration item"),
    ("[device]\nspeed_mm_s = true\n", "is not a number or a name"),
    ("[device]\nspeed_mm_s = [1, 2]\n", "speed_mm_s is a list, not a value"),
    ("[device]\n[device.sub]\nx = 1\n", "sub is a dict, not a value"),
    ("[device]\nlaser_power_mw = 3\n", "none of its items \\(laser_power_mw\\) is in this firmware's"),
])
def test_what_a_backup_may_not_hold_is_one_clear_error(text, message):
    with pytest.raises(InputError, match=message.replace("[", r"\[")):
        parse_config(text, "b.toml")


def test_names_of_another_register_map_are_returned_not_fatal():
    values, unknown = parse_config("[device]\nspeed_mm_s = 50.0\nlaser_power_mw = 3\n", "b.toml")
    assert values == {"speed_mm_s": 50.0} and unknown == ["laser_power_mw"]


def test_only_an_ignored_saved_configuration_is_warned_about():
    assert config_source_warning(regs.ConfigSource.SAVED) is None
    assert config_source_warning(regs.ConfigSource.DEFAULTS) is None  # nothing was ever saved
    assert "another register map" in config_source_warning(regs.ConfigSource.OTHER_REGISTER_MAP)
    assert "fails the firmware's checks" in config_source_warning(regs.ConfigSource.REFUSED)


def test_the_configuration_block_has_no_holes():
    """Device.write_config restores a backup in one request, which the firmware cross-checks as a
    whole, only because the block is contiguous: a write over an unmapped address is refused."""
    block = sorted((regs.BY_NAME[n] for n in CONFIG_NAMES), key=lambda r: r.address)
    assert block[0].address == 64 and block[-1].address + block[-1].words == regs.SPANS["holding_register"]
    for a, b in itertools.pairwise(block):
        assert a.address + a.words == b.address, (a.name, b.name)
