"""The twin's flash storage seeded with a map table, as an instrument leaves the factory with one: the
image is made once per firmware build and table (a twin flashed over Modbus, then stopped) and copied
into each twin's state directory before its firmware starts, so a seeded twin starts as fast as an
empty one."""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

from trimeter.atomic import atomic_write
from trimeter.errors import InputError


def _template_dir() -> Path:
    import platformdirs

    root = os.environ.get("TRIMETER_CACHE_DIR") or platformdirs.user_cache_dir("trimeter")
    return Path(root) / "twin-storage"


def table_bytes(table: str | Path | bytes) -> bytes:
    """A table given as bytes or a file (a shipped map's name: maps/<name>.tlut), checked as the device
    would be given it (`trimeter map flash` refuses the same)."""
    from trimeter.maps.device_table import SUFFIX, DeviceTable
    from trimeter.paths import MAPS_DIR

    if isinstance(table, bytes):
        data = table
    else:
        path = Path(table)
        if not path.is_file() and (MAPS_DIR / f"{table}{SUFFIX}").is_file():
            path = MAPS_DIR / f"{table}{SUFFIX}"
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InputError(f"map_table: cannot read {path} ({exc.strerror or exc})") from None
    DeviceTable.from_bytes(data, source="the twin's map table")
    return data


def seed(storage: Path, binary: Path, table: bytes, twin: Callable) -> None:
    """Write a storage image holding `table` active in slot A to `storage` (made once, then copied).
    `twin`: the Twin class (passed in: the twin is above its storage), started to make the image."""
    fw = hashlib.sha256(binary.read_bytes()).hexdigest()[:16]
    template = _template_dir() / f"{fw}-{hashlib.sha256(table).hexdigest()[:16]}.bin"
    if not template.is_file():
        _make_template(template, binary, table, twin)
    storage.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(template, storage)


def _make_template(template: Path, binary: Path, table: bytes, Twin: Callable) -> None:
    from trimeter.device import Device

    with tempfile.TemporaryDirectory(prefix="trimeter-seed-") as tmp:
        with Twin(state_dir=tmp, firmware=binary) as twin:
            assert twin.modbus_port is not None  # set by start()
            device = Device.open(twin.modbus_port)
            try:
                device.flash_map(table, version=1)
            finally:
                device.close()
        # the firmware has exited cleanly (close()): its storage file is complete
        atomic_write(template, (Path(tmp) / "storage.bin").read_bytes())
