/* The Modbus RTU slave over an in-memory line with a hand-moved clock: every function code, its
 * exceptions, broadcast, addressing and the framer (split frames, back-to-back frames, garbage,
 * bad CRC, t3.5 gaps, overruns). The app is the register bank + file store of mb_test_app.h. */
#include "../core/crc.h"
#include "../core/modbus.h"
#include "check.h"
#include "mb_test_app.h"

static tb_bank_t bank;
static tb_line_t line;
static mb_io_t io;
static mb_app_t app;
static mb_slave_t slave;

static void setup(uint8_t address, uint32_t baud) {
    memset(&bank, 0, sizeof bank);
    memset(&line, 0, sizeof line);
    tb_app_init(&app, &bank);
    tb_io_init(&io, &line);
    mb_init(&slave, address, baud, &io, &app);
}

static size_t with_crc(uint8_t *out, const uint8_t *adu, size_t n) {
    memcpy(out, adu, n);
    uint16_t crc = crc16_modbus(adu, n);
    out[n] = (uint8_t)crc;
    out[n + 1] = (uint8_t)(crc >> 8);
    return n + 2;
}

static void silence(void) {
    line.now_us += slave.t35_us;
    mb_poll(&slave);
}

/* Send address+PDU (CRC appended), let the line go silent, return the reply without its CRC. */
static size_t transact(const uint8_t *adu, size_t n, uint8_t *reply) {
    uint8_t buf[300];
    size_t len = with_crc(buf, adu, n);
    line.out_len = 0;
    tb_line_push(&line, buf, len);
    mb_poll(&slave);
    silence();
    if (line.out_len == 0) return 0;
    CHECK(line.out_len >= 4);
    CHECK_EQ_INT(crc16_modbus(line.out, line.out_len), 0);
    memcpy(reply, line.out, line.out_len - 2);
    return line.out_len - 2;
}

#define BYTES(...) (const uint8_t[]){__VA_ARGS__}, sizeof((const uint8_t[]){__VA_ARGS__})
#define TRANSACT(reply, ...) transact(BYTES(__VA_ARGS__), reply)
#define CHECK_BYTES(buf, ...)                                                                \
    CHECK_MEM(buf, ((const uint8_t[]){__VA_ARGS__}), sizeof((const uint8_t[]){__VA_ARGS__}))

static void check_exception(const uint8_t *reply, size_t len, uint8_t fc, uint8_t code) {
    CHECK_EQ_INT(len, 3);
    CHECK_EQ_INT(reply[0], 1);
    CHECK_EQ_INT(reply[1], fc | 0x80);
    CHECK_EQ_INT(reply[2], code);
}

/* ------------------------------------------------------------------------- function codes */

static void test_fc03_fc04_read_registers(void) {
    setup(1, 19200);
    uint8_t r[260];
    bank.holding[10] = 0x1234;
    bank.holding[11] = 0xABCD;
    bank.input[0] = 0x5452;
    size_t n = TRANSACT(r, 1, 0x03, 0x00, 10, 0x00, 2);
    CHECK_EQ_INT(n, 7);
    CHECK_BYTES(r, 1, 0x03, 4, 0x12, 0x34, 0xAB, 0xCD);
    n = TRANSACT(r, 1, 0x04, 0x00, 0, 0x00, 1);
    CHECK_BYTES(r, 1, 0x04, 2, 0x54, 0x52);
    CHECK_EQ_INT(n, 5);
    /* 125 is the limit, 126 and 0 are exception 03; past 65535 is 02; the app's map: 02. */
    n = TRANSACT(r, 1, 0x03, 0x00, 0, 0x00, 125);
    CHECK_EQ_INT(n, 3 + 250);
    n = TRANSACT(r, 1, 0x03, 0x00, 0, 0x00, 126);
    check_exception(r, n, 0x03, 3);
    n = TRANSACT(r, 1, 0x04, 0x00, 0, 0x00, 0);
    check_exception(r, n, 0x04, 3);
    n = TRANSACT(r, 1, 0x03, 0xFF, 0xFF, 0x00, 2);
    check_exception(r, n, 0x03, 2);
    n = TRANSACT(r, 1, 0x03, 0x01, 0x00, 0x00, 1); /* address 256: outside the bank */
    check_exception(r, n, 0x03, 2);
    n = TRANSACT(r, 1, 0x03, 0x00, 0x00, 0x00); /* PDU one byte short */
    check_exception(r, n, 0x03, 3);
    CHECK_EQ_INT(mb_counters(&slave)->exceptions, 5);
}

/* An app that fills whole bytes: the slave must still send the unused high bits as zero. */
static uint8_t sloppy_read_bits(void *ctx, mb_table_t t, uint16_t addr, uint16_t n, uint8_t *out) {
    (void)ctx, (void)t, (void)addr;
    memset(out, 0xFF, (n + 7u) / 8u);
    return MB_OK;
}

static void test_fc01_fc02_read_bits(void) {
    setup(1, 19200);
    uint8_t r[260];
    /* Spec example shape: 10 coils from 3, packed LSB first, unused high bits zero. */
    const uint8_t pattern[10] = {1, 0, 1, 1, 0, 0, 1, 1, 1, 1};
    memcpy(bank.coils + 3, pattern, 10);
    bank.coils[13] = 1; /* just past the request: must not leak into the padding */
    size_t n = TRANSACT(r, 1, 0x01, 0x00, 3, 0x00, 10);
    CHECK_EQ_INT(n, 5);
    CHECK_BYTES(r, 1, 0x01, 2, 0xCD, 0x03);
    bank.discrete[0] = 1;
    bank.discrete[8] = 1;
    n = TRANSACT(r, 1, 0x02, 0x00, 0, 0x00, 9);
    CHECK_BYTES(r, 1, 0x02, 2, 0x01, 0x01);
    n = TRANSACT(r, 1, 0x01, 0x00, 0, 0x07, 0xD1); /* 2001 */
    check_exception(r, n, 0x01, 3);
    n = TRANSACT(r, 1, 0x02, 0x00, 60, 0x00, 5); /* runs past the bank */
    check_exception(r, n, 0x02, 2);
    app.read_bits = sloppy_read_bits;
    n = TRANSACT(r, 1, 0x01, 0x00, 0, 0x00, 11);
    CHECK_BYTES(r, 1, 0x01, 2, 0xFF, 0x07);
}

static void test_fc05_write_single_coil(void) {
    setup(1, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 1, 0x05, 0x00, 7, 0xFF, 0x00);
    CHECK_EQ_INT(n, 6);
    CHECK_BYTES(r, 1, 0x05, 0x00, 7, 0xFF, 0x00);
    CHECK_EQ_INT(bank.coils[7], 1);
    n = TRANSACT(r, 1, 0x05, 0x00, 7, 0x00, 0x00);
    CHECK_EQ_INT(bank.coils[7], 0);
    n = TRANSACT(r, 1, 0x05, 0x00, 7, 0x12, 0x34);
    check_exception(r, n, 0x05, 3);
    n = TRANSACT(r, 1, 0x05, 0x00, 99, 0xFF, 0x00);
    check_exception(r, n, 0x05, 2);
}

static void test_fc06_write_single_register(void) {
    setup(1, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 1, 0x06, 0x00, 4, 0xBE, 0xEF);
    CHECK_EQ_INT(n, 6);
    CHECK_BYTES(r, 1, 0x06, 0x00, 4, 0xBE, 0xEF);
    CHECK_EQ_INT(bank.holding[4], 0xBEEF);
    n = TRANSACT(r, 1, 0x06, 0x00, 4, 0xDE, 0xAD); /* the app refuses the value */
    check_exception(r, n, 0x06, 3);
    CHECK_EQ_INT(bank.holding[4], 0xBEEF);
    n = TRANSACT(r, 1, 0x06, 0x00, TB_FAILING_REG, 0x00, 1);
    check_exception(r, n, 0x06, 4);
}

static void test_fc0f_write_multiple_coils(void) {
    setup(1, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 1, 0x0F, 0x00, 20, 0x00, 10, 2, 0xCD, 0x01);
    CHECK_EQ_INT(n, 6);
    CHECK_BYTES(r, 1, 0x0F, 0x00, 20, 0x00, 10);
    const uint8_t expect[10] = {1, 0, 1, 1, 0, 0, 1, 1, 1, 0};
    CHECK_MEM(bank.coils + 20, expect, 10);
    n = TRANSACT(r, 1, 0x0F, 0x00, 20, 0x00, 10, 1, 0xCD); /* byte count should be 2 */
    check_exception(r, n, 0x0F, 3);
    n = TRANSACT(r, 1, 0x0F, 0x00, 20, 0x00, 10, 2, 0xCD); /* data shorter than byte count */
    check_exception(r, n, 0x0F, 3);
    n = TRANSACT(r, 1, 0x0F, 0x00, 0, 0x07, 0xB1, 0xF7); /* 1969 coils: over the limit */
    check_exception(r, n, 0x0F, 3);
}

static void test_fc10_write_multiple_registers(void) {
    setup(1, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 1, 0x10, 0x00, 30, 0x00, 2, 4, 0x11, 0x22, 0x33, 0x44);
    CHECK_EQ_INT(n, 6);
    CHECK_BYTES(r, 1, 0x10, 0x00, 30, 0x00, 2);
    CHECK_EQ_INT(bank.holding[30], 0x1122);
    CHECK_EQ_INT(bank.holding[31], 0x3344);
    n = TRANSACT(r, 1, 0x10, 0x00, 30, 0x00, 2, 3, 0x11, 0x22, 0x33);
    check_exception(r, n, 0x10, 3);
    n = TRANSACT(r, 1, 0x10, 0xFF, 0xFF, 0x00, 2, 4, 0, 1, 0, 2);
    check_exception(r, n, 0x10, 2);
    /* 124 registers: over the FC 0x10 limit of 123 even though it would fit 253 bytes? No: 124*2
     * = 248 + 6 > 253 - so the count alone decides. */
    uint8_t big[7 + 248];
    const uint8_t head[] = {1, 0x10, 0x00, 0, 0x00, 124, 248};
    memcpy(big, head, sizeof head);
    memset(big + 7, 0, 248);
    n = transact(big, sizeof big, r);
    CHECK_EQ_INT(n, 0); /* 255 + 2 bytes > 256: an overrun on the wire, never answered */
    big[5] = 123;
    big[6] = 246;
    n = transact(big, 7 + 246, r);
    CHECK_EQ_INT(n, 6);
}

static void test_fc17_read_write_multiple(void) {
    setup(1, 19200);
    uint8_t r[260];
    bank.holding[5] = 0x0505;
    /* Write 6..7, read 5..7: the write happens first, so the read sees the new values. */
    size_t n = TRANSACT(r, 1, 0x17, 0x00, 5, 0x00, 3, 0x00, 6, 0x00, 2, 4, 0xAA, 0xAA, 0xBB, 0xBB);
    CHECK_EQ_INT(n, 9);
    CHECK_BYTES(r, 1, 0x17, 6, 0x05, 0x05, 0xAA, 0xAA, 0xBB, 0xBB);
    n = TRANSACT(r, 1, 0x17, 0x00, 5, 0x00, 126, 0x00, 6, 0x00, 1, 2, 0, 0);
    check_exception(r, n, 0x17, 3);
    n = TRANSACT(r, 1, 0x17, 0x00, 5, 0x00, 1, 0x00, 6, 0x00, 1, 4, 0, 0); /* byte count */
    check_exception(r, n, 0x17, 3);
    n = TRANSACT(r, 1, 0x17, 0x00, 5, 0x00, 1, 0x00, 6, 0x00, 1, 2, 0xDE, 0xAD);
    check_exception(r, n, 0x17, 3);
    CHECK_EQ_INT(bank.holding[6], 0xAAAA);
}

static void test_fc14_fc15_file_records(void) {
    setup(1, 19200);
    uint8_t r[260];
    /* Write 3 records to file 1 at record 9997, and 1 record to file 2 at 0, in one request. */
    size_t n = TRANSACT(r, 1, 0x15, 22, 6, 0x00, 1, 0x27, 0x0D, 0x00, 3, 0x01, 0x02, 0x03, 0x04,
                        0x05, 0x06, 6, 0x00, 2, 0x00, 0, 0x00, 1, 0x0A, 0x0B);
    CHECK_EQ_INT(n, 1 + 2 + 22);
    CHECK_BYTES(r, 1, 0x15, 22, 6, 0x00, 1, 0x27, 0x0D, 0x00, 3);
    CHECK_EQ_INT(bank.files[0][9997], 0x0102);
    CHECK_EQ_INT(bank.files[0][9999], 0x0506);
    CHECK_EQ_INT(bank.files[1][0], 0x0A0B);
    /* Read them back in two sub-requests. */
    n = TRANSACT(r, 1, 0x14, 14, 6, 0x00, 1, 0x27, 0x0E, 0x00, 2, 6, 0x00, 2, 0x00, 0, 0x00, 1);
    CHECK_EQ_INT(n, 1 + 2 + 6 + 4);
    CHECK_BYTES(r, 1, 0x14, 10, 5, 6, 0x03, 0x04, 0x05, 0x06, 3, 6, 0x0A, 0x0B);
    /* Exceptions: reference type, record 10000, record range past 9999, file 0, byte count,
     * reply too long, the app's own refusal. */
    n = TRANSACT(r, 1, 0x14, 7, 7, 0x00, 1, 0x00, 0, 0x00, 1);
    check_exception(r, n, 0x14, 2);
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 1, 0x27, 0x10, 0x00, 1);
    check_exception(r, n, 0x14, 2);
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 1, 0x27, 0x0F, 0x00, 2);
    check_exception(r, n, 0x14, 2);
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 0, 0x00, 0, 0x00, 1);
    check_exception(r, n, 0x14, 2);
    n = TRANSACT(r, 1, 0x14, 6, 6, 0x00, 1, 0x00, 0, 0x00);
    check_exception(r, n, 0x14, 3);
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 1, 0x00, 0, 0x00, 125); /* 2+2+250 > 253 */
    check_exception(r, n, 0x14, 3);
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 1, 0x00, 0, 0x00, 124);
    CHECK_EQ_INT(n, 1 + 2 + 2 + 248);
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 9, 0x00, 0, 0x00, 1); /* file 9: not in the store */
    check_exception(r, n, 0x14, 2);
    n = TRANSACT(r, 1, 0x15, 9, 6, 0x00, 3, 0x00, 0, 0x00, 1, 0x12, 0x34); /* read-only file */
    check_exception(r, n, 0x15, 1);
    /* A malformed second sub-request (data short of its length) must leave the first unwritten. */
    unsigned writes = bank.writes;
    n = TRANSACT(r, 1, 0x15, 20, 6, 0x00, 1, 0x00, 5, 0x00, 1, 0x77, 0x77, 6, 0x00, 1, 0x00, 6,
                 0x00, 2, 0x88, 0x88, 0x99);
    check_exception(r, n, 0x15, 3);
    CHECK_EQ_INT(bank.files[0][5], 0);
    CHECK_EQ_INT(bank.writes, writes);
}

static void test_fc2b_device_identification(void) {
    setup(1, 19200);
    uint8_t r[260];
    /* Basic stream from object 0: VendorName, ProductCode, MajorMinorRevision. */
    size_t n = TRANSACT(r, 1, 0x2B, 0x0E, 1, 0);
    const uint8_t head[] = {1, 0x2B, 0x0E, 1, 0x82, 0x00, 0x00, 3};
    CHECK_MEM(r, head, sizeof head);
    CHECK_EQ_INT(n, sizeof head + 2 + 16 + 2 + 10 + 2 + 5);
    CHECK_EQ_INT(r[8], 0);
    CHECK_EQ_INT(r[9], 16);
    CHECK_MEM(r + 10, "trimeter project", 16);
    CHECK_EQ_INT(r[26], 1);
    CHECK_MEM(r + 28, "TRIMETER-1", 10);
    CHECK_EQ_INT(r[38], 2);
    CHECK_MEM(r + 40, "0.1.0", 5);
    /* Regular stream: also objects 3 and 4. */
    n = TRANSACT(r, 1, 0x2B, 0x0E, 2, 0);
    CHECK_EQ_INT(r[7], 5);
    /* Individual access to object 2; an object that does not exist is exception 02. */
    n = TRANSACT(r, 1, 0x2B, 0x0E, 4, 2);
    CHECK_EQ_INT(n, 8 + 2 + 5);
    CHECK_EQ_INT(r[7], 1);
    CHECK_MEM(r + 10, "0.1.0", 5);
    n = TRANSACT(r, 1, 0x2B, 0x0E, 4, 0x80);
    check_exception(r, n, 0x2B, 2);
    /* Stream request with an out-of-range object id restarts at object 0. */
    n = TRANSACT(r, 1, 0x2B, 0x0E, 1, 9);
    CHECK_EQ_INT(r[7], 3);
    CHECK_EQ_INT(r[8], 0);
    n = TRANSACT(r, 1, 0x2B, 0x0E, 5, 0);
    check_exception(r, n, 0x2B, 3);
    n = TRANSACT(r, 1, 0x2B, 0x0D, 1, 0); /* CANopen MEI: not supported */
    check_exception(r, n, 0x2B, 1);
    /* Without regular objects the conformity level is basic. */
    app.vendor_url = app.product_name = NULL;
    n = TRANSACT(r, 1, 0x2B, 0x0E, 2, 0);
    CHECK_EQ_INT(r[4], 0x81);
    CHECK_EQ_INT(r[7], 3);
}

static void test_unsupported_function_codes(void) {
    setup(1, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 1, 0x08, 0x00, 0x00, 0x12, 0x34); /* diagnostics */
    check_exception(r, n, 0x08, 1);
    n = TRANSACT(r, 1, 0x41);
    check_exception(r, n, 0x41, 1);
    /* A function the app does not provide answers 01 too. */
    app.read_file = NULL;
    n = TRANSACT(r, 1, 0x14, 7, 6, 0x00, 1, 0x00, 0, 0x00, 1);
    check_exception(r, n, 0x14, 1);
}

/* ------------------------------------------------------------------ addressing, broadcast */

static void test_broadcast_executes_and_never_replies(void) {
    setup(5, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 0, 0x06, 0x00, 9, 0x00, 42);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(line.writes, 0);
    CHECK_EQ_INT(bank.holding[9], 42);
    n = TRANSACT(r, 0, 0x0F, 0x00, 0, 0x00, 3, 1, 0x05);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(bank.coils[0] + bank.coils[2], 2);
    /* A refused broadcast is not answered with an exception either. */
    n = TRANSACT(r, 0, 0x06, 0x00, 9, 0xDE, 0xAD);
    CHECK_EQ_INT(n, 0);
    /* Reads are not broadcastable: ignored, no reply. */
    n = TRANSACT(r, 0, 0x03, 0x00, 0, 0x00, 1);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(line.writes, 0);
    CHECK_EQ_INT(mb_counters(&slave)->broadcasts, 3);
}

static void test_other_addresses_ignored_and_address_change(void) {
    setup(5, 19200);
    uint8_t r[260];
    size_t n = TRANSACT(r, 6, 0x03, 0x00, 0, 0x00, 1);
    CHECK_EQ_INT(n, 0);
    CHECK_EQ_INT(mb_counters(&slave)->frames_other, 1);
    n = TRANSACT(r, 5, 0x03, 0x00, 0, 0x00, 1);
    CHECK_EQ_INT(n, 5);
    CHECK_EQ_INT(r[0], 5);
    mb_set_address(&slave, 6);
    n = TRANSACT(r, 6, 0x03, 0x00, 0, 0x00, 1);
    CHECK_EQ_INT(n, 5);
    CHECK_EQ_INT(r[0], 6);
    mb_set_address(&slave, 0);   /* invalid: kept */
    mb_set_address(&slave, 248); /* invalid: kept */
    n = TRANSACT(r, 6, 0x03, 0x00, 0, 0x00, 1);
    CHECK_EQ_INT(n, 5);
}

/* ---------------------------------------------------------------------------------- framer */

static const uint8_t READ_ONE[] = {1, 0x03, 0x00, 0x00, 0x00, 0x01};

static void test_t35_values(void) {
    CHECK_EQ_INT(mb_t35_us(9600), 4011);   /* 38.5 bit times */
    CHECK_EQ_INT(mb_t35_us(19200), 2006);
    CHECK_EQ_INT(mb_t35_us(38400), 1750);  /* fixed above 19200 */
    CHECK_EQ_INT(mb_t35_us(115200), 1750);
}

static void test_frame_split_byte_by_byte(void) {
    setup(1, 9600);
    uint8_t buf[16];
    size_t len = with_crc(buf, READ_ONE, sizeof READ_ONE);
    for (size_t i = 0; i < len; i++) { /* one byte per poll, 1 ms apart (< t3.5 = 4 ms) */
        tb_line_push(&line, buf + i, 1);
        mb_poll(&slave);
        line.now_us += 1000;
        mb_poll(&slave);
    }
    CHECK_EQ_INT(line.out_len, 0); /* not before t3.5 of silence */
    line.now_us += slave.t35_us - 1000 - 1;
    mb_poll(&slave);
    CHECK_EQ_INT(line.out_len, 0);
    line.now_us += 1;
    mb_poll(&slave);
    CHECK_EQ_INT(line.out_len, 7);
}

static void test_gap_inside_frame_drops_it_and_resyncs(void) {
    setup(1, 19200);
    uint8_t buf[16];
    size_t len = with_crc(buf, READ_ONE, sizeof READ_ONE);
    tb_line_push(&line, buf, 3);
    mb_poll(&slave);
    silence(); /* a t3.5 gap cuts the frame: both halves have bad CRCs */
    tb_line_push(&line, buf + 3, len - 3);
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.out_len, 0);
    CHECK_EQ_INT(mb_counters(&slave)->crc_errors, 2);
    uint8_t r[64];
    CHECK_EQ_INT(transact(READ_ONE, sizeof READ_ONE, r), 5);
}

static void test_back_to_back_frames_in_one_read(void) {
    setup(1, 19200);
    uint8_t buf[64];
    size_t a = with_crc(buf, READ_ONE, sizeof READ_ONE);
    const uint8_t write_regs[] = {1, 0x10, 0x00, 1, 0x00, 2, 4, 0, 7, 0, 8};
    size_t b = with_crc(buf + a, write_regs, sizeof write_regs);
    size_t c = with_crc(buf + a + b, BYTES(1, 0x2B, 0x0E, 4, 0));
    tb_line_push(&line, buf, a + b + c);
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.writes, 3);
    CHECK_EQ_INT(bank.holding[2], 8);
    CHECK_EQ_INT(mb_counters(&slave)->crc_errors, 0);
    /* A good request followed by noise: the request is served, the noise counted. */
    line.writes = 0;
    line.out_len = 0;
    tb_line_push(&line, buf, a);
    tb_line_push(&line, BYTES(0x55, 0xAA, 0x01, 0x02, 0x03));
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.writes, 1);
    CHECK_EQ_INT(mb_counters(&slave)->crc_errors, 1);
}

static void test_noise_before_a_request_is_skipped(void) {
    setup(1, 19200);
    uint8_t buf[16];
    size_t len = with_crc(buf, READ_ONE, sizeof READ_ONE);
    tb_line_push(&line, BYTES(0x00, 0xFF, 0x01, 0x7E)); /* glitch bytes, one looks like our address */
    tb_line_push(&line, buf, len);
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.writes, 1);
    CHECK_EQ_INT(line.out_len, 7);
    CHECK_EQ_INT(mb_counters(&slave)->crc_errors, 1);
    /* Noise before a request for another slave: nothing answered. */
    uint8_t other[16];
    const uint8_t for_slave_2[] = {2, 0x03, 0x00, 0x00, 0x00, 0x01};
    len = with_crc(other, for_slave_2, sizeof for_slave_2);
    line.writes = 0;
    tb_line_push(&line, BYTES(0x11, 0x22));
    tb_line_push(&line, other, len);
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.writes, 0);
}

static void test_garbage_and_bad_crc_are_dropped(void) {
    setup(1, 19200);
    uint8_t r[64], buf[16];
    tb_line_push(&line, BYTES(0xFF, 0x00, 0x13, 0x37, 0x42, 0x99, 0x01));
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.out_len, 0);
    size_t len = with_crc(buf, READ_ONE, sizeof READ_ONE);
    buf[len - 1] ^= 0x40;
    tb_line_push(&line, buf, len);
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.out_len, 0);
    tb_line_push(&line, BYTES(0x01, 0x03)); /* truncated */
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.out_len, 0);
    CHECK_EQ_INT(mb_counters(&slave)->crc_errors, 3);
    CHECK_EQ_INT(transact(READ_ONE, sizeof READ_ONE, r), 5);
    CHECK_EQ_INT(mb_counters(&slave)->frames_ok, 1);
}

static void test_oversize_frame_is_dropped(void) {
    setup(1, 19200);
    uint8_t junk[300], r[64];
    memset(junk, 0x01, sizeof junk);
    line.chunk = 16; /* like a UART FIFO: several reads per poll */
    tb_line_push(&line, junk, sizeof junk);
    mb_poll(&slave);
    mb_poll(&slave);
    silence();
    CHECK_EQ_INT(line.out_len, 0);
    CHECK_EQ_INT(mb_counters(&slave)->overruns, 1);
    CHECK_EQ_INT(transact(READ_ONE, sizeof READ_ONE, r), 5);
}

static void test_clock_wraparound(void) {
    setup(1, 19200);
    line.now_us = 0xFFFFFFFFu - 500u;
    mb_init(&slave, 1, 19200, &io, &app);
    uint8_t buf[16];
    size_t len = with_crc(buf, READ_ONE, sizeof READ_ONE);
    tb_line_push(&line, buf, len);
    mb_poll(&slave);
    line.now_us += 1000; /* wraps; 1000 us < t3.5 */
    mb_poll(&slave);
    CHECK_EQ_INT(line.out_len, 0);
    line.now_us += 1006;
    mb_poll(&slave);
    CHECK_EQ_INT(line.out_len, 7);
}

static void test_poll_never_spins_on_a_flooding_line(void) {
    setup(1, 19200);
    uint8_t junk[1000];
    memset(junk, 0xA5, sizeof junk);
    tb_line_push(&line, junk, sizeof junk);
    mb_poll(&slave); /* bounded budget: returns with bytes left in the line */
    CHECK(line.in_len - line.in_pos > 0);
}

int main(void) {
    RUN_TEST(test_fc03_fc04_read_registers);
    RUN_TEST(test_fc01_fc02_read_bits);
    RUN_TEST(test_fc05_write_single_coil);
    RUN_TEST(test_fc06_write_single_register);
    RUN_TEST(test_fc0f_write_multiple_coils);
    RUN_TEST(test_fc10_write_multiple_registers);
    RUN_TEST(test_fc17_read_write_multiple);
    RUN_TEST(test_fc14_fc15_file_records);
    RUN_TEST(test_fc2b_device_identification);
    RUN_TEST(test_unsupported_function_codes);
    RUN_TEST(test_broadcast_executes_and_never_replies);
    RUN_TEST(test_other_addresses_ignored_and_address_change);
    RUN_TEST(test_t35_values);
    RUN_TEST(test_frame_split_byte_by_byte);
    RUN_TEST(test_gap_inside_frame_drops_it_and_resyncs);
    RUN_TEST(test_back_to_back_frames_in_one_read);
    RUN_TEST(test_noise_before_a_request_is_skipped);
    RUN_TEST(test_garbage_and_bad_crc_are_dropped);
    RUN_TEST(test_oversize_frame_is_dropped);
    RUN_TEST(test_clock_wraparound);
    RUN_TEST(test_poll_never_spins_on_a_flooding_line);
    return CHECK_SUMMARY();
}
