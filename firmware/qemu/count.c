/* Bare-metal driver for counting instructions per call on a Cortex-M4 under QEMU (machine netduinoplus2).
 *
 * Each measurement prints its label over semihosting, then calls count_begin(), the function under test,
 * count_end(). count.py runs QEMU one instruction per translation block with every executed block logged,
 * and counts the instructions between the two markers; a measurement of nothing between them ("baseline",
 * first) is the markers' own cost, subtracted from the others. No interrupt is enabled, so nothing else
 * runs in between.
 *
 * Built with the inverse core (firmware/Makefile FIT_CORE_SRC, and COUNT_TABLE = a map table file), it
 * also counts tr_fit_bins on one bin at a time, for a spread of bins. */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "crc.h"
#include "map_table.h"
#include "modbus.h"

#ifdef TRIMETER_FIT_CORE
#include "fit.h"
#include "fit_core.h"
#endif

/* ---- semihosting (ARM "angel" calls: bkpt 0xAB, r0 = operation, r1 = argument) */
static int semihost(int op, const void *arg)
{
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

static void say(const char *text) { semihost(0x04, text); } /* SYS_WRITE0 */

static void leave(void) { semihost(0x18, (const void *)0x20026); } /* SYS_EXIT, ADP_Stopped_ApplicationExit */

/* ---- the markers: out of line, so their addresses are where the count starts and stops */
__attribute__((noinline)) void count_begin(void) { __asm__ volatile("" ::: "memory"); }
__attribute__((noinline)) void count_end(void) { __asm__ volatile("" ::: "memory"); }

/* ---- what is measured */
static uint8_t frame[256];
static volatile uint32_t sink;

static size_t no_read(void *ctx, uint8_t *buf, size_t max)
{
    (void)ctx, (void)buf, (void)max;
    return 0;
}
static void drop_write(void *ctx, const uint8_t *buf, size_t n) { (void)ctx, (void)buf, (void)n; }
static uint32_t zero_clock(void *ctx)
{
    (void)ctx;
    return 0;
}
static uint8_t read_zeros(void *ctx, mb_table_t t, uint16_t addr, uint16_t n, uint16_t *out)
{
    (void)ctx, (void)t, (void)addr;
    memset(out, 0, n * sizeof *out);
    return MB_OK;
}

static mb_slave_t slave;
static const mb_io_t io = {.read = no_read, .write = drop_write, .now_us = zero_clock};
static const mb_app_t modbus_app = {.read_regs = read_zeros};

#ifdef TRIMETER_FIT_CORE
extern const uint8_t count_table[], count_table_end[];
/* I_b, I_w, I_c, rho_b, rho_w: from a dark, dense sample to a pale, clear one */
static const float bins[][TR_FIT_IN_PER_BIN] = {
    {0.02f, 0.05f, 0.001f, 0.02f, 0.95f}, {0.10f, 0.30f, 0.05f, 0.02f, 0.95f}, {0.25f, 0.55f, 0.20f, 0.02f, 0.95f},
    {0.40f, 0.70f, 0.40f, 0.02f, 0.95f},  {0.60f, 0.62f, 0.002f, 0.02f, 0.95f}, {0.05f, 0.80f, 0.70f, 0.02f, 0.95f},
    {0.30f, 0.45f, 0.10f, 0.03f, 0.90f},  {0.15f, 0.90f, 0.85f, 0.02f, 0.95f},
};
#endif

int main(void)
{
    for (size_t i = 0; i < sizeof frame; i++) frame[i] = (uint8_t)(i * 7u + 3u);
    sink = crc16_modbus(frame, 1); /* the CRC tables fill on first use (at boot on the device): not counted */

    say("baseline\n");
    count_begin();
    count_end();

    say("crc16_modbus, 256 B\n");
    count_begin();
    sink = crc16_modbus(frame, sizeof frame);
    count_end();

    say("crc32_update, 1024 B\n");
    static uint8_t kib[1024];
    memset(kib, 0x5A, sizeof kib);
    count_begin();
    sink = crc32_update(0, kib, sizeof kib);
    count_end();

    say("mb_handle_adu, FC03 read of 10 registers\n");
    mb_init(&slave, 1, 115200, &io, &modbus_app);
    uint8_t adu[8] = {1, 0x03, 0, 0, 0, 10};
    uint16_t crc = crc16_modbus(adu, 6);
    adu[6] = (uint8_t)crc;
    adu[7] = (uint8_t)(crc >> 8);
    count_begin();
    mb_handle_adu(&slave, adu, sizeof adu);
    count_end();

    say("map_table_check, header\n");
    static uint8_t header[MAP_TABLE_HEADER_BYTES];
    count_begin();
    sink = (uint32_t)map_table_check(header, sizeof header + 4u, 0, 0);
    count_end();

#ifdef TRIMETER_FIT_CORE
    size_t table_len = (size_t)(count_table_end - count_table);
    float out[TR_FIT_OUT_PER_BIN];
    uint16_t flags;
    say("tr_fit_bins, table check (n = 0)\n");
    count_begin();
    sink = (uint32_t)tr_fit_bins(count_table, table_len, NULL, 0, NULL, NULL);
    count_end();
    for (size_t b = 0; b < sizeof bins / sizeof bins[0]; b++) {
        say("tr_fit_bins, 1 bin\n");
        count_begin();
        sink = (uint32_t)tr_fit_bins(count_table, table_len, bins[b], 1, out, &flags);
        count_end();
    }
    /* as the device fits a spectrum: fit_poll hands FIT_BINS_PER_POLL bins to one call, so the table check
     * is shared by that many */
    _Static_assert(FIT_BINS_PER_POLL == 4, "the label names 4 bins");
    static float poll_out[FIT_BINS_PER_POLL][TR_FIT_OUT_PER_BIN];
    static uint16_t poll_flags[FIT_BINS_PER_POLL];
    for (size_t b = 0; b + FIT_BINS_PER_POLL <= sizeof bins / sizeof bins[0]; b += FIT_BINS_PER_POLL) {
        say("tr_fit_bins, one fit_poll's 4 bins\n");
        count_begin();
        sink = (uint32_t)tr_fit_bins(count_table, table_len, &bins[b][0], FIT_BINS_PER_POLL, &poll_out[0][0],
                                     poll_flags);
        count_end();
    }
    /* the same bins in one call: the table is checked once for all of them */
    _Static_assert(sizeof bins / sizeof bins[0] == 8, "the label names 8 bins");
    static float all_out[sizeof bins / sizeof bins[0]][TR_FIT_OUT_PER_BIN];
    static uint16_t all_flags[sizeof bins / sizeof bins[0]];
    say("tr_fit_bins, the 8 bins in one call\n");
    count_begin();
    sink = (uint32_t)tr_fit_bins(count_table, table_len, &bins[0][0], sizeof bins / sizeof bins[0], &all_out[0][0],
                                 all_flags);
    count_end();
#endif
    leave();
    for (;;) {
    }
}

/* ---- start-up: the FPU on (the core is built for hard float), .data copied, .bss cleared */
extern uint32_t _sidata[], _sdata[], _edata[], _sbss[], _ebss[], _estack[];

__attribute__((noreturn)) void count_reset(void)
{
    *(volatile uint32_t *)0xE000ED88u |= 0xFu << 20; /* CPACR: CP10, CP11 full access */
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    for (uint32_t *s = _sidata, *d = _sdata; d < _edata;) *d++ = *s++;
    for (uint32_t *d = _sbss; d < _ebss;) *d++ = 0;
    main();
    for (;;) {
    }
}

__attribute__((section(".isr_vector"), used)) static void *const vectors[2] = {_estack, (void *)count_reset};
