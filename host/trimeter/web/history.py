"""The measurement history: an SQLite index (stdlib sqlite3, WAL) over the results directories.

The directories stay the source of truth; the index only makes them searchable. It is rebuilt from
them when its file is missing, fails `PRAGMA integrity_check`, has another schema or indexes another
results directory; at every open, directories it lacks (runs made before it existed, or by
`trimeter measure` meanwhile) are added and entries whose directory is gone are dropped.
Each thread gets its own connection. WAL with synchronous=NORMAL: a writer killed mid-insert loses at
most that insert, never the file (the next open adds the directory again).
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import sqlite3
import threading
from collections.abc import Iterator
from datetime import date, datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from trimeter.errors import InputError, OutputError, TrimeterError
from trimeter.inversion.flags import FitFlag, describe
from trimeter.paths import real_subdirectory
from trimeter.results.reader import MEASUREMENT_FILE, read_parameters, read_record
from trimeter.results.writer import PARTIAL_PREFIX

log = logging.getLogger("trimeter.web")

SCHEMA_VERSION = 2
# A results directory's name: the writer's UTC stamp, an optional label and a uniqueness suffix.
ID_PATTERN = re.compile(r"\d{8}T\d{6}Z(?:-[A-Za-z0-9._-]+)?")
MAX_PAGE = 500
MAX_OFFSET = 2**62   # SQLite's integers are 64-bit: a larger offset is an overflow, not an empty page

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE measurements (
    id TEXT PRIMARY KEY,
    written_utc TEXT NOT NULL,
    label TEXT,
    instrument TEXT,                   -- the name of the instrument that measured it
    method TEXT,
    thicknesses_mm TEXT NOT NULL,      -- JSON list
    maps TEXT NOT NULL,                -- JSON list
    bins INTEGER NOT NULL,
    flagged_bins INTEGER NOT NULL,     -- bins whose combined fit carries any flag
    flags INTEGER NOT NULL,            -- OR of every bin's flags
    incomplete TEXT,
    refit_of TEXT,
    advice TEXT NOT NULL,              -- JSON list of sentences
    mtime REAL NOT NULL
);
CREATE INDEX measurements_written ON measurements (written_utc);
"""
_COLUMNS = ("id", "written_utc", "label", "instrument", "method", "thicknesses_mm", "maps", "bins", "flagged_bins",
            "flags", "incomplete", "refit_of", "advice", "mtime")


def is_measurement_id(text: str) -> bool:
    return bool(ID_PATTERN.fullmatch(text)) and ".." not in text


def _stamp_of(name: str) -> str:
    stamp = datetime.strptime(name[:16], "%Y%m%dT%H%M%SZ").replace(tzinfo=timezone.utc)
    return stamp.isoformat(timespec="seconds")


def summarize(directory: Path) -> dict | None:
    """The index row of one results directory, or None when it is not one (no readable measurement.json)."""
    if not is_measurement_id(directory.name) or real_subdirectory(directory.parent, directory.name) is None:
        return None
    try:
        meta = read_record(directory)
        mtime = (directory / MEASUREMENT_FILE).stat().st_mtime
    except (OSError, InputError, RecursionError):
        return None
    try:
        flags = read_parameters(directory)[0].flags
    except (InputError, OverflowError):
        flags = np.zeros(0, np.int64)  # no fit to index (a damaged or missing parameters.json): listed unflagged
    written = meta.get("written_utc")
    try:
        written = datetime.fromisoformat(str(written)).astimezone(timezone.utc).isoformat(timespec="seconds")
    except (TypeError, ValueError):
        written = _stamp_of(directory.name)

    def listed(key: str) -> list:
        value = meta.get(key)
        return value if isinstance(value, list) else []

    return {"id": directory.name, "written_utc": written, "label": _text(meta.get("label")),
            "instrument": _text(meta.get("instrument")),
            "method": _text(meta.get("method")), "thicknesses_mm": json.dumps(listed("thicknesses_mm")),
            "maps": json.dumps(listed("maps")), "bins": int(flags.size),
            "flagged_bins": int(np.count_nonzero(flags)),
            "flags": int(np.bitwise_or.reduce(flags)) if flags.size else 0,
            "incomplete": _text(meta.get("incomplete")), "refit_of": _text(meta.get("refit_of")),
            "advice": json.dumps([a for a in listed("advice") if isinstance(a, str)]), "mtime": mtime}


def _text(value: object) -> str | None:
    return value if isinstance(value, str) and value else None


def row_to_json(row: dict) -> dict:
    out = dict(row)
    for key in ("thicknesses_mm", "maps", "advice"):
        out[key] = json.loads(out[key])
    out["flag_names"] = [] if not out["flags"] else describe(out["flags"]).split("|")
    out.pop("mtime", None)
    return out


def parse_day_or_time(text: str, name: str, *, end: bool = False) -> str:
    """An ISO date or date-time from a query, as the index's UTC text; a bare date as `end` includes that day."""
    try:
        if re.fullmatch(r"\d{4}-\d{2}-\d{2}", text):
            day = date.fromisoformat(text) + timedelta(days=1 if end else 0)
            moment = datetime(day.year, day.month, day.day, tzinfo=timezone.utc)
        else:
            moment = datetime.fromisoformat(text)
            moment = moment.replace(tzinfo=timezone.utc) if moment.tzinfo is None else moment.astimezone(timezone.utc)
    except (ValueError, OverflowError):  # OverflowError: a day after 9999-12-31 or a UTC time before year 1
        raise InputError(f"{name}: {text[:64]!r} is not a date (YYYY-MM-DD) or an ISO date-time within "
                         f"0001-01-01..9999-12-31 UTC") from None
    return moment.isoformat(timespec="seconds")


class IndexUnavailable(TrimeterError):
    """The index was found damaged while serving and is being rebuilt from the results directories."""

    RETRY_AFTER_S = 2


class History:
    """The index of `root`'s results directories, kept in the SQLite file `db_path`. An index found damaged
    while in use (a query fails with a database error) is rebuilt on a thread of its own; meanwhile every
    call raises IndexUnavailable."""

    def __init__(self, root: Path, db_path: Path) -> None:
        self.root = Path(root)
        self.db_path = Path(db_path)
        self._local = threading.local()
        self._write_lock = threading.Lock()
        self._generation = 0          # bumped by a rebuild: every thread's connection to the old file is replaced
        self._rebuilding: threading.Thread | None = None
        self.notes: list[str] = []   # what opening found (a rebuild and why)

    # ------------------------------------------------------------------------------ opening
    def _connect(self) -> sqlite3.Connection:
        con = sqlite3.connect(self.db_path, timeout=10.0, isolation_level=None, check_same_thread=True)
        con.row_factory = sqlite3.Row
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA synchronous=NORMAL")
        return con

    @property
    def db(self) -> sqlite3.Connection:
        con = getattr(self._local, "con", None)
        if con is not None and getattr(self._local, "generation", 0) != self._generation:
            con.close()
            con = None
        if con is None:
            con = self._local.con = self._connect()
            self._local.generation = self._generation
        return con

    @contextlib.contextmanager
    def _in_use(self) -> Iterator[None]:
        """Around every query: a database error means a damaged index, rebuilt in the background."""
        if self._rebuilding is not None:
            raise IndexUnavailable("the history index is being rebuilt from the results directories")
        try:
            yield
        except sqlite3.DatabaseError as exc:
            self._start_rebuild(str(exc))
            raise IndexUnavailable(f"the history index was found damaged ({exc}); it is being rebuilt from the "
                                   f"results directories") from None

    def _start_rebuild(self, why: str) -> None:
        with self._write_lock:
            if self._rebuilding is not None:
                return
            log.warning("history index %s damaged (%s): rebuilding it from %s", self.db_path, why, self.root)
            self._rebuilding = threading.Thread(target=self._rebuild, args=(why,), name="trimeter-history-rebuild",
                                                daemon=True)
        self._rebuilding.start()

    def _rebuild(self, why: str) -> None:
        try:
            self._generation += 1
            self._recreate()
            added, _ = self.sync()
            self.notes.append(f"history index rebuilt while serving ({why}): {added} measurement(s)")
        except (sqlite3.Error, OSError) as exc:
            log.error("the history index %s could not be rebuilt (%s); retried at the next damaged query",
                      self.db_path, exc)
        finally:
            self.close()
            self._rebuilding = None

    def open(self) -> list[str]:
        """Check the index (rebuilding it if needed) and bring it up to date with the directories."""
        try:
            return self._open()
        except sqlite3.Error as exc:  # e.g. a read-only data directory: a clear error, not a traceback
            raise OutputError(f"the history index {self.db_path} cannot be opened or written ({exc})") from None

    def _open(self) -> list[str]:
        self.db_path.parent.mkdir(parents=True, exist_ok=True)
        problem = None if self.db_path.exists() else "no index yet"
        if problem is None:
            try:
                problem = self._problem()
            except sqlite3.DatabaseError as exc:
                problem = f"the index file is damaged ({exc})"
        if problem:
            self._recreate()
            self.notes.append(f"history index built from the results directories ({problem})")
        added, removed = self.sync()
        if added or removed:
            self.notes.append(f"history index: {added} measurement(s) added, {removed} gone")
        return self.notes

    def _problem(self) -> str | None:
        con = self.db
        if con.execute("PRAGMA integrity_check").fetchone()[0] != "ok":
            return "the index file failed its integrity check"
        meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
        if meta.get("schema") != str(SCHEMA_VERSION):
            return "the index has another schema version"
        if meta.get("root") != str(self.root.resolve()):
            return f"the index was of {meta.get('root')}"
        return None

    def _recreate(self) -> None:
        self.close()
        for suffix in ("", "-wal", "-shm", "-journal"):
            Path(f"{self.db_path}{suffix}").unlink(missing_ok=True)
        con = self.db
        con.executescript(_SCHEMA)
        con.executemany("INSERT INTO meta VALUES (?, ?)",
                        [("schema", str(SCHEMA_VERSION)), ("root", str(self.root.resolve()))])

    def close(self) -> None:
        con = getattr(self._local, "con", None)
        if con is not None:
            con.close()
            self._local.con = None

    # ------------------------------------------------------------------------------ writing
    def sync(self) -> tuple[int, int]:
        """Add directories the index lacks (or that changed), drop entries whose directory is gone."""
        on_disk = {}
        if self.root.is_dir():
            for path in self.root.iterdir():
                if not path.name.startswith(PARTIAL_PREFIX) and is_measurement_id(path.name) \
                        and real_subdirectory(self.root, path.name) is not None:
                    try:
                        on_disk[path.name] = (path / MEASUREMENT_FILE).stat().st_mtime
                    except OSError:
                        continue
        known = dict(self.db.execute("SELECT id, mtime FROM measurements").fetchall())
        rows = [row for name, mtime in on_disk.items() if known.get(name) != mtime
                if (row := summarize(self.root / name)) is not None]
        gone = [name for name in known if name not in on_disk]
        with self._write_lock:
            con = self.db
            con.execute("BEGIN IMMEDIATE")
            try:
                con.executemany(f"INSERT OR REPLACE INTO measurements VALUES ({', '.join('?' * len(_COLUMNS))})",
                                [tuple(row[c] for c in _COLUMNS) for row in rows])
                con.executemany("DELETE FROM measurements WHERE id = ?", [(name,) for name in gone])
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        return len(rows), len(gone)

    def add(self, directory: Path) -> dict | None:
        """Index one (new) results directory; returns its row as JSON, or None if it is not one."""
        row = summarize(Path(directory))
        if row is None:
            return None
        with self._in_use(), self._write_lock:
            self.db.execute(f"INSERT OR REPLACE INTO measurements VALUES ({', '.join('?' * len(_COLUMNS))})",
                            tuple(row[c] for c in _COLUMNS))
        return row_to_json(row)

    # ------------------------------------------------------------------------------ reading
    def get(self, measurement_id: str) -> dict | None:
        if not is_measurement_id(measurement_id):
            return None
        with self._in_use():
            row = self.db.execute("SELECT * FROM measurements WHERE id = ?", (measurement_id,)).fetchone()
        return None if row is None else row_to_json(dict(row))

    def search(self, *, label: str | None = None, instrument: str | None = None, since: str | None = None,
               until: str | None = None, flagged: bool | None = None, flag: str | None = None, limit: int = 50,
               offset: int = 0) -> tuple[list[dict], int]:
        """(one page of rows, newest first; how many match). Dates as parse_day_or_time gives them."""
        where: list[str] = []
        args: list[object] = []
        if label:
            where.append("label LIKE ? ESCAPE '\\'")
            args.append("%" + re.sub(r"([%_\\])", r"\\\1", label) + "%")
        if instrument:
            where.append("instrument = ?")
            args.append(instrument)
        if since:
            where.append("written_utc >= ?")
            args.append(since)
        if until:
            where.append("written_utc < ?")
            args.append(until)
        if flagged is not None:
            where.append("flagged_bins > 0" if flagged else "flagged_bins = 0")
        if flag:
            try:
                bit = FitFlag[flag.upper()]
            except KeyError:
                known = ", ".join(str(f.name) for f in FitFlag if f)
                raise InputError(f"flag: {flag!r} is not one of {known}") from None
            where.append("flags & ? != 0")
            args.append(int(bit))
        if not 1 <= limit <= MAX_PAGE:
            raise InputError(f"limit: must be within 1..{MAX_PAGE}, got {limit}")
        if not 0 <= offset <= MAX_OFFSET:
            raise InputError(f"offset: must be within 0..{MAX_OFFSET}, got {offset}")
        clause = (" WHERE " + " AND ".join(where)) if where else ""
        with self._in_use():
            total = self.db.execute(f"SELECT COUNT(*) FROM measurements{clause}", args).fetchone()[0]
            rows = self.db.execute(f"SELECT * FROM measurements{clause} ORDER BY written_utc DESC, id DESC "
                                   f"LIMIT ? OFFSET ?", [*args, limit, offset]).fetchall()
        return [row_to_json(dict(r)) for r in rows], total
