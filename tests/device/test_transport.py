"""The pymodbus adapter over a real pty against a scripted RTU slave: garbage and bad CRCs are
recovered from, a late reply is never taken as the answer to the next request, a dropped reply is
retried, an exception reply is raised at once, and the port is reopened after it disappears."""

import contextlib
import os
import select
import struct
import threading

import pytest

from trimeter.device.transport import ModbusExceptionReply, RtuTransport
from trimeter.errors import DeviceError
from trimeter.crc import crc16_modbus_bytes as crc16


class ScriptedSlave(threading.Thread):
    """Answers FC 03/04 with register value = address + request number; `script[n]` alters reply n."""

    REQUEST_BYTES = 8  # FC 03/04: address, function, start, count, CRC

    def __init__(self, script=None):
        super().__init__(daemon=True)
        self.master, slave = os.openpty()
        self.port = os.ttyname(slave)
        self._slave_fd = slave
        self.script = script or {}
        self.requests = 0
        self.stop = False
        import tty

        tty.setraw(slave)

    def frames(self):
        """Each request (REQUEST_BYTES) as it completes (the line goes quiet), until stopped or closed."""
        buffer = b""
        while not self.stop:
            try:  # the test closes the pty to unplug the adapter: either call may then fail
                ready, _, _ = select.select([self.master], [], [], 0.01)
                if ready:
                    buffer += os.read(self.master, 512)
                    continue
            except (OSError, ValueError):
                return
            if len(buffer) < self.REQUEST_BYTES:
                continue
            frame, buffer = buffer[:self.REQUEST_BYTES], b""
            self.requests += 1
            yield frame

    def run(self):
        for frame in self.frames():
            address, fc, start, count = struct.unpack(">BBHH", frame[:6])
            action = self.script.get(self.requests, "ok")
            if fc not in (3, 4):
                continue
            if action in ("exception", "exception-prefix"):
                body = bytes([address, fc | 0x80, 2])
            else:
                values = [start + i + 100 * self.requests for i in range(count)]
                body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *values)
            reply = body + crc16(body)
            if action == "drop":
                continue
            if action == "garbage":
                reply = b"\x55\xaa\x13" + reply
            if action == "exception-prefix":
                # What two flipped bits in a read reply can look like (seen in CI: 01 02 01 01 60 48 →
                # 01 82 01 81 60 48, whose first three bytes + "81 60" check out as an exception frame).
                reply += b"\x48"
            if action == "badcrc":
                reply = reply[:-1] + bytes([reply[-1] ^ 0xFF])
            if action.startswith("late"):
                threading.Timer(float(action[4:]), os.write, (self.master, reply)).start()
                continue
            os.write(self.master, reply)


@pytest.fixture
def slave_factory():
    slaves = []

    def make(script=None, cls=None):
        slave = (cls or ScriptedSlave)(script)
        slave.start()
        slaves.append(slave)
        return slave

    yield make
    for slave in slaves:
        slave.stop = True
        slave.join(1)
        for fd in (slave.master, slave._slave_fd):
            with contextlib.suppress(OSError):  # already closed by the test (the unplugged adapter)
                os.close(fd)


def test_plain_read(slave_factory):
    slave = slave_factory()
    link = RtuTransport(slave.port, timeout_s=0.2)
    assert link.read_words("holding_register", 10, 3) == [110, 111, 112]
    link.close()


@pytest.mark.parametrize("fault", ["garbage", "badcrc", "drop"])
def test_recovers_from_a_bad_reply_by_retrying_on_a_clean_buffer(slave_factory, fault):
    slave = slave_factory({1: fault})
    # this slave's values change on every read: no confirmation of reads after the drop (tested below)
    link = RtuTransport(slave.port, timeout_s=0.15, late_reply_horizon_s=0.0)
    values = link.read_words("input_register", 0, 2)
    # the value comes from the request that was answered last: never a mix, never stale bytes
    assert values == [100 * slave.requests, 100 * slave.requests + 1]
    if fault != "garbage":  # garbage before a good frame may be skipped by the framer without a retry
        assert slave.requests == 2 and link.stats.retries == 1
    assert link.read_words("input_register", 5, 1) == [5 + 100 * slave.requests]
    link.close()


def test_late_reply_is_not_taken_as_the_answer_to_the_next_request(slave_factory):
    slave = slave_factory({1: "late0.25"})
    link = RtuTransport(slave.port, timeout_s=0.15, late_reply_window_s=0.4)
    first = link.read_words("holding_register", 0, 4)
    assert first == [i + 100 * 2 for i in range(4)]  # the retry's reply, not the late one
    second = link.read_words("holding_register", 0, 4)
    assert second == [i + 100 * 3 for i in range(4)]
    link.close()


def test_exception_reply_is_raised_at_once_with_its_code(slave_factory):
    slave = slave_factory({1: "exception"})
    link = RtuTransport(slave.port, timeout_s=0.15)
    with pytest.raises(ModbusExceptionReply, match="exception 02") as info:
        link.read_words("holding_register", 999, 1)
    assert info.value.code == 2 and slave.requests == 1
    link.close()


def test_a_valid_frame_inside_a_longer_garbled_reply_is_not_taken_as_the_answer(slave_factory):
    slave = slave_factory({1: "exception-prefix"})
    link = RtuTransport(slave.port, timeout_s=0.15)
    assert link.read_words("holding_register", 7, 1) == [7 + 100 * 2]
    assert slave.requests == 2 and link.stats.garbled_replies == 1
    link.close()


def test_the_whole_frame_check_sees_what_pymodbus_framing_lets_through():
    from pymodbus.framer.rtu import FramerRTU
    from pymodbus.pdu import DecodePDU

    from trimeter.device.transport import is_one_whole_frame

    garbled = bytes.fromhex("018201816048")  # 01 02 01 01 60 48 with two bits flipped
    _, pdu = FramerRTU(DecodePDU(False)).handleFrame(garbled, 1, 0)
    assert pdu is not None and pdu.isError()  # pymodbus alone would raise "illegal function"
    assert not is_one_whole_frame(garbled)
    assert is_one_whole_frame(bytes.fromhex("010201016048"))


def test_gives_up_with_a_clear_error_naming_port_and_request(slave_factory):
    slave = slave_factory({n: "drop" for n in range(1, 10)})
    link = RtuTransport(slave.port, timeout_s=0.05, attempts=3)
    with pytest.raises(DeviceError, match=rf"no valid reply from the device on {slave.port} to a read of 1 "
                                          r"input_registers at 7 after 3 attempts"):
        link.read_words("input_register", 7, 1)
    link.close()


def test_missing_port_gives_a_clear_error():
    with pytest.raises(DeviceError, match="cannot open serial port /dev/nonexistent-trimeter"):
        RtuTransport("/dev/nonexistent-trimeter", reconnect_timeout_s=0.1)


def test_reopens_after_the_adapter_disappears_and_returns(slave_factory, tmp_path):
    first = slave_factory()
    link_path = tmp_path / "ttyTRIMETER"
    link_path.symlink_to(first.port)
    link = RtuTransport(str(link_path), timeout_s=0.1, reconnect_timeout_s=3.0)
    assert link.read_words("holding_register", 1, 1) == [101]
    # unplug: the old pty goes away; a new adapter appears under the same name a moment later
    first.stop = True
    first.join(1)
    os.close(first.master)
    link_path.unlink()
    second = slave_factory()
    threading.Timer(0.3, link_path.symlink_to, (second.port,)).start()
    assert link.read_words("holding_register", 1, 1)[0] % 100 == 1
    assert link.stats.reconnects >= 1
    link.close()


class EchoingSlave(ScriptedSlave):
    """An RS-485 adapter without echo suppression: the master hears its own request before the reply."""

    def run(self):
        for frame in self.frames():
            address, fc, start, count = struct.unpack(">BBHH", frame[:6])
            body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *[start + i for i in range(count)])
            os.write(self.master, frame + body + crc16(body))


def test_rs485_local_echo_is_stripped_when_configured(slave_factory):
    slave = slave_factory(cls=EchoingSlave)
    link = RtuTransport(slave.port, timeout_s=0.2, local_echo=True)
    assert link.read_words("holding_register", 3, 2) == [3, 4]
    link.close()


class HoldingSlave(ScriptedSlave):
    """Register value = its address (the same read gives the same answer); `hold`: this reply is kept
    back, and goes out when the first read at `release_at` arrives, ahead of that read's own reply (which
    follows `gap_s` later): a reply later than any drain window, in the worst place."""

    gap_s = 0.05
    release_at = 50

    def run(self):
        held = []
        for frame in self.frames():
            address, fc, start, count = struct.unpack(">BBHH", frame[:6])
            body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *[start + i for i in range(count)])
            action = self.script.get(self.requests, "ok")
            if action == "hold":
                held.append(body + crc16(body))
                continue
            if held and start == self.release_at:
                os.write(self.master, held.pop())
                threading.Event().wait(self.gap_s)
            os.write(self.master, body + crc16(body))


def test_a_reply_later_than_the_drain_is_not_taken_as_the_answer_to_a_read_of_its_shape(slave_factory):
    slave = slave_factory({1: "hold"}, cls=HoldingSlave)
    link = RtuTransport(slave.port, timeout_s=0.5)  # the answer behind the late reply comes well within it
    # request 1 unanswered; the retry's reply (2) is confirmed by a second ask (3) that agrees
    assert link.read_words("holding_register", 0, 4) == [0, 1, 2, 3]
    # the read at 50 gets request 1's reply first: the same shape (4 registers), another address
    assert link.read_words("holding_register", 50, 4) == [50, 51, 52, 53]
    assert link.stats.stale_replies >= 1 and link.stats.confirmations >= 2
    # another shape is not confirmed: no late reply of its length can be on its way
    before = slave.requests
    assert link.read_words("holding_register", 9, 1) == [9]
    assert slave.requests == before + 1
    link.close()


def test_reads_are_confirmed_only_within_the_horizon_after_an_unanswered_read(slave_factory):
    slave = slave_factory({1: "hold"}, cls=HoldingSlave)
    link = RtuTransport(slave.port, timeout_s=0.1, late_reply_horizon_s=0.0)
    assert link.read_words("holding_register", 0, 2) == [0, 1]
    assert link.read_words("holding_register", 5, 2) == [5, 6]
    assert slave.requests == 3 and link.stats.confirmations == 0
    link.close()


class FileRecordSlave(ScriptedSlave):
    """Answers FC 0x14 reads from `data` (file 1, 16-bit records); on a line that garbles long frames, every
    reply of more than `longest_clean_words` records arrives with a flipped bit."""

    REQUEST_BYTES = 12  # FC 0x14 with one sub-request

    def __init__(self, data, longest_clean_words=None):
        super().__init__()
        self.data, self.longest_clean_words = data, longest_clean_words

    def run(self):
        for frame in self.frames():
            address, fc, _, _, _, record, words = struct.unpack(">BBBBHHH", frame[:10])
            chunk = self.data[2 * record:2 * (record + words)]
            body = bytes([address, fc, 2 + len(chunk), 1 + len(chunk), 6]) + chunk
            reply = bytearray(body + crc16(body))
            if self.longest_clean_words is not None and words > self.longest_clean_words:
                reply[5] ^= 0x04
            os.write(self.master, bytes(reply))


def _read_all(link, total_words):
    """What a long transfer (a map table) does: records of the link's current size, one after another, a
    lost one asked for again."""
    from trimeter.device.transport import LinkError, record_words

    out, lost = b"", 0
    while len(out) < 2 * total_words:
        words = min(record_words(link), total_words - len(out) // 2)
        try:
            out += link.read_file_records(1, len(out) // 2, words)
        except LinkError:
            lost += 1
            assert lost < 60, "the records never shrank to what the line carries"
    return out, lost


def test_long_transfers_shrink_their_records_on_a_line_that_garbles_long_frames(slave_factory):
    data = bytes(range(256)) * 8  # 1024 records
    slave = slave_factory(cls=lambda _: FileRecordSlave(data, longest_clean_words=24))
    link = RtuTransport(slave.port, timeout_s=0.3)
    got, lost = _read_all(link, len(data) // 2)
    # it shrinks to what the line carries, grows back a quarter per clean record, and loses one record each
    # time it outgrows the line again: never at 120 words, where no record would ever pass
    assert got == data and 1 <= lost < 60 and link.record_words <= 30


def test_a_clean_line_keeps_the_longest_records(slave_factory):
    from trimeter.device.transport import MAX_FILE_RECORD_WORDS

    data = bytes(range(256)) * 4
    slave = slave_factory(cls=lambda _: FileRecordSlave(data))
    link = RtuTransport(slave.port, timeout_s=0.3)
    got, lost = _read_all(link, len(data) // 2)
    assert got == data and lost == 0 and link.record_words == MAX_FILE_RECORD_WORDS
    assert slave.requests == -(-len(data) // 2 // MAX_FILE_RECORD_WORDS)  # ceil: the fewest requests


class GarblingRegisterSlave(ScriptedSlave):
    """ScriptedSlave whose replies longer than `longest_clean_words` registers arrive with a bit flipped."""

    def __init__(self, longest_clean_words):
        super().__init__()
        self.longest_clean_words = longest_clean_words
        self.counts = []

    def run(self):
        for frame in self.frames():
            address, fc, start, count = struct.unpack(">BBHH", frame[:6])
            self.counts.append(count)
            body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *range(start, start + count))
            reply = bytearray(body + crc16(body))
            if count > self.longest_clean_words:
                reply[4] ^= 0x10
            os.write(self.master, bytes(reply))


def test_a_span_of_registers_is_read_in_requests_the_line_carries(slave_factory):
    """The device's register reads (Device.read_many) split a long span into whole registers per request, as
    long as the link's record_words: a line that garbles every reply over 20 registers still answers a
    100-register status read, where one request of 100 would fail every try."""
    from trimeter import registers as regs
    from trimeter.device.client import Device
    from trimeter.device.transport import LinkError

    slave = slave_factory(cls=lambda _: GarblingRegisterSlave(longest_clean_words=20))
    link = RtuTransport(slave.port, timeout_s=0.3, attempts=3)
    names = [r.name for r in regs.REGISTERS if r.table == "input_register" and r.address < 100]
    device = Device.__new__(Device)  # the register layer alone: no identity check against this scripted slave
    device.transport, device.identity, device._reconnects_checked = link, None, 0
    values = device.read_many(*names)  # its first requests are lost while they shrink to what the line carries
    assert values["vendor_id"] == regs.BY_NAME["vendor_id"].address  # the slave answers each address with itself
    assert link.record_words <= 30 and slave.counts[0] >= 90
    assert sum(c > 20 for c in slave.counts) <= 3 * 6  # lost requests (3 tries each), at most MAX_SPAN_LOSSES
    link.close()
    with pytest.raises(LinkError):  # a request the line never carries, tried alone, is still a LinkError
        RtuTransport(slave.port, timeout_s=0.1, attempts=2).read_words("input_register", 0, 30)


def test_only_a_clean_read_of_the_whole_record_size_grows_it(slave_factory):
    """A short read passing says nothing of the longer frames the line garbled: the end of a transfer, or a
    poll of a few registers, leaves the record size where the long reads put it."""
    slave = slave_factory()
    link = RtuTransport(slave.port, timeout_s=0.3)
    link.record_words = 16
    for _ in range(3):
        link.read_words("holding_register", 10, 3)
    assert link.record_words == 16
    link.read_words("holding_register", 10, 16)
    assert link.record_words == 20
    link.close()


def test_a_link_closed_by_another_thread_mid_request_is_a_link_error(slave_factory):
    """A service stopping while its loop still waits for a reply (the soak's end): the waiting request ends with
    a DeviceError the service's loop handles, never pyserial's TypeError on a closed port."""
    slave = slave_factory({n: "drop" for n in range(1, 20)})  # the request waits out its timeout
    link = RtuTransport(slave.port, timeout_s=0.5, attempts=2)
    closer = threading.Timer(0.1, link.close)
    closer.start()
    try:
        with pytest.raises(DeviceError, match="closed while a read of 3 holding_registers at 10 waited"):
            link.read_words("holding_register", 10, 3)
    finally:
        closer.join()


def test_a_close_reported_as_a_missing_reply_ends_the_request_and_is_never_reopened(slave_factory, monkeypatch):
    """The close can land while pymodbus waits, which then reports no reply rather than failing: the request
    must end there, not reopen the port its owner just closed and wait out its other attempts."""
    from pymodbus.exceptions import ModbusIOException

    slave = slave_factory()
    link = RtuTransport(slave.port, timeout_s=0.5, attempts=3)

    def closed_while_waiting(*args, **kwargs):
        link.close()
        raise ModbusIOException("No response received, expected at least 4 bytes (0 received)")

    monkeypatch.setattr(link._client, "read_holding_registers", closed_while_waiting)
    with pytest.raises(DeviceError, match="closed while a read of 3 holding_registers at 10 waited"):
        link.read_words("holding_register", 10, 3)
    assert link._client.socket is None and link.stats.reconnects == 0 and link.stats.retries == 0


class DroppingFileRecordSlave(FileRecordSlave):
    """FileRecordSlave that never answers its first request (lost on the way: its reply may still come late)."""

    def frames(self):
        for frame in super().frames():
            if self.requests > 1:
                yield frame


def test_a_long_read_avoids_the_shape_a_late_reply_may_come_in_and_is_not_asked_twice(slave_factory):
    from trimeter.device.transport import unsuspected_record_words

    data = bytes(range(256)) * 2
    slave = slave_factory(cls=lambda _: DroppingFileRecordSlave(data))
    link = RtuTransport(slave.port, timeout_s=0.1)
    # the first read went unanswered; its retry's reply has its shape, so it is confirmed by a second ask
    assert link.read_file_records(1, 0, 20) == data[:40]
    assert slave.requests == 3 and link.stats.confirmations == 1
    assert unsuspected_record_words(link, 20) == 19 and unsuspected_record_words(link, 30) == 30
    # a read of a fresh shape is asked once
    assert link.read_file_records(1, 20, unsuspected_record_words(link, 20)) == data[40:78]
    assert slave.requests == 4 and link.stats.confirmations == 1
    assert unsuspected_record_words(object(), 20) == 20   # a transport that keeps no suspicions
    link.close()


class SlowingSlave(ScriptedSlave):
    """Register value = its address; answers at once for its first `fast` requests, then each `delay_s` late."""

    fast, delay_s = 16, 0.25

    def run(self):
        for frame in self.frames():
            address, fc, start, count = struct.unpack(">BBHH", frame[:6])
            body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *range(start, start + count))
            if self.requests > self.fast:
                threading.Event().wait(self.delay_s)
            os.write(self.master, body + crc16(body))


def test_reads_wait_a_few_times_the_devices_answering_time_and_longer_when_it_slows(slave_factory):
    from trimeter.device.transport import READ_ALLOWANCE_ANSWERS, READ_ALLOWANCE_FLOOR_S

    slave = slave_factory(cls=lambda _: SlowingSlave())
    link = RtuTransport(slave.port, timeout_s=1.0)
    assert link._read_allowance_s() == 1.0   # nothing seen yet: the whole timeout
    for i in range(READ_ALLOWANCE_ANSWERS):
        assert link.read_words("holding_register", i, 2) == [i, i + 1]
    assert READ_ALLOWANCE_FLOOR_S <= link._read_allowance_s() < 1.0 and link.stats.timeouts == 0
    # the device now answers far later than it did: the first tries time out, each waiting twice as long as the
    # last, and the late answers are not taken for the next try's
    assert link.read_words("holding_register", 40, 3) == [40, 41, 42]
    assert link.read_words("holding_register", 7, 3) == [7, 8, 9]
    assert link.stats.timeouts >= 1 and link.stats.failures == 0
    link.close()


class OneSlowAnswerSlave(SlowingSlave):
    """Answers at once, but for request number `slow` (1-based), which it answers `delay_s` late."""

    slow = 17

    def run(self):
        for frame in self.frames():
            address, fc, start, count = struct.unpack(">BBHH", frame[:6])
            body = bytes([address, fc, 2 * count]) + struct.pack(f">{count}H", *range(start, start + count))
            if self.requests == self.slow:
                threading.Event().wait(self.delay_s)
            os.write(self.master, body + crc16(body))


def test_an_answer_let_be_slow_does_not_widen_the_reads_allowance(slave_factory):
    """A request made under slow_reply() (a flash erase) may take far longer than a read: its answer must not
    count as the device's answering time, or every read after it waits the whole timeout on a lost try."""
    from trimeter.device.transport import READ_ALLOWANCE_ANSWERS

    slave = slave_factory(cls=lambda _: OneSlowAnswerSlave())
    link = RtuTransport(slave.port, timeout_s=1.0)
    for i in range(READ_ALLOWANCE_ANSWERS):
        assert link.read_words("holding_register", i, 2) == [i, i + 1]
    before = link._read_allowance_s()
    assert before < 0.5
    with link.slow_reply(2.0):
        assert link.read_words("holding_register", 3, 1) == [3]
    assert slave.requests == OneSlowAnswerSlave.slow and link.stats.timeouts == 0
    assert link._read_allowance_s() < 0.5
    link.close()
