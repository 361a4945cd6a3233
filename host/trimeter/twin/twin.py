"""The twin process: firmware sim + plant polling + optics + spectrometer pty + fault-injecting Modbus proxy.

Threads, each with one job and a wake-up pipe for a clean stop: plant poller (LED thermal models),
Modbus proxy, spectrometer server, control server (+ one thread per control client). The firmware is a
child process that dies with us (PR_SET_PDEATHSIG) and is stopped with SIGTERM on close().
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import functools
import json
import os
import secrets
import select
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any, Callable, Self

import numpy as np

from trimeter.errors import DeviceError, InputError, TrimeterError
from trimeter.paths import REPO_ROOT
from trimeter.twin.c12880 import C12880Light
from trimeter.twin.faults import FaultConfig, ModbusProxy, as_lamps_emit, as_optics_see_it
from trimeter.twin.optics import MapSource, Optics, material_names
from trimeter.twin.plant import PlantClient
from trimeter.twin.sensor import As7341Model
from trimeter.twin.specserver import SpectrometerServer
from trimeter.twin.storage import seed as seed_storage
from trimeter.twin.storage import table_bytes

FIRMWARE_DIR = REPO_ROOT / "firmware"
FIRMWARE_BINARY = FIRMWARE_DIR / "build" / "sim" / "trimeter-fw-sim"
READY_TIMEOUT_S = 20.0
POLL_INTERVAL_S = 0.05
_UNIX_PATH_MAX = 100  # sun_path is 108 bytes; keep a margin
MAX_REQUEST = 65536  # control-socket line limit
MONITOR_UPDATE = 2e-4  # relative emission change that is sent to the plant's photodiodes


def _die_with_parent() -> None:
    """Runs in the child before exec: SIGTERM it when the twin's process dies, however it dies."""
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1


def _firmware_is_current(binary: Path) -> bool:
    """The binary exists and, where the firmware sources are here, `make -q` finds nothing newer: a binary
    left over from before a register-map change would answer with the old map (and fail its identity check)."""
    if not binary.is_file():
        return False
    if binary != FIRMWARE_BINARY or not (FIRMWARE_DIR / "Makefile").is_file() or not shutil.which("make"):
        return True
    return subprocess.run(["make", "-q", "-C", str(FIRMWARE_DIR), "sim"], capture_output=True).returncode == 0


def ensure_firmware(binary: Path = FIRMWARE_BINARY) -> Path:
    """The firmware sim binary, (re)built with `make -C firmware sim` if it is missing or older than its
    sources (serialised by a lock)."""
    if _firmware_is_current(binary):
        return binary
    binary.parent.mkdir(parents=True, exist_ok=True)
    with open(binary.parent / ".build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not _firmware_is_current(binary):
            run = subprocess.run(["make", "-C", str(FIRMWARE_DIR), "sim"], capture_output=True, text=True)
            if run.returncode != 0 or not binary.is_file():
                tail = (run.stdout + run.stderr).strip().splitlines()[-3:]
                raise DeviceError(f"cannot build the firmware sim ({binary}): "
                                  f"{' | '.join(tail) or 'make gave no output'}")
    return binary


class Twin:
    """The simulated instrument. Use as a context manager; see README.md in this package for the contract."""

    def __init__(self, sample: str | None = None, thickness_mm: float = 0.4, time_scale: float = 1.0,
                 faults: FaultConfig | None = None, state_dir: str | Path | None = None,
                 appearance_map: MapSource = None, seed: int | None = None, white: str = "white",
                 firmware: str | Path | None = None, map_table: str | Path | bytes | None = None,
                 sensor: str = "spectrometer", address: int | None = None) -> None:
        """address: the firmware's Modbus address, over the one its saved configuration holds (as a jumper
        would); None: the saved one (1 by default).
        map_table: a device table (bytes, a .tlut file or a shipped map's name) the twin's storage
        holds active from the start, as an instrument carries its own; None: empty map slots.
        sensor: what the host reads, "spectrometer" or "as7341" (optics.SENSORS), or "c12880ma": the firmware's
        micro-spectrometer, read by the host over Modbus (spectrometer_url mcu:…)."""
        try:
            self.time_scale = float(time_scale)
        except (TypeError, ValueError):
            raise InputError(f"time_scale must be a number, got {time_scale!r}") from None
        if not np.isfinite(self.time_scale) or not 0.0 < self.time_scale <= 1000.0:
            raise InputError(f"time_scale must be within (0, 1000], got {time_scale!r}")
        self.faults = faults or FaultConfig()
        if not isinstance(self.faults, FaultConfig):
            raise InputError("faults must be a FaultConfig")
        if address is not None and (isinstance(address, bool) or not isinstance(address, int)
                                    or not 1 <= address <= 247):
            raise InputError(f"address must be a Modbus address within 1..247, got {address!r}")
        self.address = address
        self._sample, self._thickness_mm, self._sensor = sample, thickness_mm, sensor
        self._state_dir_arg, self._appearance_map, self._white = state_dir, appearance_map, white
        self._firmware = Path(firmware) if firmware else FIRMWARE_BINARY
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise InputError(f"seed must be a non-negative integer, got {seed!r}")
        self._rng = np.random.default_rng(seed)
        # The link faults' fates are keyed on this seed (faults.Fates), apart from the noise's generator: the
        # noise draws, which follow the exposures, must not shift them. No seed: a random one, kept to report.
        self.fault_seed = int(seed) if seed is not None else secrets.randbits(64)
        self._map_table = None if map_table is None else table_bytes(map_table)
        self._stop = threading.Event()
        self._optics_lock = threading.Lock()
        self._closers: list[Callable[[], object]] = []
        self._process: subprocess.Popen | None = None
        self._drain_thread: threading.Thread | None = None
        self.control = TwinControl(self)
        self.modbus_port: str | None = None  # set by start()
        self.spectrometer_port: str | None = None
        self.control_path: str | None = None
        self.last_plant_state: dict | None = None
        self.poll_error: str | None = None
        self._monitor_sent: dict | None = None  # what the plant's photodiode model was last given
        self._chip_light: C12880Light | None = None

    # ---------------------------------------------------------------------------------- lifecycle
    def __enter__(self) -> "Twin":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> "Twin":
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def _start(self) -> None:
        if self._state_dir_arg is None:
            self.state_dir = Path(tempfile.mkdtemp(prefix="trimeter-twin-"))
            self._closers.append(lambda: shutil.rmtree(self.state_dir, ignore_errors=True))
        else:
            self.state_dir = Path(self._state_dir_arg)
            self.state_dir.mkdir(parents=True, exist_ok=True)
        socket_dir = self.state_dir
        if len(str(socket_dir / "control.sock")) > _UNIX_PATH_MAX:
            socket_dir = Path(tempfile.mkdtemp(prefix="trimeter-"))
            self._closers.append(lambda: shutil.rmtree(socket_dir, ignore_errors=True))

        self.optics = Optics(self._appearance_map, white=self._white, sensor=self._sensor)
        if self._sample is not None:  # before anything is launched: a bad sample fails fast
            self.optics.insert_sample(self._sample, self._thickness_mm)

        binary = ensure_firmware(self._firmware)
        if self._map_table is not None:
            seed_storage(self.state_dir / "storage.bin", binary, self._map_table, Twin)
        fw_modbus = self.state_dir / "firmware-modbus"
        plant_path = socket_dir / "plant.sock"
        # The firmware removes these on a clean exit; after a crash (SIGKILL) the twin does.
        self._closers.append(functools.partial(fw_modbus.unlink, missing_ok=True))
        self._closers.append(functools.partial(plant_path.unlink, missing_ok=True))
        self._launch(binary, fw_modbus, plant_path)
        self.plant = PlantClient(str(plant_path))
        self._closers.append(self.plant.close)
        if self.faults.stuck_slider:
            self.plant.request(cmd="set", stuck_slider=True)
        if self.faults.endstop_broken:
            self.plant.request(cmd="set", endstop_broken=True)
        self._poll_once()
        self._feed_lamp_monitor()
        self._chip_light = C12880Light(self.optics) if self._sensor == "c12880ma" else None
        self._feed_chip_light(force=True)

        poller = threading.Thread(target=self._poll, name="twin-plant-poller", daemon=True)
        poller.start()
        self._closers.append(lambda: poller.join(timeout=5))

        self.proxy = ModbusProxy(os.path.realpath(fw_modbus), lambda: self.faults, self.fault_seed,
                                 self._on_request)
        self._closers.append(self.proxy.close)
        self.modbus_port = self.proxy.port

        model = self.optics.sensor
        bands = model.band_weights() if isinstance(model, As7341Model) else None
        self.spectrometer = SpectrometerServer(model.description(), model.wavelengths_nm, self._expose, bands=bands)
        self._closers.append(self.spectrometer.close)
        self.spectrometer_port = self.spectrometer.port

        self.control_path = str(socket_dir / "control.sock")
        self._control_server = ControlServer(self.control_path, self.control)
        self._closers.append(self._control_server.close)
        ports_file = self.state_dir / "ports.json"  # how `trimeter sim --ctl` finds this twin
        ports_file.write_text(json.dumps(self.control.ports()) + "\n")
        self._closers.append(lambda: ports_file.unlink(missing_ok=True))
        for name, target in (("modbus", self.proxy.port), ("spectrometer", self.spectrometer.port)):
            link = self.state_dir / name
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(target)
            self._closers.append(functools.partial(link.unlink, missing_ok=True))

    def _launch(self, binary: Path, fw_modbus: Path, plant_path: Path) -> None:
        log = open(self.state_dir / "firmware.log", "ab")
        self._closers.append(log.close)
        self._process = process = subprocess.Popen(
            [str(binary), "--storage", str(self.state_dir / "storage.bin"), "--modbus-link", str(fw_modbus),
             "--plant-link", str(plant_path), "--time-scale", repr(self.time_scale),
             *(["--address", str(self.address)] if self.address is not None else [])],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log,
            # PDEATHSIG fires when the *thread* that forked exits: only safe from the main thread.
            preexec_fn=_die_with_parent if threading.current_thread() is threading.main_thread() else None)
        self._closers.append(self._stop_firmware)
        stdout = process.stdout
        assert stdout is not None  # stdout=PIPE
        deadline, seen = time.monotonic() + READY_TIMEOUT_S, b""
        while b"ready" not in seen:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or process.poll() is not None:
                log.flush()
                tail = (self.state_dir / "firmware.log").read_text(errors="replace").strip().splitlines()[-2:]
                why = "exited" if process.poll() is not None else f"not ready within {READY_TIMEOUT_S:.0f} s"
                raise DeviceError(f"firmware sim {why}: {' | '.join(tail) or 'no output'}")
            if select.select([stdout], [], [], min(remaining, 0.2))[0]:
                chunk = os.read(stdout.fileno(), 4096)
                seen += chunk
                log.write(chunk)
        drain = threading.Thread(target=self._drain, args=(stdout, log), name="twin-fw-stdout",
                                 daemon=True)
        drain.start()
        self._drain_thread = drain  # joined by _stop_firmware, once stdout is at EOF

    @staticmethod
    def _drain(stream: IO[bytes], log: IO[bytes]) -> None:
        try:
            for chunk in iter(lambda: os.read(stream.fileno(), 4096), b""):
                log.write(chunk)
                log.flush()
        except (OSError, ValueError):
            pass

    def _stop_firmware(self) -> None:
        process = self._process
        if process is not None and process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=3)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=3)
        if self._drain_thread is not None:
            self._drain_thread.join(timeout=5)

    def close(self) -> None:
        self._stop.set()
        while self._closers:
            closer = self._closers.pop()
            with contextlib.suppress(Exception):  # keep going: every resource gets its chance to be released
                closer()
        if self._process is not None and self._process.stdout is not None:
            self._process.stdout.close()

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None and not self._stop.is_set()

    # ------------------------------------------------------------------------------- simulation
    @property
    def spectrometer_url(self) -> str:
        if self._sensor == "c12880ma":  # the firmware captures: the host reads it over the Modbus link
            return f"mcu:{self.modbus_port}"
        return f"sim:{self.spectrometer_port}"

    def sim_time(self) -> float:
        """Simulated seconds (the firmware's clock)."""
        return float(self.plant.state()["time_s"])

    def _poll_once(self) -> dict:
        state = as_optics_see_it(self.plant.state(), self.faults)
        with self._optics_lock:
            self.optics.advance(state, self.faults.lamp_failure)
            self.last_plant_state = state
        return state

    def _feed_lamp_monitor(self, force: bool = False) -> None:
        """Give the plant's photodiodes what only the twin knows: each lamp's emission (warm-up droop from the
        thermal model, dimming, failure) and a shutter stuck open. The plant applies LED level and shutter
        angle itself, at every ADC sample, so the readings follow the firmware's own timing."""
        with self._optics_lock:
            droop = {lamp: float(led.spectrum().sum() / led.spectrum(0.0).sum())
                     for lamp, led in (("panels", self.optics.panels), ("collimated", self.optics.collimated))}
        emission = self.faults.lamp_emission()
        wanted: dict[str, Any] = {
            f"lamp_{channel}": round(value * droop["collimated" if channel == "collimated" else "panels"], 5)
            for channel, value in emission.items()}
        wanted["shutter_leaking"] = self.faults.stuck_shutter_open
        sent = self._monitor_sent
        lamps = [k for k in wanted if k.startswith("lamp_")]
        if not force and sent is not None and sent["shutter_leaking"] == wanted["shutter_leaking"] and all(
                abs(wanted[k] - sent[k]) <= MONITOR_UPDATE * max(sent[k], 1e-3) for k in lamps):
            return
        self.plant.request(cmd="set", **wanted)
        self._monitor_sent = wanted

    def _feed_chip_light(self, force: bool = False) -> None:
        """The firmware sim's C12880MA composes its light from the plant's state; the twin gives it the
        optics' components when they change (trimeter.twin.c12880)."""
        if self._chip_light is None:
            return
        with self._optics_lock:
            requests = self._chip_light.requests(self.optics, force)
        for request in requests:
            self.plant.request(**request)

    def _poll(self) -> None:
        while not self._stop.wait(POLL_INTERVAL_S):
            try:
                self._poll_once()
                self._feed_lamp_monitor()
                self._feed_chip_light()
                self.poll_error = None
            except TrimeterError as exc:
                self.poll_error = str(exc)
                if self._stop.wait(0.5):
                    return

    def _expose(self, integration_time_us: int) -> tuple[np.ndarray, float]:
        """One spectrometer exposure, light averaged over the plant state at its start and end."""
        start = self._poll_once()
        if self._stop.wait(integration_time_us * 1e-6 / self.time_scale):
            raise DeviceError("twin is shutting down")
        end = self._poll_once()
        with self._optics_lock:
            lamp = self.faults.lamp_failure
            start, end = as_lamps_emit(start, self.faults), as_lamps_emit(end, self.faults)
            rate = 0.5 * (self.optics.rate(start, lamp) + self.optics.rate(end, lamp))
            counts = self.optics.sensor.expose(rate, integration_time_us, self._rng)
        return counts, float(end["time_s"])

    def _on_request(self, number: int) -> None:
        if self.faults.reset_at == number:
            self.plant.request(cmd="reset")


class TwinControl:
    """What a test or the demo can do to the twin; the control socket exposes exactly these methods."""

    def __init__(self, twin: Twin) -> None:
        self._twin = twin

    def insert_sample(self, name: str, thickness_mm: float = 0.4) -> None:
        with self._twin._optics_lock:
            self._twin.optics.insert_sample(name, thickness_mm)
        self._twin._feed_chip_light()

    def remove_sample(self) -> None:
        with self._twin._optics_lock:
            self._twin.optics.remove_sample()
        self._twin._feed_chip_light()

    def press_button(self) -> None:
        self._twin.plant.request(cmd="press_button")

    def reset_firmware(self) -> None:
        self._twin.plant.request(cmd="reset")

    def set_fault(self, **changes: Any) -> dict:
        twin = self._twin
        new = twin.faults.replace(**changes)
        if "stuck_slider" in changes:
            twin.plant.request(cmd="set", stuck_slider=new.stuck_slider)
        if "endstop_broken" in changes:
            twin.plant.request(cmd="set", endstop_broken=new.endstop_broken)
        twin.faults = new
        twin._feed_lamp_monitor(force=True)
        return new.to_dict()

    def truth(self) -> dict | None:
        with self._twin._optics_lock:
            return self._twin.optics.truth()

    def sim_time(self) -> float:
        return self._twin.sim_time()

    def materials(self) -> dict:
        return material_names()

    def ports(self) -> dict:
        t = self._twin
        return {"modbus_port": t.modbus_port, "spectrometer_port": t.spectrometer_port,
                "spectrometer_url": t.spectrometer_url, "control_path": t.control_path}

    def state(self) -> dict:
        t = self._twin
        plant = {k: v for k, v in t.plant.state().items() if k != "ok"}
        with t._optics_lock:
            sample = t.optics.sample
            lamps = {"panels": t.optics.panels.heat, "collimated": t.optics.collimated.heat}
        return {"sim_time_s": plant["time_s"], "plant": plant, "sample": sample.name if sample else None,
                "thickness_mm": sample.thickness_mm if sample else None, "faults": t.faults.to_dict(),
                "lamp_temperature": lamps, "counters": dict(t.proxy.counters), "fault_seed": t.fault_seed,
                "spectrometer": {"integration_time_us": t.spectrometer.integration_time_us,
                                 "acquisitions": t.spectrometer.acquisitions}}


_COMMANDS = {"ports": (), "state": (), "sim_time": (), "insert_sample": ("name", "thickness_mm"),
             "remove_sample": (), "press_button": (), "reset_firmware": (), "set_fault": None, "truth": (),
             "materials": ()}
_REPLY_KEY = {"ports": None, "state": "state", "sim_time": "sim_time_s", "set_fault": "faults", "truth": "truth",
              "materials": "materials"}


def _jsonable(value: object) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def dispatch(control: TwinControl, line: bytes) -> dict:
    """One control-socket request line → its reply object. Bad requests get ok:false and change nothing."""
    try:
        request = json.loads(line)
        if not isinstance(request, dict):
            raise InputError("a request must be a JSON object")
        cmd = request.pop("cmd", None)
        if cmd not in _COMMANDS:
            raise InputError(f"cmd must be one of {', '.join(_COMMANDS)}, got {cmd!r}")
        allowed = _COMMANDS[cmd]
        if allowed is not None and set(request) - set(allowed):
            raise InputError(f"{cmd} takes no field {sorted(set(request) - set(allowed))[0]!r}")
        result = getattr(control, cmd)(**request)
    except ValueError as exc:  # json.JSONDecodeError and InputError are ValueErrors
        return {"ok": False, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__}
    except (TrimeterError, TypeError) as exc:
        return {"ok": False, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__}
    key = _REPLY_KEY.get(cmd)
    if key is None:
        return {"ok": True, **(_jsonable(result) or {})}
    return {"ok": True, key: _jsonable(result)}


class ControlServer:
    """JSON-lines unix-socket server over a TwinControl (several clients at once, one thread each)."""

    def __init__(self, path: str, control: TwinControl) -> None:
        self.path, self._control = path, control
        if os.path.exists(path) or os.path.islink(path):
            os.unlink(path)
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(path)
        self._listener.listen(8)
        self._clients: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._wake_r, wake_w = os.pipe()
        self._wake_w: int | None = wake_w  # None once closed
        self._thread = threading.Thread(target=self._accept, name="twin-control", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while True:
            waitable: list[socket.socket | int] = [self._listener, self._wake_r]
            ready, _, _ = select.select(waitable, [], [])
            if self._wake_r in ready:
                return
            conn, _ = self._listener.accept()
            self._clients.append(conn)
            thread = threading.Thread(target=self._serve, args=(conn,), name="twin-control-client", daemon=True)
            self._threads.append(thread)
            thread.start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            with conn.makefile("rb") as stream:
                while line := stream.readline(MAX_REQUEST + 1):
                    if len(line) > MAX_REQUEST and not line.endswith(b"\n"):
                        while (rest := stream.readline(MAX_REQUEST)) and not rest.endswith(b"\n"):
                            pass  # skip the rest of the over-long line without holding it in memory
                        reply = {"ok": False, "error": f"request line longer than {MAX_REQUEST} bytes"}
                    else:
                        reply = dispatch(self._control, line)
                    conn.sendall(json.dumps(reply).encode() + b"\n")
        except OSError:
            pass

    def close(self) -> None:
        if self._wake_w is None:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        for conn in self._clients:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()
        for thread in self._threads:
            thread.join(timeout=5)
        self._listener.close()
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._wake_w = None
        if os.path.exists(self.path):
            os.unlink(self.path)


class TwinClient:
    """The twin's control methods over its control socket (for `trimeter sim` running elsewhere)."""

    def __init__(self, path: str, timeout_s: float = 10.0) -> None:
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        try:
            self._sock.connect(str(path))
        except OSError as exc:
            self._sock.close()
            raise DeviceError(f"cannot reach the twin's control socket {path}: {exc}") from None
        self._file = self._sock.makefile("rb")
        self._lock = threading.Lock()

    def _call(self, cmd: str, **fields: object) -> dict:
        with self._lock:
            try:
                self._sock.sendall(json.dumps({"cmd": cmd, **fields}).encode() + b"\n")
                line = self._file.readline()
            except OSError as exc:
                raise DeviceError(f"twin control socket: {exc}") from None
        if not line:
            raise DeviceError("twin control socket closed (is `trimeter sim` still running?)")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise DeviceError(f"twin refused {cmd}: {reply.get('error')}")
        return reply

    def ports(self) -> dict:
        reply = self._call("ports")
        reply.pop("ok")
        return reply

    def state(self) -> dict:
        return self._call("state")["state"]

    def sim_time(self) -> float:
        return float(self._call("sim_time")["sim_time_s"])

    def insert_sample(self, name: str, thickness_mm: float = 0.4) -> None:
        self._call("insert_sample", name=name, thickness_mm=thickness_mm)

    def remove_sample(self) -> None:
        self._call("remove_sample")

    def press_button(self) -> None:
        self._call("press_button")

    def reset_firmware(self) -> None:
        self._call("reset_firmware")

    def set_fault(self, **changes: Any) -> dict:
        return self._call("set_fault", **changes)["faults"]

    def materials(self) -> dict:
        return self._call("materials")["materials"]

    def truth(self) -> dict | None:
        truth = self._call("truth")["truth"]
        if truth is not None:
            for key in ("wavelengths_nm", "alpha", "sigma_t", "g"):
                truth[key] = np.asarray(truth[key], dtype=float)
        return truth

    def close(self) -> None:
        self._file.close()
        self._sock.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
