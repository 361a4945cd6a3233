"""The typed client against an in-memory instrument (tests/fakes.py): codec, identity checks,
range checks by name, motion waits, and the map-table transfer (resume, verify, A/B activation)."""

import struct
import zlib

import pytest
from hypothesis import given, strategies as st

from fakes import FakeInstrument
from trimeter import registers as regs
from trimeter.device.client import Device, decode, encode
from trimeter.device.transport import ModbusExceptionReply
from trimeter.errors import DeviceError, InputError


def test_identity_is_checked_and_a_mismatched_register_map_is_refused():
    Device(FakeInstrument())
    with pytest.raises(DeviceError, match="register map mismatch.*0xDEADBEEF"):
        Device(FakeInstrument(regmap_hash=0xDEADBEEF))
    with pytest.raises(DeviceError, match="firmware 9.0.0 is incompatible"):
        Device(FakeInstrument(firmware=(9, 0, 0)))


@given(st.sampled_from([r for r in regs.REGISTERS if r.access == "rw" and r.type != "bool" and not r.enum]),
       st.floats(0, 1))
def test_encode_decode_round_trip_within_range(reg, fraction):
    raw = reg.min + fraction * (reg.max - reg.min)
    if reg.type != "f32":
        raw = round(raw)
    if reg.allowed:
        raw = reg.allowed[int(fraction * (len(reg.allowed) - 1))]
    physical = raw * reg.scale
    back = decode(reg, encode(reg, physical))
    assert back == pytest.approx(physical, rel=1e-6, abs=1e-9)


def test_out_of_range_values_are_refused_naming_the_field():
    dev = Device(FakeInstrument())
    with pytest.raises(InputError, match=r"led_panels_level: 1.5 is outside 0..1"):
        dev.write("led_panels_level", 1.5)
    with pytest.raises(InputError, match="modbus_baud: 12345 is not one of 9600"):
        dev.write("modbus_baud", 12345)
    with pytest.raises(InputError, match="status_pattern: 'disco' is not one of off, on"):
        dev.write("status_pattern", "disco")
    with pytest.raises(InputError, match="is read-only"):
        dev.write("uptime_s", 3)
    with pytest.raises(InputError, match="no register named 'position_furlongs'"):
        dev.read("position_furlongs")
    with pytest.raises(InputError, match="NaN"):
        dev.write("speed_mm_s", float("nan"))


def test_scaled_and_float_values_reach_the_wire_as_the_map_says():
    fake = FakeInstrument()
    dev = Device(fake)
    dev.write("led_panels_level", 0.5)
    assert fake.hr[regs.BY_NAME["led_panels_level"].address] == 500
    dev.write("speed_mm_s", 12.5)
    a = regs.BY_NAME["speed_mm_s"].address
    assert struct.unpack(">f", struct.pack(">2H", *fake.hr[a:a + 2]))[0] == 12.5  # high word first
    assert dev.read("speed_mm_s") == 12.5
    assert dev.read("led_panels_level") == pytest.approx(0.5)
    assert dev.read("status_pattern") is regs.StatusPattern.SLOW_BLINK


def test_goto_homes_first_and_waits_until_idle():
    fake = FakeInstrument(busy_polls=3)
    dev = Device(fake)
    dev.goto("white")
    assert fake.commands == ["home", "goto_white"]
    assert dev.read("position_slot") is regs.Slot.WHITE
    assert not dev.read("busy")


def test_wait_idle_times_out_with_a_clear_error():
    fake = FakeInstrument(busy_polls=10**9)
    now = [0.0]
    dev = Device(fake, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    dev.command("home")
    with pytest.raises(DeviceError, match="still busy after 1 s"):
        dev.wait_idle(1.0)


def test_flash_map_writes_inactive_slot_verifies_and_activates():
    fake = FakeInstrument()
    dev = Device(fake)
    first = bytes(range(256)) * 100 + b"x"  # odd length, spans records across several frames
    assert dev.flash_map(first, version=1) == regs.MapSlot.A
    second = bytes(reversed(first))
    assert dev.flash_map(second, version=2) == regs.MapSlot.B
    assert fake.active == regs.MapSlot.B and fake.slots[regs.MapSlot.A] == first
    assert dev.read_map("b") == second
    status = dev.map_status()
    assert status["map_slot_b_crc32"] == zlib.crc32(second) and status["map_slot_b_version"] == 2


def test_interrupted_flash_leaves_old_map_active_and_resumes():
    fake = FakeInstrument()
    dev = Device(fake)
    old, new = b"old map" * 1000, b"new map!" * 2000
    dev.flash_map(old, version=1)
    fake.fail_file_write_at = fake.file_writes + 50
    with pytest.raises(DeviceError, match="link lost"):
        dev.flash_map(new, version=2)
    assert fake.active == regs.MapSlot.A and dev.read_map("a") == old
    writes_before = fake.file_writes
    fake.fail_file_write_at = None
    assert dev.flash_map(new, version=2) == regs.MapSlot.B
    total_frames = -(-len(new) // 240)
    assert fake.file_writes - writes_before < total_frames  # resumed, not restarted
    assert dev.read_map("b") == new


def test_oversized_map_is_refused_before_touching_the_device():
    fake = FakeInstrument()
    with pytest.raises(InputError, match="slot holds 131072"):
        Device(fake).flash_map(b"\0" * (regs.MAP_SLOT_CAPACITY_BYTES + 1), version=1)
    assert fake.file_writes == 0


def test_identity_is_checked_again_after_the_transport_reopened_the_port():
    from trimeter.device.transport import LinkStats

    fake = FakeInstrument()
    fake.stats = LinkStats()
    dev = Device(fake)
    assert dev.read("led_panels_level") == pytest.approx(1.0)
    # the adapter was re-plugged and something with other firmware answers now
    fake._set("ir", regs.BY_NAME["regmap_hash"], 0x12345678)
    fake.stats.reconnects += 1
    with pytest.raises(DeviceError, match="register map mismatch"):
        dev.read("led_panels_level")


def test_position_in_millimetres_is_derived_from_steps_and_the_configured_scale():
    fake = FakeInstrument()
    fake._set("ir", regs.BY_NAME["position_steps"], 4800)
    dev = Device(fake)
    dev.write("steps_per_mm", 80)
    assert dev.read("position_mm") == pytest.approx(60.0)


def test_destructive_commands_are_unlocked_right_before_and_only_those():
    fake = FakeInstrument()
    dev = Device(fake)
    with pytest.raises(ModbusExceptionReply) as refused:  # what the firmware does without an unlock
        dev.write("command", "save_config")
    assert refused.value.code == 1
    sent = []
    real = fake.write_words
    fake.write_words = lambda address, values: (sent.append((address, list(values))), real(address, values))[1]
    dev.command("save_config")
    dev.command("load_defaults")
    dev.command("home")
    unlock, command = regs.BY_NAME["unlock"].address, regs.BY_NAME["command"].address
    assert sent == [(unlock, [regs.Unlock.KEY]), (command, [regs.Command.SAVE_CONFIG]),
                    (unlock, [regs.Unlock.KEY]), (command, [regs.Command.LOAD_DEFAULTS]),
                    (command, [regs.Command.HOME])]
    assert fake.commands == ["save_config", "load_defaults", "home"]


def test_a_window_that_closed_under_a_retried_request_is_reopened_once():
    fake = FakeInstrument()
    dev = Device(fake)
    real = fake.write_words
    closes = iter([True])  # the first destructive request finds the window closed, the next one open

    def slow_link(address, values):
        if address == regs.BY_NAME["command"].address and next(closes, False):
            fake.unlocked = False
        return real(address, values)

    fake.write_words = slow_link
    dev.command("save_config")
    assert fake.commands == ["save_config"]
    fake.write_words = lambda address, values: (setattr(fake, "unlocked", False), real(address, values))[1]
    with pytest.raises(DeviceError, match="save_config: the device refused it right after an unlock"):
        dev.command("save_config")


def test_rate_limited_erases_and_rejected_tables_get_clear_messages():
    fake = FakeInstrument()
    dev = Device(fake)

    def busy(address, values):
        raise ModbusExceptionReply("write", 6)

    real = fake.write_words
    fake.write_words = lambda address, values: (busy if address == regs.BY_NAME["command"].address
                                                else real)(address, values)
    with pytest.raises(DeviceError, match="save_config: the device's flash erase budget is used up"):
        dev.command("save_config")
    fake.write_words = real
    # begin_write refused by the erase rate limit
    status = regs.BY_NAME["map_op_status"]
    real_map = fake._on_map_command
    fake._on_map_command = lambda cmd: fake._set("ir", status, regs.MapOpStatus.ERROR_BUSY)
    with pytest.raises(DeviceError, match="map flash: the device's flash erase budget"):
        dev.flash_map(b"table" * 100, version=1)
    # verify: the CRC matched but the firmware does not take the bytes for a map table

    def not_a_table(cmd):
        real_map(cmd)
        if cmd == regs.MapCommand.VERIFY:
            fake._set("ir", status, regs.MapOpStatus.ERROR_TABLE)

    fake._on_map_command = not_a_table
    with pytest.raises(DeviceError, match="does not accept these bytes as a map table"):
        dev.flash_map(b"table" * 100, version=1)
    assert fake.active == regs.MapSlot.NONE


class _LossyInstrument(FakeInstrument):
    """Every `every`-th file record request is lost for good (all its transport attempts failed), and a reopen
    clears the slot selection as a reset device would."""

    def __init__(self, every: int):
        super().__init__()
        self.every, self.calls, self.reopens = every, 0, 0

    def read_file_records(self, file_number, record_number, count):
        self.calls += 1
        if self.calls % self.every == 0:
            from trimeter.device.transport import LinkError

            raise LinkError("no reply")
        return super().read_file_records(file_number, record_number, count)

    def reopen(self):
        self.reopens += 1
        self.hr[regs.BY_NAME["map_read_slot"].address] = 0


def test_a_map_read_resumes_where_a_lost_record_stopped_it():
    from trimeter.device.transport import LinkError

    fake = _LossyInstrument(every=4)
    dev = Device(fake)
    table = bytes(range(256)) * 100 + b"x"
    fake.every = 10**9
    dev.flash_map(table, version=1)
    fake.every, fake.calls = 4, 0
    assert dev.read_map("a") == table           # a quarter of the records lost, the read goes on from each
    assert fake.reopens > 5 and fake.hr[regs.BY_NAME["map_read_slot"].address] == 0
    fake.every = 1                               # nothing gets through: given up when the budget is spent
    with pytest.raises(LinkError):
        dev.read_map("a", time_budget_s=0.05)


class _GarblingInstrument(_LossyInstrument):
    """_LossyInstrument whose lost records were lost to garbled replies (the line is there, only noisy)."""

    def __init__(self, every: int):
        super().__init__(every)
        from types import SimpleNamespace

        self.stats = SimpleNamespace(garbled_replies=0, resumed_reads=0, reconnects=0)

    def read_file_records(self, file_number, record_number, count):
        if (self.calls + 1) % self.every == 0:
            self.stats.garbled_replies += 6
        return super().read_file_records(file_number, record_number, count)


def test_a_record_lost_to_garbled_replies_is_asked_again_without_a_reopen():
    fake = _GarblingInstrument(every=10**9)
    dev = Device(fake)
    table = bytes(range(256)) * 100 + b"x"
    dev.flash_map(table, version=1)
    fake.every, fake.calls = 4, 0
    assert dev.read_map("a") == table
    assert fake.reopens == 0 and fake.stats.resumed_reads > 5
