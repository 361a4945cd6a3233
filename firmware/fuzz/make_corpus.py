#!/usr/bin/env python3
"""Write the fuzzers' seed corpora. corpus/ (fuzz_modbus): valid RTU frames of every function code against
the trimeter register map (slave 1 and broadcast), plus bad ones. corpus_app/ (fuzz_app): short programs
of its operations (fuzz_app.c, run_op). corpus_table_fit/ (fuzz_table_fit): edits of the device table and
bins. Run with the venv (`make -C firmware/fuzz corpus`)."""

from pathlib import Path
import struct
from trimeter.crc import crc16_modbus as crc16

HERE = Path(__file__).resolve().parent


def frame(*parts) -> bytes:
    body = b"".join(p if isinstance(p, bytes) else bytes([p]) for p in parts)
    return body + struct.pack("<H", crc16(body))


def u16(*values) -> bytes:
    return struct.pack(f">{len(values)}H", *values)


F32_80 = struct.pack(">f", 80.0)
SEEDS = {
    "fc01_read_coils": frame(1, 0x01, u16(0, 6)),
    "fc02_read_discrete": frame(1, 0x02, u16(0, 5)),
    "fc03_read_holding": frame(1, 0x03, u16(64, 28)),
    "fc04_read_input_identity": frame(1, 0x04, u16(0, 8)),
    "fc05_write_coil_on": frame(1, 0x05, u16(0, 0xFF00)),
    "fc06_write_register": frame(1, 0x06, u16(2, 500)),
    "fc0f_write_coils": frame(1, 0x0F, u16(0, 6), 1, 0x2A),
    "fc10_write_f32": frame(1, 0x10, u16(64, 2), 4, F32_80),
    "fc10_map_begin": frame(1, 0x10, u16(16, 7), 14, u16(0, 1000, 0x1234, 0x5678, 1, 0, 1)),
    "fc10_baud_allowed": frame(1, 0x10, u16(90, 2), 4, struct.pack(">I", 115200)),
    "fc10_half_wide": frame(1, 0x10, u16(65, 1), 2, u16(0)),
    "fc17_read_write": frame(1, 0x17, u16(0, 5, 2, 1), 2, u16(700)),
    "fc14_read_file": frame(1, 0x14, 14, 6, u16(1, 0, 4), 6, u16(2, 9990, 10)),
    "fc15_write_file": frame(1, 0x15, 13, 6, u16(1, 0, 3), u16(0x0102, 0x0304, 0x0506)),
    "fc2b_devid_basic": frame(1, 0x2B, 0x0E, 1, 0),
    "fc2b_devid_regular": frame(1, 0x2B, 0x0E, 2, 0),
    "fc2b_devid_individual": frame(1, 0x2B, 0x0E, 4, 2),
    "broadcast_write_register": frame(0, 0x06, u16(3, 1)),
    "broadcast_write_coils": frame(0, 0x0F, u16(0, 3), 1, 0x07),
    "broadcast_read_ignored": frame(0, 0x03, u16(0, 1)),
    "other_address": frame(7, 0x03, u16(0, 1)),
    "bad_unknown_fc": frame(1, 0x08, u16(0, 0x1234)),
    "bad_quantity": frame(1, 0x03, u16(0, 126)),
    "bad_coil_value": frame(1, 0x05, u16(0, 0x1234)),
    "bad_byte_count": frame(1, 0x10, u16(0, 2), 3, u16(1, 2)),
    "bad_file_ref": frame(1, 0x14, 7, 5, u16(1, 0, 1)),
    "bad_crc": frame(1, 0x03, u16(0, 1))[:-1] + b"\x00",
    "bad_truncated": frame(1, 0x03, u16(0, 1))[:5],
    "garbage": bytes(range(0x80, 0xC0)),
    "oversize": frame(1, 0x10, u16(0, 123), 246, bytes(246)) + bytes(40),
    "back_to_back": frame(1, 0x03, u16(0, 2)) + frame(1, 0x06, u16(2, 10)),
}


# fuzz_app programs: one byte picks the operation (run_op: value % 12), its arguments follow.
FRAME, WRITE_HOLDING, RAW, TIME, REBOOT, POWER_CUT, PLANT, UNLOCKED_COMMAND, UPLOAD = range(9)
SPECTRO = 11  # op_spectro: how (clock, no EOS, saturate, valid params, a coefficient, address), words...
FIT = 10  # op_fit: how (0x01 the table's thickness, 0x02 abort, 0x20 an offset, 0xC0/0x0C addresses), bins, words...
F32_04 = struct.pack(">f", 0.4)
F32_NAN = struct.pack(">f", float("nan"))
UNICAST, BROADCAST = 1, 0
UNLOCK_KEY = (0x5A, 0xFE)
SAVE, LOAD_DEFAULTS, HOME = 0x00, 0x01, 0x02
NO_UNLOCK, TWICE = 0x40, 0x20
SLOT_WHITE_70 = bytes([WRITE_HOLDING, UNICAST, 68, 1, 0x42, 0x8C, 0, 0])  # f32 70.0 = 0x428C0000
APP_SEEDS = {
    "upload_valid_table": bytes([UPLOAD, 0x0B, 1, 0, REBOOT]),
    # a table, then 3 bins (one NaN I_c) fitted with the table's thickness, 20 ms, results read back
    "fit_three_bins": bytes([UPLOAD, 0x0B, 1, 0, FIT, 0x45, 2]) + (F32_04 * 2 + F32_NAN + F32_04 * 2) * 3
    + bytes([20, 0, 20]),
    # a 500 kHz board, 2 frames at a valid time, then a read of the light file; one losing EOS; one saturating
    "spectro_capture": bytes([SPECTRO, 0x12, 0x08, 0x00]) + bytes([0, 1, 0, 2, 0, 0, 0x27, 0x10, 0, 1]) + bytes([60, 0, 0, 100]),
    "spectro_no_eos": bytes([SPECTRO, 0x16, 0x08, 0x00]) + bytes([0, 1, 0, 2, 0, 0, 0x27, 0x10, 0, 1]) + bytes([60, 0, 0, 10]),
    "spectro_saturated_bad_coeff": bytes([SPECTRO, 0x3A]) + bytes([0, 1, 0, 1, 0, 0, 0x03, 0xE8, 0, 0])
    + bytes([0xC0, 0x2C, 0, 0, 1, 40, 0, 0, 5]),
    "fit_without_table": bytes([FIT, 0x44, 0]) + F32_04 * 5 + bytes([5, 0, 7]),
    "upload_table_bad_magic": bytes([UPLOAD, 0x0B, 2, 1, 0x00, 0x05, 0x77]),
    "upload_junk_with_fixed_crc": bytes([UPLOAD, 0x08 | 0x02, 3, 2, 0x00, 0x48, 0x09, 0x00, 0x50, 0x01]),
    "upload_activate_without_unlock": bytes([UPLOAD, 0x1B, 4, 0]),
    "unlock_save_reboot": SLOT_WHITE_70 + bytes([UNLOCKED_COMMAND, SAVE, REBOOT]),
    "save_retry_then_save_again": SLOT_WHITE_70 + bytes([UNLOCKED_COMMAND, SAVE | TWICE, UNLOCKED_COMMAND, NO_UNLOCK]),
    "broadcast_unlock_then_save": bytes([WRITE_HOLDING, BROADCAST, 1, 1, *UNLOCK_KEY, UNLOCKED_COMMAND, NO_UNLOCK]),
    "save_flood": SLOT_WHITE_70 + bytes([UNLOCKED_COMMAND, SAVE] * 12) + bytes([TIME, 0xFF]),
    "power_cut_in_a_save": SLOT_WHITE_70 + bytes([POWER_CUT, 3, UNLOCKED_COMMAND, SAVE, REBOOT]),
    "home_and_wait": bytes([UNLOCKED_COMMAND, HOME, TIME, 0x7F, TIME, 0x7F, PLANT, 0x01, TIME, 0x20]),
    "raw_two_frames": bytes([RAW, 16]) + frame(1, 0x03, u16(0, 2)) + frame(1, 0x06, u16(2, 10)),
    "unlock_window_expires": bytes([WRITE_HOLDING, UNICAST, 1, 1, *UNLOCK_KEY, TIME, 0x83,
                                    UNLOCKED_COMMAND, NO_UNLOCK]),
}


def bins(*rows) -> bytes:
    """fuzz_table_fit's bins: (I_b, I_w, I_c, rho_b, rho_w) per row, float32 little-endian."""
    return b"".join(struct.pack("<5f", *row) for row in rows)


ORDINARY = ((0.10, 0.30, 0.05, 0.02, 0.95), (0.40, 0.70, 0.40, 0.02, 0.95), (0.02, 0.05, 0.001, 0.02, 0.95))
NAN = float("nan")
TABLE_FIT_SEEDS = {  # fuzz_table_fit: edit count (bit 4: cut the length), edits (u16 offset, byte), bins
    "ordinary_bins": bytes([0]) + bins(*ORDINARY),
    "special_bins": bytes([0]) + bins((NAN, 0.5, 0.1, 0.02, 0.95), (0.1, 0.5, 0.0, 0.5, 0.2), (-1, 2, 1e30, 0, 1)),
    "n_alpha_edited": bytes([1]) + struct.pack("<HB", 116, 3) + bins(ORDINARY[0]),
    "scale_edited": bytes([2]) + struct.pack("<HBHB", 307, 0x7F, 315, 0xFF) + bins(*ORDINARY),
    "length_cut": bytes([0x10, 9]) + bins(ORDINARY[1]),
}


def main() -> None:
    for directory, seeds in (("corpus", SEEDS), ("corpus_app", APP_SEEDS), ("corpus_table_fit", TABLE_FIT_SEEDS)):
        out = HERE / directory
        out.mkdir(exist_ok=True)
        for name, data in seeds.items():
            (out / name).write_bytes(data)
        print(f"wrote {len(seeds)} seeds to {out}")


if __name__ == "__main__":
    main()
