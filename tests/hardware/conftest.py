"""Loads tools/gen_hardware.py and tools/hardware_parts.py (scripts, not package modules) once."""

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _load(name):
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


sys.path.insert(0, str(ROOT / "tools"))
hardware_parts = _load("hardware_parts")
gen_hardware = _load("gen_hardware")
