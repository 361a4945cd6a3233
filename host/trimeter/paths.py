"""Where the repository's declared-once files live (the package is installed editable from the repo)."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
HARDWARE_DIR = REPO_ROOT / "hardware"
MAPS_DIR = REPO_ROOT / "maps"
GEOMETRY_FILE = HARDWARE_DIR / "geometry.toml"
