"""Device configuration values are checked the same way from the command line, the web API and a backup's
import (device.client.encode): a boolean is no number, a number no boolean, infinity no value."""

from __future__ import annotations

import pytest

from trimeter import registers as regs
from trimeter.device.client import encode
from trimeter.errors import InputError

BOOL = next(r for r in regs.REGISTERS if r.type == "bool" and r.access == "rw")


@pytest.mark.parametrize("name,value", [("steps_per_mm", True), ("steps_per_mm", False), ("speed_mm_s", True),
                                        ("steps_per_mm", float("inf")), ("speed_mm_s", float("-inf")),
                                        ("homing_timeout_ms", float("inf")), ("steps_per_mm", None),
                                        ("steps_per_mm", [80]), ("modbus_baud", True)])
def test_booleans_and_non_finite_values_are_no_numbers(name, value):
    with pytest.raises(InputError, match=name):
        encode(regs.BY_NAME[name], value)


@pytest.mark.parametrize("value", [2, 0.5, 1.0, None, [1]])
def test_a_boolean_register_takes_only_booleans(value):
    with pytest.raises(InputError, match=BOOL.name):
        encode(BOOL, value)


def test_good_values_still_encode():
    assert encode(BOOL, True) == encode(BOOL, 1) == encode(BOOL, "on") == [1]
    assert encode(regs.BY_NAME["steps_per_mm"], 80) == encode(regs.BY_NAME["steps_per_mm"], "80")
