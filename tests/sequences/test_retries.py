"""Step-level retries (trimeter.sequences.steps.Runner.retrying) and the transport's fast give-up on a
garbled reply: a request that fails all its transport attempts (LinkError) costs a retried step, not the
sequence; a reset or a refusal is never retried; a retried sequence gives exactly the same results."""

import os
import select
import struct
import threading
import time
import tty

import numpy as np
import pytest

from fakes import FakeInstrument, FakeOptics, FakeSpectrometer
from trimeter.crc import crc16_modbus_bytes as crc16
from trimeter.device.client import Device
from trimeter.device.transport import LinkError, ModbusExceptionReply, RtuTransport
from trimeter.errors import DeviceError, InputError
from trimeter.sequences import Runner, calibration, reflectances, sample_capture
from trimeter.sequences.steps import Move, RetryPolicy, Wait

N = 48
WL = np.linspace(400, 700, N)


class FlakyLink:
    """A Transport around FakeInstrument whose requests fail as a noisy line's do after all the transport's
    attempts: lost before the device saw them (`p_lost`) or after it acted (`p_unanswered`, the reply lost)."""

    def __init__(self, instrument, *, p_lost=0.0, p_unanswered=0.0, seed=0):
        self.instrument, self.p_lost, self.p_unanswered = instrument, p_lost, p_unanswered
        self.rng = np.random.default_rng(seed)
        self.reopens = self.failures = 0

    def reopen(self):
        self.reopens += 1

    def close(self):
        pass

    def __getattr__(self, name):
        call = getattr(self.instrument, name)

        def flaky(*args):
            if self.rng.random() < self.p_lost:
                self.failures += 1
                raise LinkError(f"injected: {name} lost")
            result = call(*args)
            if self.rng.random() < self.p_unanswered:
                self.failures += 1
                raise LinkError(f"injected: {name} unanswered")
            return result
        return flaky


def rig(**link):
    fake = FakeInstrument(busy_polls=1)
    opt = FakeOptics(WL, diffuse=2e6 * (1 + 0.5 * np.sin(WL / 40)), collimated=5e6 * np.exp(-((WL - 550) / 120) ** 2),
                     rho_black=0.03, rho_white=0.99)
    spec = FakeSpectrometer(fake, opt)
    flaky = FlakyLink(fake, **link)
    device = Device(flaky, check=False)
    sleeps = []
    return fake, opt, flaky, device, spec, sleeps


def run_calibration_and_capture(runner, opt):
    cal = runner.run(calibration(white_reference_reflectance=0.99))
    opt.sample = (np.full(N, 0.2), np.full(N, 0.6), np.full(N, 0.05))
    return cal, reflectances(cal, runner.run(sample_capture(hdr_decades=1)))


def test_a_noisy_link_costs_retried_steps_and_gives_the_same_results():
    fake, opt, flaky, device, spec, sleeps = rig(p_lost=0.03, p_unanswered=0.03, seed=3)
    runner = Runner(device, spec, sleep=sleeps.append)
    cal, refl = run_calibration_and_capture(runner, opt)
    assert flaky.failures > 10 and runner.timing.step_retries == flaky.failures == flaky.reopens
    np.testing.assert_allclose(cal.rho_black, 0.03, rtol=1e-9)
    np.testing.assert_allclose(refl.I_b, 0.2, rtol=1e-9)
    np.testing.assert_allclose(refl.I_w, 0.6, rtol=1e-9)
    np.testing.assert_allclose(refl.I_c, 0.05, rtol=1e-9)
    assert runner.timing.to_dict()["step_retries"] == runner.timing.step_retries
    assert sum(sleeps) > 0  # the backoffs went through the runner's sleep


def test_without_step_retries_the_same_link_abandons_the_sequence():
    fake, opt, flaky, device, spec, sleeps = rig(p_lost=0.03, p_unanswered=0.03, seed=3)
    runner = Runner(device, spec, sleep=sleeps.append, retry=RetryPolicy(attempts=1))
    with pytest.raises(LinkError, match="failed 1 times on a bad link; the sequence was abandoned"):
        run_calibration_and_capture(runner, opt)


def test_a_dead_link_gives_up_after_the_policy_with_backoffs_doubling_and_a_clear_error():
    fake, opt, flaky, device, spec, sleeps = rig(p_lost=1.0)
    runner = Runner(device, spec, sleep=sleeps.append, retry=RetryPolicy(attempts=4, backoff_s=0.25, max_backoff_s=0.6))
    with pytest.raises(LinkError, match="moving to the white slot failed 4 times .*injected"):
        runner.run(iter_steps(Move("white")))
    assert sleeps == [0.25, 0.5, 0.6] and flaky.reopens == 3 and runner.timing.step_retries == 3


def iter_steps(*steps):
    for step in steps:
        yield step


def test_a_reset_is_not_a_link_failure_and_is_not_retried():
    fake, opt, flaky, device, spec, sleeps = rig()
    runner = Runner(device, spec, sleep=sleeps.append)
    runner.run(calibration(white_reference_reflectance=0.99))
    count = {"n": 0}

    def reset_once(instrument):
        count["n"] += 1
        if count["n"] == 40:
            instrument.reset()

    fake.on_request = reset_once
    opt.sample = (np.full(N, 0.2), np.full(N, 0.6), np.full(N, 0.05))
    with pytest.raises(DeviceError, match="reset during the sequence|lost its homing|lost its light") as info:
        runner.run(sample_capture())
    assert not isinstance(info.value, LinkError) and flaky.reopens == 0 and runner.timing.step_retries == 0


def test_a_refusal_is_not_retried():
    fake, opt, flaky, device, spec, sleeps = rig()

    def refuse(instrument):
        raise ModbusExceptionReply("a write", 4)

    fake.on_request = refuse
    runner = Runner(device, spec, sleep=sleeps.append)
    with pytest.raises(ModbusExceptionReply, match="exception 04"):
        runner.run(iter_steps(Move("black")))
    assert flaky.reopens == 0 and sleeps == []


def test_a_wait_retried_after_a_link_failure_resumes_from_its_start():
    fake, opt, flaky, device, spec, sleeps = rig()
    fake.tick_s = 0.5  # device seconds per request
    runner = Runner(device, spec, sleep=sleeps.append)
    failed = {"done": False}

    def fail_once_midway(instrument):
        if instrument.time_s > 4 and not failed["done"]:
            failed["done"] = True
            raise LinkError("injected")

    fake.on_request = fail_once_midway
    start = fake.time_s
    runner.run(iter_steps(Wait(8.0)))
    assert failed["done"] and runner.timing.step_retries == 1
    # restarting the wait would have taken ≥ 4 + 8 device seconds
    assert 8.0 <= fake.time_s - start < 10.0


def test_retry_policy_refuses_nonsense():
    for bad in (dict(attempts=0), dict(attempts=True), dict(backoff_s=-1), dict(backoff_s=3, max_backoff_s=2)):
        with pytest.raises(InputError):
            RetryPolicy(**bad)


# ------------------------------------------------------------------ the press-button service
class FlakyOutsideSequences(FlakyLink):
    """Loses requests only while no sequence (Runner.run) is running: the service's own polls, status LED
    writes, lamp switching and map-table check."""

    def __init__(self, instrument, **link):
        super().__init__(instrument, **link)
        self.in_sequence = False
        self.enabled = False

    def __getattr__(self, name):
        flaky = super().__getattr__(name)
        call = getattr(self.instrument, name)
        return call if self.in_sequence or not self.enabled else flaky


def service_rig(tmp_path, monkeypatch, policy):
    from hil_support import HIL_MAP
    from trimeter.formats.appearance import AppearanceMap
    from trimeter.sequences.service import Service
    from trimeter.sequences.settings import HostSettings

    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    amap = AppearanceMap.load(HIL_MAP)
    wl = np.linspace(420, 720, 61)
    fake = FakeInstrument(busy_polls=1)
    optics = FakeOptics(wl, diffuse=np.full(wl.size, 3e6), collimated=np.full(wl.size, 5e6), rho_black=0.03,
                        rho_white=0.99)
    flaky = FlakyOutsideSequences(fake, p_lost=0.06, p_unanswered=0.06, seed=11)
    run = Runner.run

    def run_marked(runner, plan):
        flaky.in_sequence = True
        try:
            return run(runner, plan)
        finally:
            flaky.in_sequence = False

    monkeypatch.setattr(Runner, "run", run_marked)
    settings = HostSettings()
    settings.set("results_dir", str(tmp_path / "results"))
    settings.set("map", str(amap.path))
    settings.set("warmup_interval_s", 2)
    events = []
    service = Service(lambda: Device(flaky), lambda: FakeSpectrometer(fake, optics), settings,
                      on_event=events.append, retry=policy)
    optics_sample = amap.query(np.full(wl.size, 0.8), np.full(wl.size, 3.0), np.full(wl.size, 0.5), 0.03, 0.99)
    return service, fake, optics, flaky, events, optics_sample


def test_the_service_retries_its_own_requests_so_a_lossy_line_costs_no_press(tmp_path, monkeypatch):
    service, fake, optics, flaky, events, sample = service_rig(tmp_path, monkeypatch, RetryPolicy(backoff_s=0.0,
                                                                                                  max_backoff_s=0.0))
    service.connect()
    flaky.enabled = True
    outcomes = [service.poll_once() for _ in range(5)]
    fake.press_button()
    outcomes.append(service.poll_once())
    optics.sample = sample
    for _ in range(3):
        fake.press_button()
        outcomes.append(service.poll_once())
    assert outcomes == [None] * 5 + ["calibrated"] + ["measured"] * 3
    assert [e for e in events if e.kind == "failed"] == []
    assert flaky.failures >= 5 and flaky.reopens == flaky.failures  # each one retried, after a reopen
    np.testing.assert_allclose(service.last_parameters.alpha, 0.8, atol=0.01)


def test_without_retries_the_same_line_fails_a_press_outside_any_sequence(tmp_path, monkeypatch):
    service, fake, optics, flaky, events, sample = service_rig(tmp_path, monkeypatch, RetryPolicy(attempts=1))
    service.connect()
    flaky.enabled = True
    with pytest.raises(LinkError, match="failed 1 times on a bad link; gave up on the device link"):
        for _ in range(20):
            fake.press_button()
            service.poll_once()


# ------------------------------------------------------------------ the transport over a real pty
class BadCrcThenGoodSlave(threading.Thread):
    """Answers FC 03 reads; the first reply has a flipped bit (bad CRC), the others are good."""

    def __init__(self):
        super().__init__(daemon=True)
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self.requests = 0
        self.stop = False

    def run(self):
        buffer = b""
        while not self.stop:
            if select.select([self.master], [], [], 0.01)[0]:
                buffer += os.read(self.master, 512)
                continue
            if len(buffer) < 8:
                continue
            address, fc, start, count = struct.unpack(">BBHH", buffer[:6])
            buffer = b""
            self.requests += 1
            body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *range(start, start + count))
            reply = bytearray(body + crc16(body))
            if self.requests == 1:
                reply[4] ^= 0x10
            os.write(self.master, bytes(reply))

    def close(self):
        self.stop = True
        self.join(timeout=2)
        os.close(self.master)
        os.close(self._slave)


def test_a_garbled_reply_is_retried_at_once_not_after_the_timeout():
    slave = BadCrcThenGoodSlave()
    slave.start()
    link = RtuTransport(slave.port, timeout_s=2.0)
    try:
        t0 = time.monotonic()
        assert link.read_words("holding_register", 10, 3) == [10, 11, 12]
        elapsed = time.monotonic() - t0
    finally:
        link.close()
        slave.close()
    assert slave.requests == 2 and link.stats.garbled_replies == 1 and link.stats.timeouts == 0
    assert elapsed < 1.5, elapsed  # waiting out the timeout (2 s) and the late-reply window (2 s) would be 4 s


def test_a_silent_device_is_a_link_error_naming_the_timeout():
    master, slave = os.openpty()
    tty.setraw(slave)
    link = RtuTransport(os.ttyname(slave), timeout_s=0.05, attempts=2)
    try:
        # the allowance plus both frames on the wire: 8 request bytes, 9 reply bytes at 11 bits each
        timeout = 0.05 + (8 + 9) * 11 / 19200
        assert link.request_timeout_s(8, 9) == pytest.approx(timeout)
        with pytest.raises(LinkError, match=f"after 2 attempts .last: no reply within {timeout:.3g} s"):
            link.read_words("input_register", 0, 2)
        assert link.stats.timeouts == 2
        link.attempts = 1
        t0 = time.monotonic()
        with link.slow_reply(0.3), pytest.raises(LinkError, match=f"no reply within {timeout + 0.3:.3g} s"):
            link.read_words("input_register", 0, 2)
        assert time.monotonic() - t0 >= 2 * (timeout + 0.3)  # waited that long, then drained as long
        assert link.request_timeout_s(8, 9) == pytest.approx(timeout)  # only inside
    finally:
        link.close()
        os.close(master)
        os.close(slave)


class SlowReplyRecorder:
    """FakeInstrument with a transport's slow_reply(): records each request with the extra time it was allowed."""

    def __init__(self, instrument):
        self.instrument, self.extra_s, self.log = instrument, 0.0, []

    def slow_reply(self, seconds):
        import contextlib

        @contextlib.contextmanager
        def allowing():
            saved, self.extra_s = self.extra_s, seconds
            try:
                yield
            finally:
                self.extra_s = saved
        return allowing()

    def __getattr__(self, name):
        call = getattr(self.instrument, name)

        def recorded(*args):
            self.log.append((name, args[0] if args else None, args[1] if len(args) > 1 else None, self.extra_s))
            return call(*args)
        return recorded


def test_requests_the_firmware_answers_after_a_flash_erase_get_the_erase_time():
    from trimeter import registers as regs
    from trimeter.device.client import CONFIG_ERASE_S, MAP_ERASE_S

    recorder = SlowReplyRecorder(FakeInstrument())
    device = Device(recorder)
    device.command("save_config")
    table = bytes(range(256)) * 4
    device.flash_map(table, version=3)
    command, map_command = regs.BY_NAME["command"].address, regs.BY_NAME["map_command"].address
    slow = {(name, address): extra for name, address, values, extra in recorder.log if extra}
    writes = [(address, values, extra) for name, address, values, extra in recorder.log if name == "write_words"]
    save = [extra for address, values, extra in writes if address == command and values == [regs.Command.SAVE_CONFIG]]
    begin = [extra for address, values, extra in writes if address <= map_command < address + len(values)
             and values[map_command - address] == regs.MapCommand.BEGIN_WRITE]
    activate = [extra for address, values, extra in writes if address == map_command
                and values == [regs.MapCommand.ACTIVATE]]
    assert save == [CONFIG_ERASE_S] and begin == [MAP_ERASE_S] and activate == [CONFIG_ERASE_S]
    # everything else waits the ordinary timeout: the file records, the polls, verify
    assert all(name != "write_file_records" for name, _ in slow)
    assert sum(1 for *_, extra in recorder.log if not extra) > 10
