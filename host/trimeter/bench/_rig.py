"""What the link and soak benchmarks share: a twin and an in-process Service opened the way `trimeter
serve` opens the instrument (host settings → Device.open), with the host's directories in a temporary
place so a benchmark never touches the user's calibration or results."""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from trimeter.device import Device
from trimeter.errors import InputError
from trimeter.paths import user_dirs_at
from trimeter.sequences.measure import map_for_thickness
from trimeter.sequences.service import Event, Service
from trimeter.sequences.settings import HostSettings
from trimeter.spectrometer import open_spectrometer
from trimeter.twin import FaultConfig, Twin
from trimeter.twin.storage import table_bytes


def host_dirs(root: Path) -> contextlib.AbstractContextManager[None]:
    """TRIMETER_DATA_DIR / TRIMETER_CONFIG_DIR under `root` while the benchmark runs (the calibration
    path is read from them), restored afterwards."""
    return user_dirs_at(data=root / "data", config=root / "config")


@contextlib.contextmanager
def twin_and_service(*, time_scale: float, seed: int, faults: FaultConfig | None = None,
                     settings: dict | None = None, on_event: Callable[[Event], None] | None = None,
                     root: Path | None = None) -> Iterator[tuple[Twin, Service, HostSettings]]:
    """Yields (twin, service, settings): a twin with no sample, and a Service for it (not yet connected)."""
    if not 0 < time_scale <= 1000:
        raise InputError(f"--time-scale must be within (0, 1000], got {time_scale:g}")
    with contextlib.ExitStack() as stack:
        if root is None:
            root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="trimeter-bench-")))
        stack.enter_context(host_dirs(root))
        host = HostSettings()
        # the instrument carries the table of the thickness `serve` measures, as a flashed one would
        table = table_bytes(map_for_thickness(host.thickness_mm).name)
        twin = stack.enter_context(Twin(time_scale=time_scale, faults=faults, state_dir=root / "twin", seed=seed,
                                        map_table=table))
        # the benches drive the button loop with the shipped map named, so that their figures are the link's and
        # the sequence's, not a first table read's; `settings` may name none (bench soak --device-table: serve's
        # default), and bench link --table times that read
        host.set("map", map_for_thickness(host.thickness_mm).name, source="benchmark")
        host.set("port", twin.modbus_port)
        host.set("spectrometer", twin.spectrometer_url)
        host.set("results_dir", str(root / "results"))
        for key, value in (settings or {}).items():
            host.set(key, value, source="benchmark")
        service = Service(lambda: _open_device(host), lambda: open_spectrometer(host.spectrometer), host,
                          on_event=on_event, device_clock=twin.sim_time, label="bench")
        stack.callback(service.close)
        yield twin, service, host


def _open_device(host: HostSettings) -> Device:
    """The twin's device as the host settings describe it (the rig set its port itself)."""
    return Device.open(host.port, address=host.address, baudrate=host.baudrate, timeout_s=host.timeout_s,
                       attempts=host.attempts, local_echo=bool(host.local_echo))
