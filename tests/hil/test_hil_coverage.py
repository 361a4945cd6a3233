"""Hardware-in-the-loop, the twin only: do the σ the instrument reports cover the virtual samples'
truth at the rates they claim (68 % within ±1σ, 95 % within ±2σ)? One calibration, then six virtual
samples in a row (so the lamps drift between calibration and shots, as on the bench), each measured
with the shipped device map; the twin's samples are traced by the tracer that map was built with and
reduced to its I(ρ) model, not read from it, so the figures include the map's interpolation and Monte
Carlo error but not the tracer's or the model's own. Coverage is pooled over the samples' unflagged bins in
420-720 nm (2784 of them): each sample's bins are correlated (the same lamps, calibration and
map), so the bounds are wider than a binomial count would need — measured on the twin with seeds 1-4:
α 68-72 % / 95.1-96.3 %, σt 68-70 % / 94.4-95.7 %, g 82-85 % / 99.1-99.5 %. g is wider than it needs to
be (the map's error term, fitted on α, is generous for g); checked here only for not claiming more
precision than it has, and for not being trivially wide."""

from __future__ import annotations

import csv
import queue
import threading
import time

import numpy as np
import pytest

from hil_support import twin_truth
from trimeter.bench.uncertainty import coverage
from trimeter.device import Device
from trimeter.formats.appearance import AppearanceMap
from trimeter.paths import MAPS_DIR
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings
from trimeter.spectrometer import open_spectrometer

SAMPLES = ("cyan-ink", "magenta-ink", "yellow-ink", "white-ink", "milk", "black-ink")
DEVICE_MAP = MAPS_DIR / "device-n1.5-l0.4.tmap"
THICKNESS_MM = 0.4
# (±1σ low, high), (±2σ low, high): the goal 68 ± 5 / 95 ± 3 widened for the bins' correlation
BOUNDS = {"alpha": ((0.60, 0.78), (0.91, 0.99)), "sigma_t": ((0.60, 0.78), (0.91, 0.99)),
          "g": ((0.60, 0.92), (0.91, 1.0))}


def _wait(events: queue.Queue, kind: str, timeout_s: float = 300.0):
    """The next `kind` event, within one deadline over all events (a service busy with other events must not
    keep the wait alive)."""
    deadline = time.monotonic() + timeout_s
    while True:
        event = events.get(timeout=max(deadline - time.monotonic(), 0.0))
        assert event.kind != "failed", event.message
        if event.kind == kind:
            return event


def test_reported_sigma_covers_the_twins_truth(request, tmp_path, monkeypatch):
    if request.config.getoption("--port"):
        pytest.skip("needs the twin (the virtual samples' truth)")
    from trimeter.twin import Twin

    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    amap = AppearanceMap.load(DEVICE_MAP)
    settings = HostSettings()
    for key, value in (("results_dir", str(tmp_path / "results")), ("thickness_mm", THICKNESS_MM),
                       ("method", "lut"), ("timeout_s", 0.3), ("map", str(amap.path))):
        settings.set(key, value)
    events: queue.Queue = queue.Queue()
    z = {k: [] for k in BOUNDS}
    with Twin(sample=None, thickness_mm=THICKNESS_MM, time_scale=50.0, appearance_map=amap,
              state_dir=tmp_path / "twin", seed=1) as twin:
        service = Service(lambda: Device.open(twin.modbus_port, timeout_s=settings.timeout_s),
                          lambda: open_spectrometer(twin.spectrometer_url), settings, on_event=events.put,
                          device_clock=twin.sim_time, label="coverage")
        stop = threading.Event()
        thread = threading.Thread(target=service.serve, kwargs={"stop": stop.is_set}, daemon=True)
        thread.start()
        try:
            _wait(events, "connected")
            twin.control.press_button()
            _wait(events, "calibrated")
            for sample in SAMPLES:
                twin.control.insert_sample(sample, THICKNESS_MM)
                twin.control.press_button()
                event = _wait(events, "measured")
                # traced by the tracer the map was built with, reduced to its I(ρ) model: the coverage counts the
                # map's interpolation and Monte Carlo error, not what the tracer and the model get wrong alike
                truth = twin_truth(twin, request)
                params = event.data["parameters"]
                with open(event.data["path"] / "reflectances.csv") as f:
                    wl = np.array([float(row["wavelength_nm"]) for row in csv.DictReader(f)])
                at = np.abs(truth["wavelengths_nm"][None, :] - wl[:, None]).argmin(axis=1)
                clean = (wl >= 420) & (wl <= 720) & (params.flags == 0)
                assert clean.sum() > 0.8 * np.count_nonzero((wl >= 420) & (wl <= 720)), sample
                for k in z:
                    est, std, tru = getattr(params, k)[clean], getattr(params, f"{k}_std")[clean], truth[k][at][clean]
                    z[k].append(np.abs(est - tru) / std)
        finally:
            stop.set()
            thread.join(timeout=10)
    figures = {}
    for k, ((lo1, hi1), (lo2, hi2)) in BOUNDS.items():
        scores = np.concatenate(z[k])
        c1, c2, n = coverage(scores, np.ones_like(scores), np.zeros_like(scores), np.ones(len(scores), bool))
        figures[k] = (round(c1, 3), round(c2, 3), n)
        assert lo1 <= c1 <= hi1 and lo2 <= c2 <= hi2, (k, figures)
    print("HIL coverage ±1σ/±2σ over", figures["alpha"][2], "unflagged bins:", figures)
