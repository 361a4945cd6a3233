/* A Modbus application and an in-memory line for the Modbus tests and the fuzzer: a register bank
 * plus a file store that behave like the real app (ranges, refusals, exceptions of every kind), so
 * that every path of the slave is reachable. Header-only (static), included by one .c each. */
#ifndef TRIMETER_MB_TEST_APP_H
#define TRIMETER_MB_TEST_APP_H

#include <string.h>

#include "../core/modbus.h"

#define TB_BITS 64u
#define TB_REGS 256u
#define TB_FILES 3u                  /* files 1..3 exist */
#define TB_BAD_VALUE 0xDEADu         /* holding value the app refuses with 03 */
#define TB_FAILING_REG 200u          /* holding address whose write fails with 04 */

typedef struct {
    uint8_t coils[TB_BITS], discrete[TB_BITS];
    uint16_t input[TB_REGS], holding[TB_REGS];
    uint16_t files[TB_FILES][MB_FILE_RECORD_MAX + 1];
    unsigned writes; /* successful write callbacks */
} tb_bank_t;

static void tb_get_bits(const uint8_t *src, uint16_t addr, uint16_t n, uint8_t *out) {
    for (uint16_t i = 0; i < n; i++)
        if (src[addr + i]) out[i / 8] = (uint8_t)(out[i / 8] | (1u << (i % 8)));
}

static uint8_t tb_read_bits(void *ctx, mb_table_t t, uint16_t addr, uint16_t n, uint8_t *out) {
    tb_bank_t *b = ctx;
    if ((uint32_t)addr + n > TB_BITS) return MB_EX_ILLEGAL_DATA_ADDRESS;
    tb_get_bits(t == MB_TABLE_COILS ? b->coils : b->discrete, addr, n, out);
    return MB_OK;
}

static uint8_t tb_write_bits(void *ctx, uint16_t addr, uint16_t n, const uint8_t *bits) {
    tb_bank_t *b = ctx;
    if ((uint32_t)addr + n > TB_BITS) return MB_EX_ILLEGAL_DATA_ADDRESS;
    for (uint16_t i = 0; i < n; i++) b->coils[addr + i] = (uint8_t)((bits[i / 8] >> (i % 8)) & 1u);
    b->writes++;
    return MB_OK;
}

static uint8_t tb_read_regs(void *ctx, mb_table_t t, uint16_t addr, uint16_t n, uint16_t *out) {
    tb_bank_t *b = ctx;
    if ((uint32_t)addr + n > TB_REGS) return MB_EX_ILLEGAL_DATA_ADDRESS;
    memcpy(out, (t == MB_TABLE_HOLDING_REGISTERS ? b->holding : b->input) + addr, n * sizeof *out);
    return MB_OK;
}

static uint8_t tb_write_regs(void *ctx, uint16_t addr, uint16_t n, const uint16_t *vals) {
    tb_bank_t *b = ctx;
    if ((uint32_t)addr + n > TB_REGS) return MB_EX_ILLEGAL_DATA_ADDRESS;
    for (uint16_t i = 0; i < n; i++) {
        if (vals[i] == TB_BAD_VALUE) return MB_EX_ILLEGAL_DATA_VALUE;
        if (addr + i == TB_FAILING_REG) return MB_EX_SERVER_DEVICE_FAILURE;
    }
    memcpy(b->holding + addr, vals, n * sizeof *vals);
    b->writes++;
    return MB_OK;
}

static uint8_t tb_read_file(void *ctx, uint16_t file, uint16_t record, uint16_t n, uint16_t *out) {
    tb_bank_t *b = ctx;
    if (file < 1u || file > TB_FILES || (uint32_t)record + n > MB_FILE_RECORD_MAX + 1u)
        return MB_EX_ILLEGAL_DATA_ADDRESS;
    memcpy(out, &b->files[file - 1][record], n * sizeof *out);
    return MB_OK;
}

static uint8_t tb_write_file(void *ctx, uint16_t file, uint16_t record, uint16_t n,
                             const uint16_t *vals) {
    tb_bank_t *b = ctx;
    if (file == TB_FILES) return MB_EX_ILLEGAL_FUNCTION; /* read-only file: "wrong state" */
    if (file < 1u || file > TB_FILES || (uint32_t)record + n > MB_FILE_RECORD_MAX + 1u)
        return MB_EX_ILLEGAL_DATA_ADDRESS;
    memcpy(&b->files[file - 1][record], vals, n * sizeof *vals);
    b->writes++;
    return MB_OK;
}

static void tb_app_init(mb_app_t *app, tb_bank_t *bank) {
    memset(app, 0, sizeof *app);
    app->read_bits = tb_read_bits;
    app->write_bits = tb_write_bits;
    app->read_regs = tb_read_regs;
    app->write_regs = tb_write_regs;
    app->read_file = tb_read_file;
    app->write_file = tb_write_file;
    app->vendor = "trimeter project";
    app->product = "TRIMETER-1";
    app->revision = "0.1.0";
    app->vendor_url = "https://example.org/trimeter";
    app->product_name = "trimeter test bank";
    app->ctx = bank;
}

/* An in-memory line: bytes the master sent (consumed by the slave's read), bytes the slave wrote,
 * and a clock the test moves by hand. `chunk` limits one read, to imitate a UART FIFO. */
typedef struct {
    uint8_t in[1024];
    size_t in_len, in_pos;
    uint8_t out[4096];
    size_t out_len;
    unsigned writes;
    uint32_t now_us;
    size_t chunk;
} tb_line_t;

static size_t tb_line_read(void *ctx, uint8_t *buf, size_t max) {
    tb_line_t *l = ctx;
    size_t n = l->in_len - l->in_pos;
    if (n > max) n = max;
    if (l->chunk && n > l->chunk) n = l->chunk;
    memcpy(buf, l->in + l->in_pos, n);
    l->in_pos += n;
    if (l->in_pos == l->in_len) l->in_pos = l->in_len = 0;
    return n;
}

static void tb_line_write(void *ctx, const uint8_t *buf, size_t n) {
    tb_line_t *l = ctx;
    if (n > sizeof l->out - l->out_len) n = sizeof l->out - l->out_len;
    memcpy(l->out + l->out_len, buf, n);
    l->out_len += n;
    l->writes++;
}

static uint32_t tb_line_now(void *ctx) { return ((tb_line_t *)ctx)->now_us; }

static void tb_line_push(tb_line_t *l, const uint8_t *bytes, size_t n) {
    if (n > sizeof l->in - l->in_len) n = sizeof l->in - l->in_len;
    memcpy(l->in + l->in_len, bytes, n);
    l->in_len += n;
}

static void tb_io_init(mb_io_t *io, tb_line_t *line) {
    io->read = tb_line_read;
    io->write = tb_line_write;
    io->now_us = tb_line_now;
    io->ctx = line;
}

#endif
