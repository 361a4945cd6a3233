"""Nothing captured is lost: checks before a capture, a spool for captures the results directory
could not take, and recovery of the `.partial-*` directories an interrupted write leaves behind.

- `prepare_results_dir(root, …)` before a capture: the directory exists or can be created, a file
  can be created and deleted in it, and it has room for a generous estimate of one results
  directory (twice: the spool may share its disk). Leftovers of earlier, interrupted writes are
  reported and moved to the spool (empty ones deleted).
- `write_or_spool(root, measurement)` after it: when the results directory cannot take the
  measurement (full disk, removed, read-only), the capture goes to the spool
  (`<data dir>/spool/<name>`; the temp directory's private `trimeter-spool-<uid>` if that fails too) and an
  OutputError names where it is and how to re-fit it.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from trimeter.atomic import describe_os_error, fsync_directory
from trimeter.errors import OutputError
from trimeter.domain import Measurement
from trimeter.paths import data_dir
from trimeter.results.writer import PARTIAL_PREFIX, expected_size_bytes, write_measurement

# A partial whose writer is still alive is a write in progress (another process on the same results
# directory), unless it is older than any write takes: then its pid was reused, after a reboot say.
IN_PROGRESS_MAX_AGE_S = 3600.0
_PARTIAL = re.compile(re.escape(PARTIAL_PREFIX) + r"(?:(\d+)-)?(.+)")


def spool_dir() -> Path:
    return data_dir() / "spool"


def _private_temp_spool() -> Path | None:
    """The last-resort spool in the shared temp directory: one per user, mode 0700, and refused when it is a
    link or someone else's (another local user could otherwise create it first and read or redirect captures)."""
    path = Path(tempfile.gettempdir()) / f"trimeter-spool-{os.getuid()}"
    try:
        path.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(path)
    except OSError:
        return None
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o077:
        return None
    return path


def _spool_roots(spool: Path | None) -> list[Path]:
    fallback = _private_temp_spool()
    return [spool or spool_dir(), *([fallback] if fallback else [])]


def refit_hint(directory: Path) -> str:
    """How to get parameters from a spooled capture: `trimeter fit` on its reflectances (one per thickness)."""
    refl = sorted(directory.glob("reflectances*.csv")) if directory.is_dir() else []
    if not refl:
        return f"its files are in {directory}"
    more = f" (likewise {', '.join(p.name for p in refl[1:])} with its thickness's map)" if len(refl) > 1 else ""
    return f"re-fit it with `trimeter fit --map MAP --input {refl[0]} -o params.csv`{more}"


class CaptureSpooled(OutputError):
    """The results directory could not take a measurement; its capture is kept at `path` instead."""

    def __init__(self, message: str, path: Path) -> None:
        super().__init__(message)
        self.path = path


# ------------------------------------------------------------------------------------- before
def prepare_results_dir(root: str | Path, *, n_bins: int, n_samples: int, spool: Path | None = None) -> list[str]:
    """Raise OutputError unless `root` can take a measurement of `n_samples` × `n_bins`; return notes
    on leftovers of interrupted writes (moved to the spool)."""
    root = Path(root)
    where = f"results directory {root}"
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{where} cannot be created ({describe_os_error(exc)}); choose another with --results "
                          f"or `trimeter config set --host results_dir DIR`") from None
    try:
        fd, probe = tempfile.mkstemp(dir=root, prefix=".write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{where} is not writable ({describe_os_error(exc)}); choose another with --results "
                          f"or `trimeter config set --host results_dir DIR`") from None
    need = 2 * expected_size_bytes(n_bins, n_samples)
    free = shutil.disk_usage(root).free
    if free < need:
        raise OutputError(f"{where} has {free / 1e6:.1f} MB free; a measurement needs {need / 1e6:.1f} MB: "
                          f"free some space or choose another with --results")
    return recover_partials(root, spool=spool)


@dataclass(frozen=True)
class Leftover:
    path: Path
    name: str            # the results directory it was going to become
    age_s: float
    files: int


def find_partials(root: str | Path, *, now: float | None = None) -> list[Leftover]:
    """`.partial-*` directories in `root` that no live write owns."""
    root = Path(root)
    now = time.time() if now is None else now
    found = []
    for path in sorted(root.glob(f"{PARTIAL_PREFIX}*")):
        match = _PARTIAL.fullmatch(path.name)
        if not match or not path.is_dir():
            continue
        try:
            entries = list(path.iterdir())
            age = now - max([path.stat().st_mtime] + [p.stat().st_mtime for p in entries])
        except OSError:
            continue  # gone meanwhile (its writer finished) or unreadable: not ours to judge
        pid = int(match[1]) if match[1] else None
        if pid is not None and _alive(pid) and age < IN_PROGRESS_MAX_AGE_S:
            continue
        found.append(Leftover(path, match[2], max(age, 0.0), len(entries)))
    return found


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True   # someone else's process
    except (OverflowError, OSError):
        return False
    return True


def _age(seconds: float) -> str:
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            return f"{seconds / size:.0f} {unit}"
    return f"{seconds:.0f} s"


def recover_partials(root: str | Path, *, spool: Path | None = None) -> list[str]:
    """Move leftovers holding files to the spool (`<name>-interrupted`), delete empty ones; return notes."""
    leftovers = find_partials(root)
    if not leftovers:
        return []
    notes = [f"{len(leftovers)} interrupted results write(s) found in {root}"]
    for left in leftovers:
        if not left.files:
            try:
                left.path.rmdir()
                notes.append(f"{left.path.name} ({_age(left.age_s)} old) was empty: deleted")
            except OSError as exc:
                notes.append(f"{left.path.name} ({_age(left.age_s)} old) is empty but could not be deleted "
                             f"({describe_os_error(exc)})")
            continue
        try:
            moved = _move_to_spool(left.path, f"{left.name}-interrupted", spool)
            notes.append(f"{left.path.name} ({_age(left.age_s)} old, {left.files} file(s)) moved to {moved}; "
                         f"{refit_hint(moved)}")
        except OutputError as exc:
            notes.append(f"{left.path.name} ({_age(left.age_s)} old, {left.files} file(s)) left in place: {exc}")
    return notes


def _unique(directory: Path, name: str) -> Path:
    target, n = directory / name, 1
    while target.exists():
        n += 1
        target = directory / f"{name}-{n}"
    return target


def _move_to_spool(source: Path, name: str, spool: Path | None) -> Path:
    """Rename within one file system; otherwise copy (under a partial name, then renamed) and delete."""
    errors = []
    for directory in _spool_roots(spool):
        try:
            directory.mkdir(parents=True, exist_ok=True)
            target = _unique(directory, name)
            try:
                os.rename(source, target)
            except OSError:
                staging = directory / f"{PARTIAL_PREFIX}{os.getpid()}-{target.name}"
                try:
                    shutil.copytree(source, staging)
                    os.rename(staging, target)
                except BaseException:
                    shutil.rmtree(staging, ignore_errors=True)
                    raise
                shutil.rmtree(source)
            fsync_directory(directory)
            return target
        except OSError as exc:
            errors.append(f"{directory}: {describe_os_error(exc)}")
    raise OutputError(f"no spool directory could take it ({'; '.join(errors)})")


# -------------------------------------------------------------------------------------- after
def write_or_spool(root: str | Path, measurement: Measurement, *, label: str | None = None,
                   spool: Path | None = None) -> Path:
    """write_measurement into `root`; if that fails, keep the capture in the spool and raise CaptureSpooled,
    which says where and how to re-fit it (OutputError if no spool could take it either)."""
    try:
        return write_measurement(root, measurement, label=label)
    except Exception as exc:  # noqa: BLE001 - whatever broke the write, the capture must be kept
        reason = describe_os_error(exc) if isinstance(exc, OSError) else str(exc)
        failure = f"cannot write the results to {root} ({reason})"
    errors = []
    for directory in _spool_roots(spool):
        try:
            # no figure or medium: the least to write, and all that a re-fit needs
            kept = write_measurement(directory, measurement, label=label, figure=False, medium=False)
        except Exception as exc:  # noqa: BLE001 - try the next spool
            errors.append(f"{directory}: {describe_os_error(exc) if isinstance(exc, OSError) else exc}")
            continue
        raise CaptureSpooled(f"{failure}; the capture is kept in {kept}: {refit_hint(kept)}", kept)
    raise OutputError(f"{failure}, and no spool directory could take the capture ({'; '.join(errors)})")
