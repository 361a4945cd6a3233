/* libFuzzer target over the Modbus RTU slave: the framer (mb_poll over a chunked byte stream with
 * t3.5 gaps) and the dispatcher (every input also handled as one ADU with its CRC fixed up, so
 * mutations reach the function-code handlers instead of dying at the CRC check).
 *
 * The application is the register bank + file store of tests/mb_test_app.h, with the real
 * register-map rules (regmap.c) in front of holding-register reads/writes, so every exception path
 * of both layers is reachable. Invariants (abort = a finding), besides the sanitizers':
 *   - every reply, in every pass, is one whole frame per write: 4..256 bytes, good CRC, our
 *     address; an exception reply is exactly 5 bytes with code 01..04;
 *   - a single ADU gets at most one reply, echoing its function code (| 0x80 for an exception);
 *   - no reply at all to a broadcast.
 */
#include <stdlib.h>

#include "../core/crc.h"
#include "../core/modbus.h"
#include "../core/regmap.h"
#include "../tests/mb_test_app.h"

#define SLAVE_ADDRESS 1u

static tb_bank_t bank;
static tb_line_t line;
static mb_io_t io;
static mb_app_t app;
static mb_slave_t slave;

static uint8_t fz_read_regs(void *ctx, mb_table_t t, uint16_t addr, uint16_t n, uint16_t *out) {
    uint8_t ex = regmap_check_read((regmap_table_t)t, addr, n);
    return ex ? ex : tb_read_regs(ctx, t, addr, n, out);
}

static uint8_t fz_write_regs(void *ctx, uint16_t addr, uint16_t n, const uint16_t *vals) {
    uint8_t ex = regmap_check_write_regs(addr, n, vals);
    return ex ? ex : tb_write_regs(ctx, addr, n, vals);
}

static uint8_t fz_write_bits(void *ctx, uint16_t addr, uint16_t n, const uint8_t *bits) {
    /* Half of the coil space goes through the map's rules, the rest straight to the bank. */
    if (addr < 32u) {
        uint8_t ex = regmap_check_write_bits(addr, n);
        if (ex) return ex;
    }
    return tb_write_bits(ctx, addr, n, bits);
}

/* Every reply the slave writes, checked as it is written. */
static void fz_write(void *ctx, const uint8_t *buf, size_t n) {
    if (n < 4 || n > MB_ADU_MAX || crc16_modbus(buf, n) != 0 || buf[0] != SLAVE_ADDRESS) abort();
    if ((buf[1] & 0x80u) && (n != 5 || buf[2] < 1u || buf[2] > 4u)) abort();
    tb_line_write(ctx, buf, n);
}

/* The invariants on the reply to one ADU handed to mb_handle_adu. */
static void check_reply(const uint8_t *request) {
    if (request[0] == MB_ADDRESS_BROADCAST) {
        if (line.writes) abort(); /* a broadcast is never answered */
        return;
    }
    if (line.writes == 0) return;
    if (line.writes != 1) abort();
    uint8_t expect_fc = (line.out_len == 5 && (line.out[1] & 0x80u)) ? (uint8_t)(request[1] | 0x80u)
                                                                    : request[1];
    if (line.out[1] != expect_fc) abort();
}

static void reset(void) {
    memset(&line, 0, sizeof line);
    /* The bank persists across inputs (clearing 60 KB per run would halve the speed); its contents
     * are only copied, never branched on, so a finding replays the same from a fresh process. */
    tb_app_init(&app, &bank);
    app.read_regs = fz_read_regs;
    app.write_regs = fz_write_regs;
    app.write_bits = fz_write_bits;
    tb_io_init(&io, &line);
    io.write = fz_write;
    mb_init(&slave, SLAVE_ADDRESS, 19200, &io, &app);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    uint8_t frame[MB_ADU_MAX + 2];
    reset();

    /* 1. Dispatcher: the input with its last two bytes replaced by the right CRC. */
    if (size >= 4 && size <= MB_ADU_MAX) {
        size_t n = size - 2;
        memcpy(frame, data, n);
        uint16_t crc = crc16_modbus(frame, n);
        frame[n] = (uint8_t)crc;
        frame[n + 1] = (uint8_t)(crc >> 8);
        mb_handle_adu(&slave, frame, size);
        check_reply(frame);
    }

    /* 2. Framer: the raw bytes as a stream, in chunks whose size the first byte picks, with gaps
     *    below t3.5 between chunks; then silence. */
    line.out_len = 0;
    line.writes = 0;
    size_t chunk = size ? 1u + data[0] % 37u : 1u;
    for (size_t off = 0; off < size; off += chunk) {
        size_t n = size - off < chunk ? size - off : chunk;
        tb_line_push(&line, data + off, n);
        mb_poll(&slave);
        line.now_us += 300u + (data[off] & 0x3Fu) * 40u; /* 300..2820 us: some gaps exceed t3.5 */
        mb_poll(&slave);
    }
    line.now_us += slave.t35_us;
    mb_poll(&slave);
    mb_poll(&slave);

    /* 3. Back-to-back: the fixed-up frame twice in one read (the splitter's path). */
    if (size >= 4 && size <= MB_ADU_MAX / 2) {
        line.out_len = 0;
        line.writes = 0;
        tb_line_push(&line, frame, size);
        tb_line_push(&line, frame, size);
        mb_poll(&slave);
        line.now_us += slave.t35_us;
        mb_poll(&slave);
    }
    return 0;
}
