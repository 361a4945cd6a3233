"""Imports tools/gen_hardware.py and tools/hardware_parts.py (scripts run as `python -m tools.…`, not package
modules) with the repo's root on the path, as they run."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tools import gen_hardware, hardware_parts  # noqa: E402

__all__ = ["ROOT", "gen_hardware", "hardware_parts"]
