"""Where the repository's declared-once files live (the package is installed editable from the repo)."""

import os
from pathlib import Path

import platformdirs

REPO_ROOT = Path(__file__).resolve().parents[2]
HARDWARE_DIR = REPO_ROOT / "hardware"
MAPS_DIR = REPO_ROOT / "maps"
GEOMETRY_FILE = HARDWARE_DIR / "geometry.toml"


def config_dir() -> Path:
    """The user's trimeter configuration directory (TRIMETER_CONFIG_DIR overrides it)."""
    return Path(os.environ.get("TRIMETER_CONFIG_DIR") or platformdirs.user_config_dir("trimeter"))


def data_dir() -> Path:
    """The user's trimeter data directory: calibration, results, spool (TRIMETER_DATA_DIR overrides it)."""
    return Path(os.environ.get("TRIMETER_DATA_DIR") or platformdirs.user_data_dir("trimeter"))
