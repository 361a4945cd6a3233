"""Nothing captured is lost: a results directory that cannot take a measurement is refused before the
capture; one that fails during the write sends the capture to the spool, and says where and how to
re-fit it; what a killed write leaves behind is reported and moved to the spool at the next start."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import trimeter.results.figure as figure
import trimeter.results.spool as spool
from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from hil_support import HIL_MAP
from trimeter.cli import main
from trimeter.device.client import Device
from trimeter.domain import Sample
from trimeter.errors import OutputError
from trimeter.formats.appearance import AppearanceMap
from trimeter.results.spool import CaptureSpooled, prepare_results_dir, recover_partials, write_or_spool
from trimeter.results.writer import expected_size_bytes, partial_name, write_measurement
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings

TESTS = Path(__file__).resolve().parents[1]


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _names(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir()) if directory.exists() else []


# --------------------------------------------------------------------------------- the estimate
def test_the_size_estimate_bounds_a_real_results_directory(tmp_path, measurement):
    out = write_measurement(tmp_path, measurement)
    on_disk = sum(p.stat().st_blocks * 512 for p in out.iterdir())
    assert on_disk <= expected_size_bytes(31, 1)
    assert expected_size_bytes(1024, 2) > expected_size_bytes(1024, 1) > expected_size_bytes(31, 1)


# ------------------------------------------------------------------------------ before a capture
def test_a_results_directory_that_cannot_be_created_is_refused(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputError, match=r"results directory .*file/results cannot be created \(Not a directory\)"):
        prepare_results_dir(tmp_path / "file" / "results", n_bins=31, n_samples=1)


def test_a_read_only_results_directory_is_refused(tmp_path):
    root = tmp_path / "results"
    root.mkdir()
    root.chmod(0o555)
    try:
        if os.access(root, os.W_OK):
            pytest.skip("running as root: permissions do not stop writes here (see the EROFS test)")
        with pytest.raises(OutputError, match="is not writable"):
            prepare_results_dir(root, n_bins=31, n_samples=1)
    finally:
        root.chmod(0o755)


def test_a_read_only_file_system_is_refused(tmp_path, monkeypatch):
    def erofs(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(spool.tempfile, "mkstemp", erofs)
    with pytest.raises(OutputError, match=r"is not writable \(Read-only file system\); choose another with --results"):
        prepare_results_dir(tmp_path, n_bins=31, n_samples=1)


def test_too_little_free_space_is_refused(tmp_path, monkeypatch):
    usage = spool.shutil.disk_usage(tmp_path)
    need = 2 * expected_size_bytes(1024, 2)
    monkeypatch.setattr(spool.shutil, "disk_usage", lambda p: usage._replace(free=need - 1))
    with pytest.raises(OutputError, match=r"MB free; a measurement needs .* MB"):
        prepare_results_dir(tmp_path, n_bins=1024, n_samples=2)
    monkeypatch.setattr(spool.shutil, "disk_usage", lambda p: usage._replace(free=need))
    assert prepare_results_dir(tmp_path, n_bins=1024, n_samples=2) == []
    assert _names(tmp_path) == []   # the write test left nothing behind


# ---------------------------------------------------------------------------------- the spool
def test_a_full_disk_during_the_write_keeps_the_capture_in_the_spool(tmp_path, measurement, monkeypatch, capsys):
    monkeypatch.setattr(figure, "plot_parameters", _enospc)  # the disk fills while the figure is written
    with pytest.raises(CaptureSpooled) as caught:
        write_or_spool(tmp_path / "results", measurement, label="ink", spool=tmp_path / "spool")
    kept = caught.value.path
    message = str(caught.value)
    assert f"cannot write the results to {tmp_path / 'results'} (No space left on device)" in message
    assert f"the capture is kept in {kept}" in message
    assert kept.parent == tmp_path / "spool" and kept.name.endswith("-ink")
    assert _names(tmp_path / "results") == []       # no half-written directory, no .partial-*
    assert {"calibration.csv", "calibration.json", "raw_black.csv", "raw_white.csv", "raw_collimated.csv",
            "reflectances.csv", "parameters.csv", "measurement.json"} <= set(_names(kept))
    # the re-fit the message names works as written
    command = message.split("re-fit it with `")[1].split("`")[0].split()
    assert command[:3] == ["trimeter", "fit", "--map"] and f"--input {kept / 'reflectances.csv'}" in " ".join(command)
    command[3] = "device-n1.5-l0.4"  # the shipped map of the capture's declared 0.4 mm (the file says so)
    command[command.index("-o") + 1] = str(tmp_path / "params.csv")
    assert main(command[1:]) == 0
    capsys.readouterr()
    fitted = np.genfromtxt(tmp_path / "params.csv", delimiter=",", names=True)
    np.testing.assert_allclose(fitted["wavelength_nm"], measurement.parameters.wavelengths_nm, rtol=1e-6)


def test_when_no_spool_can_take_it_either_the_error_says_so(tmp_path, measurement, monkeypatch):
    (tmp_path / "file").write_text("")
    monkeypatch.setattr(spool.tempfile, "gettempdir", lambda: str(tmp_path / "file"))
    with pytest.raises(OutputError, match="no spool directory could take the capture") as caught:
        write_or_spool(tmp_path / "file" / "results", measurement, spool=tmp_path / "file" / "spool")
    assert not isinstance(caught.value, CaptureSpooled)


def test_the_spool_falls_back_to_the_temp_directory(tmp_path, measurement, monkeypatch):
    (tmp_path / "file").write_text("")
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(spool.tempfile, "gettempdir", lambda: str(tmp_path / "tmp"))
    with pytest.raises(CaptureSpooled) as caught:
        write_or_spool(tmp_path / "file" / "results", measurement, spool=tmp_path / "file" / "spool")
    assert caught.value.path.parent == tmp_path / "tmp" / f"trimeter-spool-{os.getuid()}"


# ------------------------------------------------------------------------------ leftovers
_KILLED_WRITER = """
import sys, time
from pathlib import Path
sys.path.insert(0, {tests!r})
import numpy as np
from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
import trimeter.results.figure as figure
from trimeter.device.client import Device
from trimeter.domain.parameters import FitResult
from trimeter.domain import MapIdentity, Measurement, Provenance, Sample, SampleCapture
from trimeter.results import Parameters, write_measurement
from trimeter.sequences import Runner, calibration, reflectances, sample_capture

wl = np.linspace(400, 700, 31)
fake = FakeInstrument(busy_polls=1)
optics = FakeOptics(wl, diffuse=np.full(31, 1e6), collimated=np.full(31, 2e6), rho_black=np.full(31, 0.03),
                    rho_white=0.99)
runner = Runner(Device(fake), FakeSpectrometer(fake, optics), sleep=lambda s: None)
cal = runner.run(calibration(white_reference_reflectance=0.99))
optics.sample = (np.full(31, 0.2), np.full(31, 0.5), np.full(31, 0.1))
raw = runner.run(sample_capture(hdr_decades=1))
ones = np.ones(31)
result = FitResult(alpha=0.5 * ones, sigma_t=ones, g=0.4 * ones, alpha_std=ones, sigma_t_std=ones, g_std=ones,
                   flags=np.zeros(31, int), sigma_t_beer=ones, method="lut")

def hang(*args, **kwargs):
    Path({ready!r}).write_text("writing the figure")
    time.sleep(120)

figure.plot_parameters = hang
sample = Sample(0.4, MapIdentity('test-map', 0.4, 'sha256:0'))
write_measurement({root!r}, Measurement(cal, [SampleCapture(sample, raw, reflectances(cal, raw))],
                                        Parameters.from_fit(wl, result), provenance=Provenance(method='lut')),
                  label="killed")
"""


def test_a_write_killed_midway_is_reported_and_moved_to_the_spool_at_the_next_start(tmp_path):
    root, ready = tmp_path / "results", tmp_path / "ready"
    script = _KILLED_WRITER.format(tests=str(TESTS), ready=str(ready), root=str(root))
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert proc.poll() is None and time.monotonic() < deadline, "the writer ended before it was killed"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    (leftover,) = root.iterdir()
    assert leftover.name == partial_name(leftover.name.split("-", 2)[2], proc.pid)
    notes = prepare_results_dir(root, n_bins=31, n_samples=1, spool=tmp_path / "spool")
    assert notes[0] == f"1 interrupted results write(s) found in {root}"
    (kept,) = (tmp_path / "spool").iterdir()
    assert kept.name.endswith("-killed-interrupted")
    assert f"{leftover.name} (" in notes[1] and " s old, " in notes[1] and f"moved to {kept}" in notes[1]
    assert {"calibration.csv", "reflectances.csv", "parameters.csv"} <= set(_names(kept))
    assert _names(root) == []
    assert prepare_results_dir(root, n_bins=31, n_samples=1, spool=tmp_path / "spool") == []  # reported once


def test_leftovers_empty_ones_deleted_live_ones_kept(tmp_path):
    root, spool_root = tmp_path / "results", tmp_path / "spool"
    root.mkdir()
    (root / ".partial-20260101T000000Z").mkdir()                       # an empty one, of the pid-less kind
    old_kind = root / ".partial-20260101T000001Z-ink"                  # written before partials carried a pid
    old_kind.mkdir()
    (old_kind / "calibration.csv").write_text("x")
    live = root / partial_name("20260101T000002Z")                     # this process is writing it
    live.mkdir()
    (live / "raw_black.csv").write_text("x")
    stale_live = root / partial_name("20260101T000003Z")               # a pid alive again, long after
    stale_live.mkdir()
    (stale_live / "raw_white.csv").write_text("x")
    hours_ago = time.time() - 2 * spool.IN_PROGRESS_MAX_AGE_S
    os.utime(stale_live / "raw_white.csv", (hours_ago, hours_ago))
    os.utime(stale_live, (hours_ago, hours_ago))
    (root / "20260101T000004Z").mkdir()                                 # a finished result: not touched
    notes = recover_partials(root, spool=spool_root)
    assert notes[0].startswith("3 interrupted results write(s)")
    assert any("was empty: deleted" in n for n in notes)
    assert any(n.startswith(f"{stale_live.name} (2 h old, 1 file(s)) moved to") for n in notes)
    assert _names(root) == sorted(["20260101T000004Z", live.name])
    assert _names(spool_root) == ["20260101T000001Z-ink-interrupted", "20260101T000003Z-interrupted"]
    assert (spool_root / "20260101T000001Z-ink-interrupted" / "calibration.csv").read_text() == "x"


# ---------------------------------------------------------------------------- the service
@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    amap = AppearanceMap.load(HIL_MAP)
    wl = np.linspace(420, 720, 61)
    fake = FakeInstrument(busy_polls=1)
    optics = FakeOptics(wl, diffuse=np.full(wl.size, 3e6), collimated=np.full(wl.size, 5e6),
                        rho_black=np.full(wl.size, 0.03), rho_white=0.99)
    spec = FakeSpectrometer(fake, optics)
    settings = HostSettings()
    settings.set("results_dir", str(tmp_path / "results"))
    events = []
    service = Service(lambda: Device(fake), lambda: spec, settings, on_event=events.append)
    service.connect()
    service.calibrate(warm=False)
    optics.sample = amap.query(np.full(wl.size, 0.9), np.full(wl.size, 3.0), np.full(wl.size, 0.5), 0.03, 0.99)
    return service, spec, amap, events, tmp_path


def test_the_service_refuses_before_capturing_when_results_cannot_be_written(rig, monkeypatch):
    service, spec, amap, events, tmp = rig
    (tmp / "file").write_text("")
    service.settings.set("results_dir", str(tmp / "file" / "results"))
    reads = []
    monkeypatch.setattr(spec, "intensities", lambda: reads.append(1))
    with pytest.raises(OutputError, match="cannot be created"):
        service.measure([Sample(amap.thickness_mm, amap)])
    assert reads == []          # refused before a single spectrum of the sample was taken


def test_the_service_keeps_a_capture_it_cannot_write(rig, monkeypatch):
    service, spec, amap, events, tmp = rig
    monkeypatch.setattr(figure, "plot_parameters", _enospc)
    with pytest.raises(CaptureSpooled, match="No space left on device") as caught:
        service.measure([Sample(amap.thickness_mm, amap)])
    assert caught.value.path.parent == tmp / "data" / "spool"
    assert service.last_result == caught.value.path and (service.last_result / "reflectances.csv").is_file()
    assert _names(tmp / "results") == []


def test_serve_reports_and_spools_leftovers_at_start(rig):
    service, spec, amap, events, tmp = rig
    leftover = tmp / "results" / partial_name("20260101T000000Z", pid=2**22 + 1)  # above any pid_max: dead
    leftover.mkdir(parents=True)
    (leftover / "raw_black.csv").write_text("x")
    service.serve(stop=lambda: True)
    warnings = [e.message for e in events if e.kind == "warning"]
    assert warnings[0] == f"1 interrupted results write(s) found in {tmp / 'results'}"
    assert f"moved to {tmp / 'data' / 'spool' / '20260101T000000Z-interrupted'}" in warnings[1]
    assert _names(tmp / "results") == []


def test_ctrl_c_mid_write_leaves_the_partial_for_the_next_start(tmp_path, measurement, monkeypatch):
    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(figure, "plot_parameters", interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_measurement(tmp_path, measurement)
    (partial,) = tmp_path.iterdir()
    assert partial.name.startswith(partial_name(""))
    assert spool.find_partials(tmp_path) == []          # this process's own write: still in progress
    later = time.time() + 2 * spool.IN_PROGRESS_MAX_AGE_S
    (left,) = spool.find_partials(tmp_path, now=later)  # once no write can still be running, a leftover
    assert left.path == partial and left.files >= 5


def test_the_last_resort_spool_in_the_temp_directory_is_private_and_never_a_link(tmp_path, monkeypatch):
    monkeypatch.setattr(spool.tempfile, "gettempdir", lambda: str(tmp_path))
    made = spool._private_temp_spool()
    assert made == tmp_path / f"trimeter-spool-{os.getuid()}" and (made.stat().st_mode & 0o777) == 0o700
    made.rmdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir(mode=0o700)
    made.symlink_to(elsewhere)          # planted by someone to redirect captures
    assert spool._private_temp_spool() is None
    made.unlink()
    made.mkdir(mode=0o777)
    os.chmod(made, 0o777)               # open to others: not used either
    assert spool._private_temp_spool() is None
