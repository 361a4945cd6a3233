"""The instrument's table read into the cache: a read the link cuts short is resumed by the next try from the
bytes it kept, not started over, and what is kept can never make a wrong table."""

from __future__ import annotations

import os

import pytest

from trimeter.device.table_cache import PARTIAL_SUFFIX, instrument_table
from trimeter.device.transport import LinkError
from trimeter.errors import MapFileError
from trimeter.formats.device_table import SUFFIX, DeviceTable
from trimeter.paths import MAPS_DIR
from trimeter.registers import MapSlot

TABLE = (MAPS_DIR / "device-n1.5-l0.4.tlut").read_bytes()


class FlakySlotDevice:
    """A device whose slot A holds `table`; each whole-table read delivers `per_read` more bytes, in records
    handed to `on_data`, and then loses the link (as a read whose time budget ran out does)."""

    def __init__(self, table: bytes, per_read: int) -> None:
        self.table, self.per_read = table, per_read
        self.offsets: list[int] = []   # where each long read started

    def map_status(self) -> dict:
        return {"map_active_slot": MapSlot.A, "map_slot_a_length": len(self.table)}

    def read_map(self, slot, length, *, offset=0, on_data=None, **_):
        assert slot == MapSlot.A and offset % 2 == 0
        if length <= 256:  # the header and trailing CRC-32 that find a table in the cache
            return self.table[offset:offset + length]
        self.offsets.append(offset)
        end = min(offset + length, offset + self.per_read)
        for at in range(offset, end, 240):
            chunk = self.table[at:min(at + 240, end)]
            if on_data:
                on_data(chunk)
        if end < offset + length:
            raise LinkError("no valid reply from the device to a file-record read (the read's budget ran out)")
        return self.table[offset:offset + length]


def test_a_read_the_link_cut_short_goes_on_where_it_stopped(tmp_path):
    device = FlakySlotDevice(TABLE, per_read=48_000)
    for _ in range(2):
        with pytest.raises(LinkError):
            instrument_table(device, tmp_path)
    table, slot, cached = instrument_table(device, tmp_path)
    assert device.offsets == [0, 48_000, 96_000]   # each try went on from the last, none started over
    assert (table.sha256, slot, cached) == (DeviceTable.from_bytes(TABLE).sha256, "A", False)
    assert not list(tmp_path.glob("*" + PARTIAL_SUFFIX))   # whole: what was kept is gone, the table cached
    assert instrument_table(device, tmp_path)[2] is True


def test_what_is_kept_cannot_make_a_wrong_table(tmp_path):
    device = FlakySlotDevice(TABLE, per_read=50_000)
    with pytest.raises(LinkError):
        instrument_table(device, tmp_path)
    (partial,) = tmp_path.glob("*" + PARTIAL_SUFFIX)
    assert partial.read_bytes() == TABLE[:50_000]
    damaged = bytearray(partial.read_bytes())
    damaged[1000] ^= 0xFF
    partial.write_bytes(bytes(damaged))
    device.per_read = len(TABLE)
    with pytest.raises(MapFileError, match="flash a current table"):   # the whole table's CRC-32 says so
        instrument_table(device, tmp_path)
    assert not partial.exists()   # not resumed again: the next read starts afresh, and is right
    device.offsets.clear()
    assert instrument_table(device, tmp_path)[0].sha256 == DeviceTable.from_bytes(TABLE).sha256
    assert device.offsets == [0]


def test_bytes_kept_for_another_table_or_behind_a_link_are_not_used(tmp_path):
    other = bytearray(TABLE)
    other[-1] ^= 0x01   # another trailing CRC-32: another table, by what identifies it before it is whole
    with pytest.raises(LinkError):
        instrument_table(FlakySlotDevice(bytes(other), per_read=60_000), tmp_path)
    device = FlakySlotDevice(TABLE, per_read=len(TABLE))
    assert instrument_table(device, tmp_path)[0].sha256 == DeviceTable.from_bytes(TABLE).sha256
    assert device.offsets == [0]

    # a link in place of the kept bytes is neither read nor written through
    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_bytes(TABLE[:60_000])
    cache = tmp_path / "cache"
    with pytest.raises(LinkError):
        instrument_table(FlakySlotDevice(TABLE, per_read=2_000), cache)
    (partial,) = cache.glob("*" + PARTIAL_SUFFIX)
    partial.unlink()
    os.symlink(elsewhere, partial)
    device = FlakySlotDevice(TABLE, per_read=len(TABLE))
    assert instrument_table(device, cache)[0].sha256 == DeviceTable.from_bytes(TABLE).sha256
    assert device.offsets == [0] and elsewhere.read_bytes() == TABLE[:60_000]


@pytest.mark.skipif(os.name != "posix", reason="the lock is POSIX's flock")
def test_a_second_reader_of_the_same_table_neither_resumes_nor_damages_the_first_ones_bytes(tmp_path):
    """Two processes reading the same table at once (two instruments with the same map): the one that holds
    the kept bytes goes on with them, the other reads its own from the start and leaves them alone."""
    import fcntl

    with pytest.raises(LinkError):
        instrument_table(FlakySlotDevice(TABLE, per_read=48_000), tmp_path)
    (partial,) = tmp_path.glob("*" + PARTIAL_SUFFIX)
    with open(partial, "rb") as held:  # the first reader, still reading
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(LinkError):  # cut short: nothing of it kept
            instrument_table(FlakySlotDevice(TABLE, per_read=10_000), tmp_path)
        second = FlakySlotDevice(TABLE, per_read=len(TABLE))
        assert instrument_table(second, tmp_path)[0].sha256 == DeviceTable.from_bytes(TABLE).sha256
        assert second.offsets == [0] and partial.read_bytes() == TABLE[:48_000]  # read alone, the kept bytes left
    for cached in tmp_path.glob("*" + SUFFIX):  # so that the first reader's next try reads the slot again
        cached.unlink()
    device = FlakySlotDevice(TABLE, per_read=len(TABLE))
    assert instrument_table(device, tmp_path)[0].sha256 == DeviceTable.from_bytes(TABLE).sha256
    assert device.offsets == [48_000] and not partial.exists()
