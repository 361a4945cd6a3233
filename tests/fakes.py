"""In-memory fakes for the layers above the wire: an instrument behind the Transport contract and a
spectrometer behind the Spectrometer protocol whose optics are set by the test (known I_b, I_w, I_c).

They follow hardware/registers.md (through trimeter.registers) so the client and the sequences are
tested without a pty, a firmware build or a twin. Wire-level behaviour is tested in tests/device/
against a real pty, and everything together in tests/hil/ against the twin.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from trimeter import registers as regs
from trimeter.device.transport import ModbusExceptionReply
from trimeter.spectrometer.base import SpectrometerDescription


class FakeInstrument:
    """A trimeter's register map in memory, with instant motion (busy for `busy_polls` reads)."""

    def __init__(self, *, regmap_hash: int = regs.REGMAP_HASH, firmware=regs.FIRMWARE_VERSION, busy_polls: int = 2):
        self.coils = [False] * regs.SPANS["coil"]
        self.inputs = [False] * regs.SPANS["discrete_input"]
        self.ir = [0] * regs.SPANS["input_register"]
        self.hr = [0] * regs.SPANS["holding_register"]
        for reg in regs.REGISTERS:
            if reg.table == "holding_register":
                self._set("hr", reg, reg.default)
        self._set("ir", regs.BY_NAME["vendor_id"], regs.VENDOR_ID)
        self._set("ir", regs.BY_NAME["model_id"], regs.MODEL_ID)
        for part, value in zip(("major", "minor", "patch"), firmware, strict=True):
            self._set("ir", regs.BY_NAME[f"firmware_version_{part}"], value)
        self._set("ir", regs.BY_NAME["regmap_hash"], regmap_hash)
        self.busy_polls = busy_polls
        self._busy_left = 0
        self.slots = {regs.MapSlot.A: b"", regs.MapSlot.B: b""}
        self.versions = {regs.MapSlot.A: 0, regs.MapSlot.B: 0}
        self.active = regs.MapSlot.NONE
        self.write_buffer: bytearray | None = None
        self.write_target = regs.MapSlot.NONE
        self.file_writes = 0
        self.fail_file_write_at: int | None = None  # raise a link failure on this file-record write
        self.commands: list[str] = []
        self.unlocked = False      # like the firmware: one destructive command per unlock write
        self.time_s = 0.0          # device clock: advances tick_s per request (what a real link costs)
        self.tick_s = 0.05
        self.on_request = None     # callable(fake) run on every request (fault injection in tests)
        # lamp monitor: per LED channel (left, right, collimated), its emission relative to nominal, seen by a
        # photodiode past its shutter: dark offset + span × LED on × shutter open × emission
        self.lamp_emission = [1.0, 1.0, 1.0]
        self.monitor_dark_counts, self.monitor_span_counts = 60, 3200
        self._refresh_map_registers()

    # ------------------------------------------------------------------------------ helpers
    def _set(self, table, reg, value):
        """Store a raw (unscaled) value."""
        words = struct.unpack(f">{reg.words}H", struct.pack({"u16": ">H", "i16": ">h", "u32": ">I", "i32": ">i",
                                                            "f32": ">f"}[reg.type],
                                                           value if reg.type == "f32" else int(round(value))))
        getattr(self, table)[reg.address:reg.address + reg.words] = list(words)

    def get(self, name):
        reg = regs.BY_NAME[name]
        table = {"coil": "coils", "discrete_input": "inputs", "input_register": "ir",
                 "holding_register": "hr"}[reg.table]
        if reg.type == "bool":
            return getattr(self, table)[reg.address]
        words = getattr(self, table)[reg.address:reg.address + reg.words]
        raw = struct.unpack({"u16": ">H", "i16": ">h", "u32": ">I", "i32": ">i", "f32": ">f"}[reg.type],
                            struct.pack(f">{reg.words}H", *words))[0]
        return raw

    def press_button(self):
        reg = regs.BY_NAME["button_events"]
        self.ir[reg.address] = (self.ir[reg.address] + 1) & 0xFFFF

    def reset(self):
        """Like a power cycle: unhomed, LEDs off, uptime from 0 (config and map slots persist)."""
        self.coils = [False] * len(self.coils)
        self.inputs[regs.BY_NAME["homed"].address] = False
        self._set("ir", regs.BY_NAME["position_slot"], 0)
        self.time_s = 0.0

    def _tick(self):
        self.time_s += self.tick_s
        self._set("ir", regs.BY_NAME["uptime_s"], int(self.time_s))
        if self.on_request:
            self.on_request(self)

    def _refresh_map_registers(self):
        self._set("ir", regs.BY_NAME["map_active_slot"], int(self.active))
        for slot in (regs.MapSlot.A, regs.MapSlot.B):
            key = slot.name.lower()
            data = self.slots[slot]
            self._set("ir", regs.BY_NAME[f"map_slot_{key}_valid"], 1 if data else 0)
            self._set("ir", regs.BY_NAME[f"map_slot_{key}_length"], len(data))
            self._set("ir", regs.BY_NAME[f"map_slot_{key}_crc32"], zlib.crc32(data) if data else 0)
            self._set("ir", regs.BY_NAME[f"map_slot_{key}_version"], self.versions[slot])

    # ----------------------------------------------------------------------- Transport contract
    def read_bits(self, table, address, count):
        self._tick()
        if table == "discrete_input":
            if self._busy_left:
                self._busy_left -= 1
            self.inputs[regs.BY_NAME["busy"].address] = self._busy_left > 0
            return list(self.inputs[address:address + count])
        return list(self.coils[address:address + count])

    def _refresh_lamp_monitor(self):
        for i, lamp in enumerate(("panel_left", "panel_right", "collimated")):
            lit = self.coils[i] and self.coils[3 + i]
            self._set("ir", regs.BY_NAME[f"lamp_monitor_{lamp}"],
                      self.monitor_dark_counts + lit * self.monitor_span_counts * self.lamp_emission[i])

    def read_words(self, table, address, count):
        self._tick()
        self._refresh_lamp_monitor()
        data = self.ir if table == "input_register" else self.hr
        if address + count > len(data):
            raise ModbusExceptionReply("read", 2)
        return list(data[address:address + count])

    def write_bits(self, address, values):
        self._tick()
        self.coils[address:address + len(values)] = [bool(v) for v in values]
        self._busy_left = self.busy_polls

    def write_words(self, address, values):
        self._tick()
        unlocked = self.unlocked  # an unlock in this same request serves only later ones
        for i, value in enumerate(values):
            self.hr[address + i] = value
        if address <= regs.BY_NAME["command"].address < address + len(values):
            cmd = regs.Command(self.hr[regs.BY_NAME["command"].address])
            if cmd in (regs.Command.SAVE_CONFIG, regs.Command.LOAD_DEFAULTS):
                if not unlocked:
                    raise ModbusExceptionReply(f"{cmd.name.lower()} without unlock", 1)
                self.unlocked = False
            self._on_command(cmd)
        cmd_reg = regs.BY_NAME["map_command"]
        if address <= cmd_reg.address < address + len(values):
            cmd = regs.MapCommand(self.hr[cmd_reg.address])
            destructive = cmd in (regs.MapCommand.BEGIN_WRITE, regs.MapCommand.ACTIVATE)
            if destructive and not unlocked:
                self._set("ir", regs.BY_NAME["map_op_status"], regs.MapOpStatus.ERROR_LOCKED)
            else:
                self.unlocked = self.unlocked and not destructive
                self._on_map_command(cmd)
        unlock = regs.BY_NAME["unlock"].address
        if address <= unlock < address + len(values):
            self.unlocked = self.hr[unlock] == regs.Unlock.KEY
            self.hr[unlock] = 0

    def _on_command(self, cmd):
        self.commands.append(cmd.name.lower())
        if cmd == regs.Command.HOME:
            self.inputs[regs.BY_NAME["homed"].address] = True
            self._busy_left = self.busy_polls
        elif cmd in (regs.Command.GOTO_BLACK, regs.Command.GOTO_WHITE, regs.Command.GOTO_OPEN):
            if not self.inputs[regs.BY_NAME["homed"].address]:
                raise ModbusExceptionReply("goto before home", 4)
            self._set("ir", regs.BY_NAME["position_slot"], int(cmd) - 1)
            self._busy_left = self.busy_polls

    def _on_map_command(self, cmd):
        status = regs.BY_NAME["map_op_status"]
        if cmd == regs.MapCommand.BEGIN_WRITE:
            self.write_target = regs.MapSlot.B if self.active == regs.MapSlot.A else regs.MapSlot.A
            self.write_length = self.get("map_expected_length")
            self.write_crc = self.get("map_expected_crc32")
            self.write_version = self.get("map_version")
            self.write_buffer = bytearray(self.write_length + self.write_length % 2)
            self.slots[self.write_target] = b""
            self.verified = None
            self._set("ir", regs.BY_NAME["map_op_bytes_written"], 0)
            self._set("ir", status, regs.MapOpStatus.WRITING)
        elif cmd == regs.MapCommand.VERIFY:
            data = bytes(self.write_buffer[:self.write_length])
            ok = zlib.crc32(data) == self.write_crc
            self.verified = data if ok else None
            self._set("ir", status, regs.MapOpStatus.VERIFY_OK if ok else regs.MapOpStatus.VERIFY_FAILED)
        elif cmd == regs.MapCommand.ACTIVATE:
            # like the firmware: a slot becomes valid (and readable) only when it is activated
            self.slots[self.write_target] = self.verified
            self.versions[self.write_target] = self.write_version
            self.write_buffer = None
            self.active = self.write_target
            self._set("ir", status, regs.MapOpStatus.ACTIVATED)
        elif cmd == regs.MapCommand.ABORT:
            self.write_buffer = None
            self._set("ir", status, regs.MapOpStatus.IDLE)
        self._refresh_map_registers()

    def write_file_records(self, file_number, record_number, data):
        self.file_writes += 1
        if self.fail_file_write_at is not None and self.file_writes == self.fail_file_write_at:
            from trimeter.errors import DeviceError

            raise DeviceError("link lost (injected)")
        if self.write_buffer is None:
            raise ModbusExceptionReply("file write", 1)
        offset = ((file_number - 1) * regs.MAP_RECORDS_PER_FILE + record_number) * 2
        if offset + len(data) > len(self.write_buffer):
            raise ModbusExceptionReply("file write", 2)
        self.write_buffer[offset:offset + len(data)] = data
        written = max(self.get("map_op_bytes_written"), offset + len(data))
        self._set("ir", regs.BY_NAME["map_op_bytes_written"], written)

    def read_file_records(self, file_number, record_number, count):
        slot = regs.MapSlot(self.hr[regs.BY_NAME["map_read_slot"].address]) or self.active
        data = self.slots.get(slot, b"")
        if not data:
            raise ModbusExceptionReply("file read of an invalid slot", 2)
        data = data + b"\0" * (len(data) % 2)
        offset = ((file_number - 1) * regs.MAP_RECORDS_PER_FILE + record_number) * 2
        if offset + 2 * count > len(data):
            raise ModbusExceptionReply("file read", 2)
        return data[offset:offset + 2 * count]

    def close(self):
        pass


class FakeOptics:
    """What the spectrometer sees, per set-up, for known per-bin I_b, I_w, I_c and background ρ's."""

    def __init__(self, wavelengths, *, diffuse, collimated, rho_black, rho_white, stray=0.0):
        self.wavelengths = np.asarray(wavelengths, float)
        self.diffuse = np.asarray(diffuse, float)          # E_d counts/s
        self.collimated = np.asarray(collimated, float)    # E_c counts/s
        self.rho_black = np.asarray(rho_black, float)
        self.rho_white = rho_white
        self.sample = None                                  # (I_b, I_w, I_c) arrays or None
        self.brightness = lambda device_time_s: 1.0         # lamp drift (warm-up tests)

    def rate(self, instrument: FakeInstrument) -> np.ndarray:
        panels = instrument.get("shutter_panel_left_open") and instrument.get("led_panel_left_on")
        coll = instrument.get("shutter_collimated_open") and instrument.get("led_collimated_on")
        slot = regs.Slot(instrument.get("position_slot"))
        out = np.zeros_like(self.wavelengths)
        if self.sample is None:
            if panels and slot == regs.Slot.BLACK:
                out += self.diffuse * self.rho_black
            elif panels and slot == regs.Slot.WHITE:
                out += self.diffuse * self.rho_white
            if coll and slot == regs.Slot.OPEN:
                out += self.collimated
        else:
            i_b, i_w, i_c = self.sample
            if panels:
                out += self.diffuse * (i_w if slot == regs.Slot.WHITE else i_b)
            if coll and slot == regs.Slot.OPEN:
                out += self.collimated * i_c
        return out * self.brightness(instrument.time_s)


class FakeSpectrometer:
    """Counts = dark offset + rate · t, clipped at saturation; no noise unless asked."""

    def __init__(self, instrument, optics, *, dark_offset=1000.0, saturation=65535.0, noise=0.0, seed=0,
                 limits=(100, 10_000_000)):
        self.instrument = instrument
        self.optics = optics
        self.dark_offset = dark_offset
        self._saturation = saturation
        self._limits = limits
        self._t = 10_000
        self.noise = noise
        self.quantize = False
        self.rng = np.random.default_rng(seed)
        self.exposures = []

    @property
    def description(self):
        wl = self.optics.wavelengths
        return SpectrometerDescription("fake", "0", len(wl), (float(wl[0]), float(wl[-1])), self._limits,
                                       self._saturation, ())

    def wavelengths_nm(self):
        return self.optics.wavelengths.copy()

    def intensities(self):
        self.exposures.append(self._t)
        counts = self.dark_offset + self.optics.rate(self.instrument) * self._t * 1e-6
        if self.noise:
            counts = counts + self.rng.normal(0, self.noise, counts.shape)
        if self.quantize:
            counts = np.floor(counts)
        return np.minimum(counts, self._saturation)

    @property
    def integration_time_us(self):
        return self._t

    @integration_time_us.setter
    def integration_time_us(self, value):
        self._t = int(min(max(value, self._limits[0]), self._limits[1]))

    @property
    def integration_time_us_limits(self):
        return self._limits

    @property
    def saturation_counts(self):
        return self._saturation

    @property
    def dark_pixels(self):
        return ()

    def close(self):
        pass
