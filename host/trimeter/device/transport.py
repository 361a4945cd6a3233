"""Modbus RTU over a serial port: the ONE module that imports pymodbus (its API moves between minors).

What this layer guarantees to the client above it (trimeter.device.client):
- every request has an explicit timeout and a bounded number of attempts; after the last one a
  DeviceError names the port, the request and the last failure. The timeout is the time the request's
  and the reply's bytes take on the wire at the baud rate, plus `timeout_s` for the device and the
  adapter to answer (the firmware answers from its main loop within milliseconds; a USB adapter adds up
  to its latency timer, 16 ms by default on FTDI chips), plus whatever `slow_reply()` allows for a
  request the device acts on before it answers (a flash erase). A lost request costs its timeout and
  then the drain (below), so a timeout longer than needed is paid on every line error: a read waits a few
  times the device's recent answering time instead, once it has seen enough answers (_read_allowance_s);
- after any failure the input is drained and then flushed, so the framer restarts on a clean buffer
  (garbage, a bad CRC or half a frame never poisons the next request);
- a garbled reply is given up on as soon as the bytes of a whole reply of the expected length are in
  (bit flips do not change a frame's length), not after the timeout: on a noisy line most failed
  attempts are garbled replies, and each would otherwise cost a full timeout;
- a reply is only accepted if its bytes are exactly one frame with a good CRC over all of them (pymodbus
  alone would also take a shorter frame whose "CRC" happens to match inside a garbled reply), and if
  it answers *this* request: same function code, same address/count
  (writes echo them), same length (reads). RTU has no transaction ids, so a late reply to an earlier
  request of a different shape is recognised and discarded, and after a request went unanswered
  everything arriving within `late_reply_window_s` (default: that request's timeout) is discarded (after a garbled
  reply, which was this request's answer, until the line is quiet). A reply later than that, of
  the same shape, cannot be told apart from the answer by its bytes (RTU has no transaction ids), so
  for `late_reply_horizon_s` after a read went unanswered every read whose reply has that read's shape
  is confirmed: asked again, and taken when the two replies are byte for byte the same (a late reply
  comes once, so it cannot agree with itself). When they differ, a file-record read (stored data) is
  asked until two in a row agree; a register or bit read (a live value: two reads may rightly differ)
  is taken once the line stayed quiet until its answer was due (the answer to this request comes within
  its timeout, so a second frame means one of the two was late: both are discarded). A read whose reply
  arrived within the drain is not suspected (its late reply came). Writes are not repeated (a command
  coil would act twice); their echo names the address and count;
- when the serial adapter disappears (USB unplugged, twin restarted) the port is closed and reopened
  until `reconnect_timeout_s` runs out; a Modbus exception reply is raised at once (never retried)
  as ModbusExceptionReply carrying the exception code;
- when every attempt failed, the error is a LinkError: the line, not the device, let the request down,
  so the layer above may try its step again later (trimeter.sequences.steps does, with a reopen).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import time
import weakref
from dataclasses import dataclass, field
from collections.abc import Iterator
from typing import Any, Callable, Protocol

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu.file_message import FileRecord

from trimeter.crc import crc16_modbus
from trimeter.errors import DeviceError

# pymodbus logs every timeout at ERROR; our retries make those routine, and our own errors say more.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())
logging.getLogger("pymodbus").propagate = False

TABLE_FUNCTION = {"coil": 0x01, "discrete_input": 0x02, "holding_register": 0x03, "input_register": 0x04}
# Largest payloads that fit one 253-byte PDU.
MAX_READ_WORDS = 125
MAX_WRITE_WORDS = 123
MAX_READ_BITS = 2000
MAX_FILE_RECORD_WORDS = 120  # FC 0x15: 1 + 7 + 2n <= 253 (one sub-request per frame)
# A noisy line garbles a long frame far more often than a short one (a frame arrives whole with the per-byte
# odds raised to its length): long transfers (file records, register spans) shrink their requests while
# requests fail and grow them back while they pass (record_words).
MIN_FILE_RECORD_WORDS = 8
# A read's attempt waits READ_ALLOWANCE_FACTOR × the slowest of the last READ_ALLOWANCE_ANSWERS answers, at least
# READ_ALLOWANCE_FLOOR_S (above a USB adapter's 16 ms latency timer), at most timeout_s (see _read_allowance_s).
READ_ALLOWANCE_ANSWERS = 16
READ_ALLOWANCE_FACTOR = 4.0
READ_ALLOWANCE_FLOOR_S = 0.03
FILE_RECORD_READ = 0x14


def record_words(transport: object) -> int:
    """The words per request of a long transfer (file records, a span of registers) over this transport now
    (its own estimate where it keeps one, else the largest a file-record frame holds)."""
    words = getattr(transport, "record_words", MAX_FILE_RECORD_WORDS)
    return words if isinstance(words, int) and MIN_FILE_RECORD_WORDS <= words <= MAX_FILE_RECORD_WORDS \
        else MAX_FILE_RECORD_WORDS


def file_record_reply_bytes(words: int) -> int:
    """The length of the reply frame to a one-sub-request file-record read of `words` records (address,
    function, response length, sub-response length, reference type, data, CRC)."""
    return 7 + 2 * words


def unsuspected_record_words(transport: object, words: int) -> int:
    """`words` records, or the nearest shorter count (down to half) whose reply no late reply to an earlier
    unanswered file-record read can be mistaken for: RTU replies carry no record number, so a read of a shape
    that is under suspicion is asked twice (the transport confirms it) and one of a fresh shape once. `words`
    when every such count is under suspicion, or the transport keeps no suspicions."""
    suspect = getattr(transport, "suspect_reply_bytes", None)
    if not callable(suspect):
        return words
    lengths = suspect(FILE_RECORD_READ)
    return next((count for count in range(words, max(1, words // 2) - 1, -1)
                 if file_record_reply_bytes(count) not in lengths), words)


class LinkError(DeviceError):
    """Every attempt at one request failed (no reply, garbled replies, replies to other requests): the
    link is noisy or gone. Unlike a ModbusExceptionReply (a refusal) the request may succeed if tried again."""


class _GarbledReply(Exception):
    """Raised from the receive hook: a whole reply's worth of bytes arrived and they are not one frame."""


class ModbusExceptionReply(DeviceError):
    """The device answered with a Modbus exception (code 1: function, 2: address, 3: value, 4: failure)."""

    def __init__(self, what: str, code: int) -> None:
        super().__init__(f"device refused {what}: Modbus exception {code:02d} ({_EXCEPTION_TEXT.get(code, 'unknown')})")
        self.code = code


_EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value", 4: "device failure",
                   6: "device busy"}


def is_one_whole_frame(buffer: bytes) -> bool:
    """True when `buffer` is exactly one RTU frame: a CRC over everything before its last two bytes
    (a CRC-16 appended low byte first leaves a residue of 0)."""
    return len(buffer) >= 4 and crc16_modbus(buffer) == 0


class Transport(Protocol):
    """The byte-level contract the typed client needs; tests substitute an in-memory fake."""

    def read_bits(self, table: str, address: int, count: int) -> list[bool]: ...
    def read_words(self, table: str, address: int, count: int) -> list[int]: ...
    def write_bits(self, address: int, values: list[bool]) -> None: ...
    def write_words(self, address: int, values: list[int]) -> None: ...
    def read_file_records(self, file_number: int, record_number: int, count: int) -> bytes: ...
    def write_file_records(self, file_number: int, record_number: int, data: bytes) -> None: ...
    def close(self) -> None: ...


@dataclass
class LinkStats:
    """Counters of what the link had to recover from (shown by `trimeter config list` / the HIL report)."""

    requests: int = 0
    retries: int = 0
    stale_replies: int = 0
    confirmations: int = 0    # reads asked again because a late reply of the same shape may still arrive
    garbled_replies: int = 0  # bytes of a whole reply arrived but were not exactly one frame with a good CRC
    timeouts: int = 0         # attempts that got no reply within the timeout
    reconnects: int = 0
    failures: int = 0
    resumed_reads: int = 0    # a long read (a map table) went on from where a lost request stopped it
    busy_s: float = field(default=0.0)  # wall time spent inside requests (host + protocol overhead)
    bus_wait_s: float = 0.0   # wall time waiting for the turn on a bus shared with other instruments (device.bus)


# The transports open in this process by port: a serial port opens once (exclusively), so a second user of the
# same link in the process — the instrument's own spectrometer (trimeter.spectrometer.mcu) — shares it.
_LIVE: "weakref.WeakValueDictionary[str, RtuTransport]" = weakref.WeakValueDictionary()


def live_transport(port: str, address: int) -> "RtuTransport | None":
    """The open transport on `port` to slave `address` in this process, if there is one."""
    transport = _LIVE.get(port)
    return transport if transport is not None and transport.address == address and transport.is_open else None


class RtuTransport:
    """Modbus RTU master on one serial port, for one slave address."""

    def __init__(self, port: str, *, address: int = 1, baudrate: int = 19200, timeout_s: float = 0.15,
                 attempts: int = 6, late_reply_window_s: float | None = None, late_reply_horizon_s: float = 10.0,
                 reconnect_timeout_s: float = 10.0, local_echo: bool = False) -> None:
        """local_echo: an RS-485 adapter that hears its own transmission (half duplex without echo
        suppression); pymodbus then strips the echoed request before framing the reply."""
        if not 1 <= address <= 247:
            raise DeviceError(f"Modbus address {address} is outside 1..247")
        self.port = port
        self.address = address
        self.timeout_s = timeout_s
        self.baudrate = baudrate
        self.attempts = max(1, attempts)
        self.late_reply_window_s = late_reply_window_s  # None: each request's own timeout
        self.late_reply_horizon_s = late_reply_horizon_s
        # (until when, function code, reply length) of each read that went unanswered: its reply may still come
        self._unanswered: list[tuple[float, int, int]] = []
        self._slow_reply_s = 0.0
        self._request_timeout_s = timeout_s
        self._answer_s: collections.deque[float] = collections.deque(maxlen=READ_ALLOWANCE_ANSWERS)
        self.reconnect_timeout_s = reconnect_timeout_s
        self.stats = LinkStats()
        self.record_words = MAX_FILE_RECORD_WORDS  # see MIN_FILE_RECORD_WORDS
        # retries=0: we retry ourselves, so every retry drains + flushes and checks the reply's shape.
        self._client = ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate, timeout=timeout_s,
                                          retries=0, reconnect_delay=0, name=f"trimeter@{port}",
                                          handle_local_echo=local_echo, trace_packet=self._trace_packet)
        self._received = b""
        self._expected_reply_bytes = 0  # length of the normal reply to the request in flight (0: unknown)
        self._quiet_s = max(0.02, 10 * 11 / baudrate)  # line quiet this long after a garbled reply: it is over
        self.is_open = False
        self._open(deadline=time.monotonic() + reconnect_timeout_s)
        self.is_open = True
        _LIVE[port] = self

    # ------------------------------------------------------------------------------------ link care
    def _open(self, deadline: float) -> None:
        while not self._client.connect():
            if time.monotonic() >= deadline:
                raise DeviceError(f"cannot open serial port {self.port} (no such device, or it is in use)")
            time.sleep(0.05)

    def reopen(self) -> None:
        """Close and open the port again (a wedged USB adapter recovers this way); counted in stats.reconnects,
        which makes trimeter.device.Device check the identity of whatever answers next."""
        self._client.close()
        self.stats.reconnects += 1
        self._open(deadline=time.monotonic() + self.reconnect_timeout_s)

    @contextlib.contextmanager
    def slow_reply(self, seconds: float) -> Iterator[None]:
        """Requests made inside may take `seconds` longer to be answered: the device acts on them before it
        replies (a flash sector erase blocks the firmware's main loop)."""
        saved, self._slow_reply_s = self._slow_reply_s, seconds
        try:
            yield
        finally:
            self._slow_reply_s = saved

    def request_timeout_s(self, request_bytes: int, reply_bytes: int) -> float:
        """How long to wait for a reply: both frames' time on the wire (11 bits a byte: start, 8 data, parity
        or a second stop, stop) plus the answering allowance and any slow_reply()."""
        return self.timeout_s + self._slow_reply_s + (request_bytes + reply_bytes) * 11 / self.baudrate

    def _drain(self, *, answered: bool = False) -> bool:
        """After a failure: discard everything that arrives for the whole late-reply window, then flush.
        Stopping at the first quiet moment would let a reply that is merely late land in the next
        request's read — and a stale `busy` or `uptime_s` of the right shape is indistinguishable.
        `answered`: the request's reply did arrive (garbled), so nothing of it is still on its way and
        draining until the line is quiet suffices. Returns whether anything arrived (a late reply did)."""
        sock = self._client.socket
        heard = False
        if sock is None:
            return heard
        now = time.monotonic()
        window = self._request_timeout_s if self.late_reply_window_s is None else self.late_reply_window_s
        end, quiet_until = now + window, now + self._quiet_s
        while time.monotonic() < (quiet_until if answered else end):
            waiting = self._waiting(sock)
            if waiting:
                sock.read(waiting)
                heard = True
                quiet_until = min(end, time.monotonic() + self._quiet_s)
            time.sleep(0.002)
        sock.reset_input_buffer()
        return heard

    def close(self) -> None:
        self.is_open = False
        if _LIVE.get(self.port) is self:
            del _LIVE[self.port]
        self._client.close()

    def listen_after(self, frame: bytes, listen_s: float) -> bytes:
        """Send raw `frame` and return every byte that arrives within `listen_s` — all the answers, not the
        first reply pymodbus would frame (trimeter.device.bus counts them to find two devices at one address)."""
        if self._client.socket is None:
            self.reopen()
        sock = self._client.socket
        if sock is None:
            raise LinkError(f"cannot open serial port {self.port}")
        sock.reset_input_buffer()
        sock.write(frame)
        sock.flush()
        data, deadline = b"", time.monotonic() + listen_s
        while time.monotonic() < deadline:
            waiting = self._waiting(sock)
            data += sock.read(waiting) if waiting else b""
            time.sleep(0.002)
        return data

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        """pymodbus hands every receive buffer through here (all bytes since the request: its RTU framer
        consumes nothing until it finds a frame): keep them, and stop waiting as soon as they are as long
        as the expected reply without being one frame — pymodbus would wait out the timeout for more."""
        if not sending:
            self._received = bytes(data)
            if self._expected_reply_bytes and len(data) >= self._expected_reply_bytes and not is_one_whole_frame(data):
                raise _GarbledReply()
        return data

    # ------------------------------------------------------------------------------------- requests
    def suspect_reply_bytes(self, function_code: int) -> set[int]:
        """The reply lengths of this function code that a late reply to an unanswered read may still arrive in
        (within the horizon): a read whose reply has one of them is confirmed."""
        now = time.monotonic()
        self._unanswered = [entry for entry in self._unanswered if entry[0] > now]
        return {reply_bytes for _, code, reply_bytes in self._unanswered if code == function_code}

    def _read_allowance_s(self) -> float:
        """How long a read's attempt waits for the device to answer, beyond the frames' time on the wire: a few times
        the slowest of its recent answers (those let be slow by slow_reply() left out; at least READ_ALLOWANCE_FLOOR_S),
        never more than `timeout_s`, which it is until enough answers were seen. On a noisy line most lost attempts are
        requests the device never heard, and each costs this allowance twice (the wait, then the drain): the full
        `timeout_s` was most of a noisy table read. A device slower than that is waited for with the allowance doubled
        at each unanswered try of a request, and its late reply is caught by the reply shapes' suspicion as any other
        late reply is; writes always wait the full `timeout_s` (asking one again could act twice)."""
        if len(self._answer_s) < READ_ALLOWANCE_ANSWERS:
            return self.timeout_s
        return min(self.timeout_s, max(READ_ALLOWANCE_FLOOR_S, READ_ALLOWANCE_FACTOR * max(self._answer_s)))

    def _late_reply_possible(self, function_code: int, reply_bytes: int) -> bool:
        """Whether an unanswered read's reply of this shape may still arrive (within the horizon)."""
        return reply_bytes in self.suspect_reply_bytes(function_code)

    def _another_frame_by(self, deadline: float) -> bool:
        """Whether any byte arrives before `deadline` (the time by which this request's answer has come)."""
        sock = self._client.socket
        while sock is not None and not self._waiting(sock):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.002)
        return sock is not None

    def _waiting(self, sock: Any) -> int:
        """Bytes waiting on the port; a LinkError when the port was closed under this request (another thread
        closed the link: pyserial then fails with a TypeError or ValueError, not an OSError)."""
        try:
            return int(sock.in_waiting)
        except (OSError, TypeError, ValueError):
            raise self._closed_under("a request") from None

    def _closed_under(self, what: str) -> LinkError:
        return LinkError(f"the serial port {self.port} was closed while {what} waited for its reply")

    def _execute(self, what: str, function_code: int, call: Callable[[ModbusSerialClient], Any],
                 answers: Callable[[Any], bool], request_bytes: int, reply_bytes: int, *,
                 read: str | None = None) -> Any:
        """The reply is the PDU class of the request's function code (bits, registers or records), hence Any.
        `request_bytes`, `reply_bytes`: the lengths of the request frame and of its normal (non-exception)
        reply frame, address and CRC included. `read`: asking again is harmless, so a reply that a late one
        could be mistaken for is confirmed (see the module's docstring): by a second reply that agrees, then
        for "live" values by a quiet line until the answer is due, for "stored" ones by two that agree."""
        started = time.monotonic()
        self.stats.requests += 1
        full_timeout = self.request_timeout_s(request_bytes, reply_bytes)
        wire_s = (request_bytes + reply_bytes) * 11 / self.baudrate
        unanswered_tries = 0
        last_failure = "no attempt"
        candidate: bytes | None = None  # a reply waiting for its confirmation
        quiet = False
        try:
            for attempt in range(self.attempts + 1):
                if attempt == self.attempts and candidate is None:
                    break  # the extra attempt only confirms the last attempt's reply
                if attempt:
                    self.stats.retries += 1
                if not self.is_open:  # closed by another thread between attempts: never reopened behind its back
                    raise self._closed_under(what)
                try:
                    if self._client.socket is None:
                        self.reopen()
                    self._received = b""
                    self._expected_reply_bytes = reply_bytes
                    timeout = full_timeout
                    if read is not None and not self._slow_reply_s:
                        timeout = min(full_timeout, wire_s + self._read_allowance_s() * 2 ** unanswered_tries)
                    self._request_timeout_s = timeout  # the drain's window after it (see _drain)
                    self._client.comm_params.timeout_connect = timeout  # what pymodbus's serial client waits
                    sent = time.monotonic()
                    answer_by = sent + full_timeout
                    reply = call(self._client)
                except _GarbledReply:
                    self.stats.garbled_replies += 1
                    last_failure = f"a garbled reply ({self._received.hex(' ')})"
                    self._drain(answered=True)
                    continue
                except (ModbusException, asyncio.TimeoutError, OSError) as exc:
                    if not self.is_open:  # pymodbus may report the close as a missing reply
                        raise self._closed_under(what) from None
                    # ConnectionException / SerialException (an OSError) = the adapter went away.
                    if isinstance(exc, ModbusIOException) and "No response" in str(exc):
                        # pymodbus's own wording ("… CLOSING CONNECTION") describes a close it does not do
                        # on a serial client; what happened is that no whole reply came back in time.
                        self.stats.timeouts += 1
                        unanswered_tries += 1
                        unanswered = not self._received
                        last_failure = (f"no reply within {timeout:.3g} s" if not self._received else
                                        f"an incomplete reply within {timeout:.3g} s ({self._received.hex(' ')})")
                    else:
                        last_failure = str(exc).strip() or type(exc).__name__
                        unanswered = False
                    if isinstance(exc, (ConnectionException, OSError)) or self._client.socket is None:
                        self.reopen()
                    elif not self._drain() and unanswered and read is not None:
                        # its reply did not come within the drain either: it may still, for the horizon
                        self._unanswered.append((time.monotonic() + self.late_reply_horizon_s, function_code,
                                                 reply_bytes))
                    continue
                if not is_one_whole_frame(self._received):
                    # pymodbus's framer also accepts a CRC over a prefix of the buffer (it hunts for frames
                    # in garbage), so two flipped bits can pass as a shorter frame — e.g. a read reply
                    # 01 02 01 01 .. turned into the exception 01 82 01 + a matching "CRC". Only a
                    # buffer that is exactly one frame with its CRC over all of it counts as a reply.
                    self.stats.garbled_replies += 1
                    last_failure = f"a garbled reply ({self._received.hex(' ')})"
                    self._drain(answered=True)
                    continue
                if not self._slow_reply_s:  # an answer let be slow (a flash erase) says nothing of a read's
                    self._answer_s.append(max(0.0, time.monotonic() - sent - wire_s))
                if reply.isError() and reply.function_code & 0x7F == function_code:
                    raise ModbusExceptionReply(what, int(getattr(reply, "exception_code", 0)))
                if reply.isError() or not answers(reply):
                    self.stats.stale_replies += 1
                    last_failure = f"a reply that answers another request ({type(reply).__name__})"
                    self._drain()
                    continue
                if read is None or not self._late_reply_possible(function_code, reply_bytes):
                    return reply
                if quiet:  # a reply counts once nothing else arrived by the time this request's answer is due
                    if not self._another_frame_by(answer_by):
                        return reply
                    self.stats.stale_replies += 1
                    last_failure = "two replies to one read (one was a late reply to an earlier read)"
                    self._drain(answered=True)
                    continue
                if candidate == self._received:
                    return reply  # two asks agree: a late reply comes once, it cannot agree with itself
                if candidate is not None:
                    self.stats.stale_replies += 1
                    last_failure = "replies that disagree (a late reply to an earlier read)"
                    # a live value may rightly change between two asks: from now on, the quiet line decides
                    quiet = read == "live"
                candidate = self._received
                self.stats.confirmations += 1
            self.stats.failures += 1
            raise LinkError(f"no valid reply from the device on {self.port} to {what} "
                            f"after {self.attempts} attempts (last: {last_failure})")
        except (AttributeError, TypeError, ValueError):
            # pyserial and pymodbus fail this way on a port another thread closed mid-request (a service stopping
            # while its loop still waits): a lost link, which the caller handles; on an open port, a real bug
            if self.is_open and self._client.socket is not None:
                raise
            raise self._closed_under(what) from None
        finally:
            self._expected_reply_bytes = 0
            self.stats.busy_s += time.monotonic() - started

    def read_bits(self, table: str, address: int, count: int) -> list[bool]:
        fc = TABLE_FUNCTION[table]
        method = {1: "read_coils", 2: "read_discrete_inputs"}[fc]
        padded = (count + 7) // 8 * 8
        reply = self._execute(
            f"a read of {count} {table}s at {address}", fc,
            lambda c: getattr(c, method)(address, count=count, device_id=self.address),
            lambda r: r.function_code == fc and len(r.bits) == padded, 8, 5 + padded // 8, read="live")
        return [bool(b) for b in reply.bits[:count]]

    def read_words(self, table: str, address: int, count: int) -> list[int]:
        fc = TABLE_FUNCTION[table]
        method = {3: "read_holding_registers", 4: "read_input_registers"}[fc]
        with self._sizing_records(count):
            reply = self._execute(
                f"a read of {count} {table}s at {address}", fc,
                lambda c: getattr(c, method)(address, count=count, device_id=self.address),
                lambda r: r.function_code == fc and len(r.registers) == count, 8, 5 + 2 * count, read="live")
        return list(reply.registers)

    def write_bits(self, address: int, values: list[bool]) -> None:
        self._execute(
            f"a write of {len(values)} coils at {address}", 0x0F,
            lambda c: c.write_coils(address, list(values), device_id=self.address),
            lambda r: r.function_code == 0x0F and (r.address, r.count) == (address, len(values)),
            9 + (len(values) + 7) // 8, 8)

    def write_words(self, address: int, values: list[int]) -> None:
        self._execute(
            f"a write of {len(values)} holding registers at {address}", 0x10,
            lambda c: c.write_registers(address, list(values), device_id=self.address),
            lambda r: r.function_code == 0x10 and (r.address, r.count) == (address, len(values)),
            9 + 2 * len(values), 8)

    def read_file_records(self, file_number: int, record_number: int, count: int) -> bytes:
        request = [FileRecord(file_number=file_number, record_number=record_number, record_length=2 * count)]
        with self._sizing_records(count):
            reply = self._execute(
                f"a file-record read of file {file_number} record {record_number} (+{count})", FILE_RECORD_READ,
                lambda c: c.read_file_record(request, device_id=self.address),
                lambda r: r.function_code == FILE_RECORD_READ and len(r.records) == 1
                and len(r.records[0].record_data) == 2 * count,
                12, file_record_reply_bytes(count), read="stored")
        return bytes(reply.records[0].record_data)

    def write_file_records(self, file_number: int, record_number: int, data: bytes) -> None:
        request = [FileRecord(file_number=file_number, record_number=record_number, record_data=bytes(data))]
        with self._sizing_records(len(data) // 2):
            self._execute(
                f"a file-record write of file {file_number} record {record_number} (+{len(data) // 2})", 0x15,
                lambda c: c.write_file_record(request, device_id=self.address),
                lambda r: r.function_code == 0x15 and len(r.records) == 1
                and (r.records[0].file_number, r.records[0].record_number) == (file_number, record_number),
                12 + len(data), 12 + len(data))

    @contextlib.contextmanager
    def _sizing_records(self, words: int) -> Iterator[None]:
        """record_words after one file-record or register request of `words` words: halved when it failed, or
        had four or more tries fail (garbled or missing replies); grown by a quarter when its first try passed and it
        was at least record_words long (a shorter one passing says nothing of the longer frames that failed)."""
        failures_before = self.stats.garbled_replies + self.stats.timeouts
        try:
            yield
        except LinkError:
            self.record_words = max(MIN_FILE_RECORD_WORDS, self.record_words // 2)
            raise
        failed = self.stats.garbled_replies + self.stats.timeouts - failures_before
        if failed >= 4:
            self.record_words = max(MIN_FILE_RECORD_WORDS, self.record_words // 2)
        elif failed == 0 and words >= self.record_words:
            self.record_words = min(MAX_FILE_RECORD_WORDS, self.record_words + max(1, self.record_words // 4))
