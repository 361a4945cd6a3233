"""A fake smbus2 bus with an AS7341 on it, emulated at register level (datasheet DS000504).

Independent of the driver: it knows the chip's photodiode layout (which SMUX RAM nibble is which
photodiode half), decodes whatever SMUX bytes are written, integrates light for
(ATIME+1)·(ASTEP+1)·2.78 µs of the injected fake clock, and clips at min(65535, (ATIME+1)(ASTEP+1)).
"""

from __future__ import annotations

import errno

# SMUX RAM nibble → photodiode half: (register, high nibble?) → name. The chip has two halves per
# filter (left/right of the array centre), two Clear halves, one NIR; other nibbles serve flicker/dark
# diodes not modelled (they read as no light).
PIXEL_LAYOUT = {
    (0x01, False): "F1", (0x10, False): "F1",
    (0x05, False): "F2", (0x0C, True): "F2",
    (0x00, True): "F3", (0x0F, True): "F3",
    (0x05, True): "F4", (0x0D, False): "F4",
    (0x06, True): "F5", (0x09, True): "F5",
    (0x04, False): "F6", (0x0E, True): "F6",
    (0x07, False): "F7", (0x0A, False): "F7",
    (0x03, True): "F8", (0x0E, False): "F8",
    (0x08, True): "Clear", (0x11, True): "Clear",
    (0x13, False): "NIR",
}
HALVES = {name: sum(1 for n in PIXEL_LAYOUT.values() if n == name) for name in set(PIXEL_LAYOUT.values())}


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += max(dt, 1e-6)


class FakeAS7341Bus:
    """smbus2.SMBus look-alike: read/write_byte_data, read/write_i2c_block_data, close."""

    def __init__(self, clock: FakeClock, flux_counts_per_ms: dict[str, float], address: int = 0x39,
                 chip_id: int = 0x24, stuck: bool = False, smux_reads_busy: int = 2):
        self.clock, self.flux, self.address, self.stuck = clock, dict(flux_counts_per_ms), address, stuck
        self.regs = bytearray(256)
        self.regs[0x92] = chip_id
        self.regs[0x81] = 0x00
        self.regs[0xCA], self.regs[0xCB] = 0xE7, 0x03  # ASTEP reset value 999
        self.regs[0xAA] = 0x09                         # AGAIN reset value 256x
        self.smux_ram = bytearray(20)
        self.smux_active = bytearray(20)
        self._smux_busy = 0
        self._smux_reads_busy = smux_reads_busy
        self._start: float | None = None
        self.latched = [0] * 6
        self.errors: list[str] = []
        self.closed = False

    # ------------------------------------------------------------------------------ chip model
    def _t_int_s(self) -> float:
        astep = self.regs[0xCA] | self.regs[0xCB] << 8
        return (self.regs[0x81] + 1) * (astep + 1) * 2.78e-6

    def _full_scale(self) -> int:
        astep = self.regs[0xCA] | self.regs[0xCB] << 8
        return min(65535, (self.regs[0x81] + 1) * (astep + 1))

    def gain(self) -> float:
        return (0.5, 1, 2, 4, 8, 16, 32, 64, 128, 256, 512)[min(self.regs[0xAA] & 0x1F, 10)]

    def _valid(self) -> bool:
        return (not self.stuck and self._start is not None and self.regs[0x80] & 0x02
                and self.clock.now() >= self._start + self._t_int_s())

    def _adc_values(self) -> tuple[list[int], bool]:
        ideal = [0.0] * 6
        for (reg, high), name in PIXEL_LAYOUT.items():
            selector = (self.smux_active[reg] >> 4) if high else (self.smux_active[reg] & 0x0F)
            if 1 <= selector <= 6:
                ideal[selector - 1] += self.flux.get(name, 0.0) / HALVES[name]
        scale = self._t_int_s() * 1e3 * self.gain()
        full = self._full_scale()
        values = [min(full, int(round(v * scale))) for v in ideal]
        return values, any(v * scale >= full for v in ideal)

    def _write(self, reg: int, value: int) -> None:
        if reg < 0x14:
            self.smux_ram[reg] = value
            return
        if reg == 0x80:
            was_measuring = self.regs[0x80] & 0x02
            if value & 0x10:
                if value & 0x02 or was_measuring:
                    self.errors.append("SMUX enabled while a spectral measurement runs")
                if (self.regs[0xAF] >> 3) & 0x3 != 2:
                    self.errors.append("SMUXEN without SMUX_CMD=write")
                self.smux_active[:] = self.smux_ram
                self._smux_busy = self._smux_reads_busy
            if value & 0x02 and not was_measuring:
                self._start = self.clock.now()
            if not value & 0x02:
                self._start = None
            if value & 0x02 and not value & 0x01:
                self.errors.append("SP_EN without PON")
        if reg == 0x92:
            return  # read-only
        self.regs[reg] = value

    def _read(self, reg: int) -> int:
        if reg == 0x80:
            if self._smux_busy:
                self._smux_busy -= 1
                return self.regs[0x80] | 0x10
            return self.regs[0x80] & ~0x10 & 0xFF
        if reg == 0xA3:
            return 0x40 if self._valid() else 0x00
        if reg == 0x94:
            values, saturated = self._adc_values() if self._valid() else ([0] * 6, False)
            self.latched = values
            return 0x80 if saturated else 0x00
        if 0x95 <= reg <= 0xA0:
            i = (reg - 0x95) // 2
            return (self.latched[i] >> 8) if (reg - 0x95) % 2 else (self.latched[i] & 0xFF)
        return self.regs[reg]

    # ----------------------------------------------------------------------------- smbus2 API
    def _check(self, address: int) -> None:
        if self.closed:
            raise OSError(errno.EBADF, "bus closed")
        if address != self.address:
            raise OSError(errno.EREMOTEIO, "Remote I/O error")  # no ACK at that address

    def read_byte_data(self, address, reg):
        self._check(address)
        return self._read(reg)

    def write_byte_data(self, address, reg, value):
        self._check(address)
        self._write(reg, value)

    def read_i2c_block_data(self, address, reg, length):
        self._check(address)
        return [self._read(reg + i) for i in range(length)]  # auto-increment

    def write_i2c_block_data(self, address, reg, data):
        self._check(address)
        for i, value in enumerate(data):
            self._write(reg + i, value)

    def close(self):
        self.closed = True
