"""One job queue for the button and the web page, run by the one thread that talks to the instrument.

The worker thread runs `Service.serve` (the press-button loop); between its button polls it runs
what the web page asked for, so the device and the spectrometer only ever see that thread. A press
on the button becomes a job too (source "button"), so either way there is at most one job at a time:
asking for another while one is queued or running raises Busy with the current one.
Everything the API reads (status, events, jobs) is a snapshot made under a lock; the asyncio loop
never waits for the device.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import math
import secrets
import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from trimeter.errors import DeviceError, TrimeterError
from trimeter.sequences.service import EMPTY_HOLDER, FAILED, NEXT_SAMPLE, READY, WORKING, Event, Service

log = logging.getLogger("trimeter.web")

RECENT_JOBS = 20
RECENT_EVENTS = 50
# what the LED shows, in words for the page and the API
STATES = {READY: "ready", WORKING: "working", EMPTY_HOLDER: "asking_empty_holder", NEXT_SAMPLE: "next_sample",
          FAILED: "failed"}
# a press's outcome (Service.handle_press) → the job's end state
OUTCOMES = {"calibrated": "done", "measured": "done", "asked": "done", "refitted": "done", "refused": "failed",
            "failed": "failed", "incomplete": "failed", "expired": "failed"}


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


@dataclass
class Job:
    kind: str            # calibrate | measure | press
    source: str          # web | button
    params: dict = field(default_factory=dict)
    id: str = field(default_factory=lambda: secrets.token_hex(6))
    state: str = "queued"   # queued | running | done | failed
    outcome: str | None = None  # handle_press's: calibrated, measured, asked, refused, failed, incomplete
    message: str = ""
    measurement: str | None = None   # the results directory's name, when one was written
    flagged: bool = False            # the fit flagged bins (advice given)
    created_utc: str = field(default_factory=utc_now)
    finished_utc: str | None = None

    def to_json(self) -> dict:
        return dict(vars(self))


class Busy(Exception):
    def __init__(self, job: Job) -> None:
        super().__init__(f"job {job.id} ({job.kind}, {job.state}) is not finished")
        self.job = job


class LinkDown(Exception):
    """Work for the instrument asked for while its link is down: what it was asked under (the holder the
    operator emptied, the sample in place) cannot be vouched for once the device answers again."""


class Jobs:
    """The worker around one Service. `listeners` get every event and finished job as JSON (on the
    worker thread: hand them to another thread quickly)."""

    def __init__(self, service: Service, *, on_measurement: Callable[[Path], object] = lambda path: None) -> None:
        self.service = service
        self.on_measurement = on_measurement   # a results directory was written (the history indexes it)
        self.listeners: list[Callable[[dict], None]] = []
        self._lock = threading.Lock()
        self._queue: collections.deque[tuple[Job, Callable[[Job], str]]] = collections.deque()
        self._calls: collections.deque[tuple[concurrent.futures.Future, Callable]] = collections.deque()
        self.current: Job | None = None
        self.apart: Job | None = None      # the job running beside the queue (run_apart), if any
        self.recent: collections.deque[Job] = collections.deque(maxlen=RECENT_JOBS)
        self.events: collections.deque[dict] = collections.deque(maxlen=RECENT_EVENTS)
        self._status: dict[str, Any] = {"connected": False, "step": None, "progress": None, "lamp_drift": None,
                        "asking_reason": None, "map_table": None, "device_config": None}
        self._refresh_device = False
        self._link_down = False  # the device stopped answering (a poll's first failed try) and has not answered since
        self._stop = threading.Event()
        self.stopped: str | None = None   # why the worker ended on its own
        self._thread: threading.Thread | None = None
        service.on_event = self._chain(service.on_event, self.on_event)
        service.on_progress = self.on_progress

    @staticmethod
    def _chain(first: Callable[[Event], None], second: Callable[[Event], None]) -> Callable[[Event], None]:
        def both(event: Event) -> None:
            first(event)
            second(event)
        return both

    # ------------------------------------------------------------------------ worker thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="trimeter-instrument", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self.service.serve(stop=self._stop.is_set, between_polls=self.between_polls)
        except Exception as exc:  # e.g. no port configured: the page says so instead of a dead thread
            if not isinstance(exc, TrimeterError):
                log.exception("the instrument loop stopped")
            self.stopped = str(exc) if isinstance(exc, TrimeterError) else f"{type(exc).__name__}: {exc}"
            self.on_event(Event("stopped", f"the instrument loop stopped: {self.stopped}"))
            with self._lock:
                job = self.current
            if job is not None:  # nothing will run or finish it now
                job.message = job.message or f"the instrument loop stopped: {self.stopped}"
                self._finish(job, "failed")

    def stop(self, timeout_s: float = 30.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        with self._lock:
            calls, self._calls = list(self._calls), collections.deque()
        for future, _ in calls:
            future.cancel()

    def between_polls(self, outcome: str | None) -> None:
        """Service.serve's hook: close the button's job, refresh what the status shows, run queued work."""
        with self._lock:
            job = self.current
        if job is not None and job.source == "button" and job.state == "running":
            self._finish(job, outcome or "failed")
        if self._refresh_device:
            self._refresh_device = False
            self._read_device()
        while True:
            with self._lock:
                call = self._calls.popleft() if self._calls else None
            if call is None:
                break
            future, fn = call
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn(self.service))
                except BaseException as exc:  # handed to the caller, which reports it
                    future.set_exception(exc)
                    if isinstance(exc, DeviceError):
                        raise
        with self._lock:
            queued = self._queue.popleft() if self._queue else None
            if queued is not None:
                queued[0].state = "running"
        if queued is not None:
            self._run_job(*queued)

    def _run_job(self, job: Job, action: Callable[[Job], str]) -> None:
        try:
            outcome = self._outcome(job, action)
        except DeviceError as exc:
            job.message = str(exc)
            self._finish(job, "failed")
            raise  # Service.serve reconnects
        self._finish(job, outcome)

    @staticmethod
    def _outcome(job: Job, action: Callable[[Job], str]) -> str:
        """action(job)'s outcome; "failed" with the reason in job.message (a DeviceError is raised)."""
        try:
            return action(job)
        except DeviceError:
            raise
        except TrimeterError as exc:
            job.message = str(exc)
        except Exception as exc:
            # A bug in one job (a re-fit of a damaged record, say) must fail that job, not end the
            # instrument loop and leave the job "running" so that every later request is Busy.
            log.exception("job %s (%s) failed", job.id, job.kind)
            job.message = f"internal error: {type(exc).__name__}: {exc} (the serve log has the details)"
        return "failed"

    def _finish(self, job: Job, outcome: str) -> None:
        with self._lock:
            job.outcome = outcome
            job.state = OUTCOMES.get(outcome, "failed")
            job.finished_utc = utc_now()
            if self.current is job:
                self.current = None
                self._status["step"], self._status["progress"] = None, None
            if self.apart is job:
                self.apart = None
            self.recent.appendleft(job)
        self._tell({"type": "job", "job": job.to_json()})

    def _read_device(self) -> None:
        """What the status shows of the device and is only read between jobs: its configuration and
        whether its active map table is the one this host fits with."""
        from trimeter.sequences.measure import prepare_fit

        service = self.service
        try:
            config = {name: _plain(value) for name, value in service.connected_device().config().items()}
        except TrimeterError as exc:
            config = {"error": str(exc)}
        try:
            prepared = prepare_fit(service.resolve_samples(service.settings.serve_samples[:1]), service.settings.method)
            table = service.device_table(prepared).to_json()
        except TrimeterError as exc:
            table = {"error": str(exc)}
        with self._lock:
            self._status["device_config"], self._status["map_table"] = config, table

    # ------------------------------------------------------------------ service callbacks
    def on_event(self, event: Event) -> None:
        data = {key: _plain(value) for key, value in event.data.items() if key != "parameters"}
        path = event.data.get("path")
        if path is not None:
            data["measurement"] = Path(path).name
        record = {"type": "event", "kind": event.kind, "message": event.message, "time_utc": utc_now(), "data": data}
        with self._lock:
            self.events.appendleft(record)
            job = self.current
            expired = []
            if event.kind in ("connected", "link_restored"):
                self._status["connected"], self._link_down = True, False
                self._refresh_device = self._refresh_device or event.kind == "connected"
            elif event.kind in ("reconnecting", "link_lost"):
                self._status["connected"], self._link_down = False, True
                # queued work expires with the link: a confirmation given before is not one for the device
                # that answers next (it may have been reset, the holder changed meanwhile)
                expired, self._queue = [queued for queued, _ in self._queue], collections.deque()
                if self.current in expired:
                    self.current = None
            elif event.kind == "warmed_up":
                self._status["lamp_drift"] = {"drift": event.data.get("drift"), "time_utc": record["time_utc"]}
            elif event.kind == "empty_holder":
                self._status["asking_reason"] = event.data.get("reason")
            elif event.kind == "press" and job is None:
                job = self.current = Job("press", "button", state="running")
            elif event.kind == "measured" and "device_map_table" in event.data:
                self._status["map_table"] = _plain(event.data["device_map_table"])
            if job is not None:
                if event.kind == "measured":
                    job.measurement = data["measurement"]
                elif event.kind == "advice":
                    job.flagged = True
                elif event.kind in ("failed", "refused") or (event.kind == "empty_holder" and not job.message):
                    job.message = event.message
        for queued in expired:
            queued.message = f"expired before it ran: {event.message}; ask again once the device answers"
            self._finish(queued, "expired")
        if event.kind == "measured" and path is not None:
            try:
                self.on_measurement(Path(path))
            except Exception:  # the index (a full disk, a locked file) must not fail a measurement already written
                log.exception("indexing %s failed; the next start adds it", path)
        self._tell(record)

    def on_progress(self, fraction: float, message: str) -> None:
        with self._lock:
            self._status["step"], self._status["progress"] = message, round(float(fraction), 4)
        self._tell({"type": "progress", "step": message, "progress": round(float(fraction), 4)})

    def _tell(self, record: dict) -> None:
        for listener in list(self.listeners):
            listener(record)

    # ---------------------------------------------------------------------- other threads
    def submit(self, kind: str, params: dict, action: Callable[[Job], str]) -> Job:
        """Queue `action(job)` (run on the worker thread; returns an outcome of OUTCOMES). Busy while another
        job is queued or running."""
        with self._lock:
            if self.current is not None:
                raise Busy(self.current)
            if self._link_down:
                raise LinkDown("the device is not answering (the link is being tried again): ask again once the "
                               "status shows it connected")
            job = self.current = Job(kind, "web", params)
            self._queue.append((job, action))
        self._tell({"type": "job", "job": job.to_json()})
        return job

    def run_apart(self, kind: str, params: dict, action: Callable[[Job], str]) -> Job:
        """Run `action(job)` on a thread of its own, beside the instrument's queue (work on stored records that
        needs no device: a re-fit). One at a time: Busy while another runs. A DeviceError it raises (from a
        call it made through `call`) fails only that job."""
        with self._lock:
            if self.apart is not None:
                raise Busy(self.apart)
            job = self.apart = Job(kind, "web", params, state="running")
        self._tell({"type": "job", "job": job.to_json()})

        def run() -> None:
            try:
                outcome = self._outcome(job, action)
            except DeviceError as exc:
                job.message, outcome = str(exc), "failed"
            self._finish(job, outcome)

        threading.Thread(target=run, name=f"trimeter-{kind}", daemon=True).start()
        return job

    def call(self, fn: Callable[[Service], object]) -> concurrent.futures.Future:
        """Run `fn(service)` on the worker thread between polls (a short device read or write)."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._lock:
            self._calls.append((future, fn))
        return future

    def job(self, job_id: str) -> Job | None:
        with self._lock:
            for job in [self.current, self.apart, *self.recent]:
                if job is not None and job.id == job_id:
                    return job
        return None

    def status(self) -> dict:
        """A snapshot of what the instrument is doing (safe from any thread)."""
        service = self.service
        with self._lock:
            snapshot = dict(self._status)
            job = self.current.to_json() if self.current else None
            recent = [j.to_json() for j in self.recent]
        pattern = service.pattern
        calibration = service.calibration
        device = service.device
        identity = getattr(device, "identity", None)
        uptime = service.device_uptime_s
        return {
            "state": "stopped" if self.stopped else STATES.get(pattern, pattern) if snapshot["connected"]
            else "connecting",
            "stopped": self.stopped,
            "asking": ({"what": "empty_holder", "reason": snapshot["asking_reason"]} if pattern == EMPTY_HOLDER else
                       {"what": "next_sample"} if pattern == NEXT_SAMPLE else None),
            "job": job,
            "step": snapshot["step"], "progress": snapshot["progress"],
            "lamp_drift": snapshot["lamp_drift"],
            "calibration": None if calibration is None else {
                "created_utc": calibration.created_utc,
                "age_s": None if uptime is None or uptime < calibration.device_time_s
                else round(uptime - calibration.device_time_s, 1),
                "max_age_s": service.settings.calibration_max_age_s,
                "due": service.calibration_stale_reason or service.calibration_requested},
            "device": None if identity is None or not snapshot["connected"] else {
                "port": service.settings.port, "vendor_id": identity.vendor_id, "model_id": identity.model_id,
                "firmware": ".".join(map(str, identity.firmware_version)),
                "regmap_hash": f"0x{identity.regmap_hash:08X}"},
            "map_table": snapshot["map_table"],
            "samples": [{"thickness_mm": t, "map": m} for t, m in service.settings.serve_samples],
            "last_measurement": service.last_result.name if service.last_result else None,
            "recent_jobs": recent,
        }

    @property
    def device_config(self) -> dict | None:
        with self._lock:
            return self._status["device_config"]

    def set_device_config(self, config: dict) -> None:
        with self._lock:
            self._status["device_config"] = {name: _plain(value) for name, value in config.items()}


def _plain(value: object) -> Any:
    """A JSON-ready copy of an event's data (enums by name, paths as text, numpy scalars as numbers)."""
    import enum

    import numpy as np

    if isinstance(value, enum.Enum):
        return value.name.lower()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None  # JSON has no NaN
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)
