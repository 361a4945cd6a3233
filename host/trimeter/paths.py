"""Where the repository's declared-once files live (the package is installed editable from the repo)."""

import contextlib
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import platformdirs

REPO_ROOT = Path(__file__).resolve().parents[2]
HARDWARE_DIR = REPO_ROOT / "hardware"
MAPS_DIR = REPO_ROOT / "maps"
GEOMETRY_FILE = HARDWARE_DIR / "geometry.toml"
# the C the host's compiled kernel shares with the firmware (the inverse core, fit_core.h)
FIT_CORE_DIR = REPO_ROOT / "fit_core"


def config_dir() -> Path:
    """The user's trimeter configuration directory (TRIMETER_CONFIG_DIR overrides it)."""
    return Path(os.environ.get("TRIMETER_CONFIG_DIR") or platformdirs.user_config_dir("trimeter"))


def data_dir() -> Path:
    """The user's trimeter data directory: calibration, results, spool (TRIMETER_DATA_DIR overrides it)."""
    return Path(os.environ.get("TRIMETER_DATA_DIR") or platformdirs.user_data_dir("trimeter"))


@contextlib.contextmanager
def user_dirs_at(*, data: Path | None = None, config: Path | None = None, cache: Path | None = None) -> Iterator[None]:
    """TRIMETER_DATA_DIR, TRIMETER_CONFIG_DIR and TRIMETER_CACHE_DIR, those given, pointed at these while the
    block runs (a demo or a benchmark whose calibration must never touch the user's), restored afterwards, also
    on an error."""
    wanted = {"TRIMETER_DATA_DIR": data, "TRIMETER_CONFIG_DIR": config, "TRIMETER_CACHE_DIR": cache}
    saved = {key: os.environ.get(key) for key, value in wanted.items() if value is not None}
    os.environ.update({key: str(value) for key, value in wanted.items() if value is not None})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


# ------------------------------------------------------------------------ reading results safely
# A results directory may be written by anyone who can write the results root, and the web API serves
# it: a symbolic link in place of a record would read outside it. The directories of the root go through
# these; their files through trimeter.tables.open_checked (regular files only, not followed, bounded).
NAME_MAX = 255


def real_subdirectory(root: Path, name: str) -> Path | None:
    """root/name when it is a real directory (not a symbolic link) whose resolved path lies directly in
    the resolved root; None otherwise (missing, a link, a file, a name with a separator or too long)."""
    if not name or len(name.encode("utf-8", "surrogatepass")) > NAME_MAX or "/" in name or "\\" in name \
            or "\0" in name or name in (".", ".."):
        return None
    path = Path(root) / name
    try:
        if not stat.S_ISDIR(os.lstat(path).st_mode):
            return None
        if path.resolve(strict=True).parent != Path(root).resolve(strict=True):
            return None
    except (OSError, RuntimeError):  # RuntimeError: a link loop on the way to the root
        return None
    return path


def regular_files(directory: Path) -> list[Path]:
    """The regular files (not links, not FIFOs, not subdirectories) directly in `directory`, sorted by name."""
    out = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return []
    for entry in entries:
        try:
            if entry.is_file(follow_symlinks=False):
                out.append(Path(entry.path))
        except OSError:
            continue
    return sorted(out)
