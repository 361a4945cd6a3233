/* libFuzzer target over the whole request path: the real application (app.c with modbus, regmap,
 * config, motion, actuators, storage, map_table) on the fake HAL of firmware/tests (simulated time,
 * plant, NOR flash that can lose power). State is kept across inputs, as on a device that runs for
 * months: the configuration, the map slots, the erase counters, the unlock window and the clock
 * carry over, so the fuzzer can build up a state over many inputs (and a finding may need the inputs
 * before it: libFuzzer keeps them in its corpus).
 *
 * An input is a program of operations (see `run_op`): Modbus frames (CRC fixed, unicast, broadcast
 * or another address), raw byte streams for the framer, time steps and jumps, reboots, power cuts
 * during flash work, plant events, and two macros that reach deep states fast: unlock + a
 * destructive command, and a whole map upload of a (mutated) map table.
 *
 * Invariants (abort = a finding), besides the sanitizers':
 *   - a reply is one whole frame from our address with a good CRC, echoing the function code, an
 *     exception only with code 01..04 or 06; a broadcast is never answered;
 *   - a broadcast never erases or programs flash, nor opens an unlock window;
 *   - an erase happens only in a request that arrived while an unlock window was open, at most one
 *     per unlock; erases since boot never exceed the rate limit's budget;
 *   - a valid map slot always holds a table whose header map_table_check accepts;
 *   - state and fault stay inside their enums;
 *   - the on-device fit (a stand-in for the inverse core, defined here, checks the seam's contract): the
 *     core is called only during a run, with the active slot's bytes in place and its committed length,
 *     at most FIT_BINS_PER_POLL bins at a time; the table it reads stays valid to the run's end;
 *     fit_status stays in its enum and fit_bins_done never exceeds the run's count;
 *   - the micro-spectrometer: spectro_status stays in its enum, a capture never counts more frames than it
 *     asked for, the frame timing the port is given is always within the C12880MA's limits, and the live
 *     wavelength polynomial is always one the driver accepts (monotonic, in range);
 *   - standalone presses: standalone_status stays in its enum, the result never holds more than its bins,
 *     the auto-exposure never leaves the integration time's register range, and lamp_changed comes only
 *     with a lamp compared and beyond the tolerance. */
#include <math.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

#include "../core/app.h"
#include "../core/crc.h"
#include "fit_core.h"
#include "../core/map_table.h"
#include "../core/regmap.h"
#include "../tests/app_fixture.h"
#include "../tests/fake_hal.h"
#include "../tests/table_fixture.h"

static fake_hal_t *f;
static int (*real_erase)(void *ctx, enum hal_region region);
static int (*real_write)(void *ctx, enum hal_region region, uint32_t offset, const void *buf, size_t len);
static uint64_t erases, writes;   /* successful or not: every attempt reaches the flash */
static uint64_t boot_us, erases_at_boot;
static bool erased_in_window;     /* an erase already used the unlock window opened at window_us */
static uint32_t window_us;
static uint32_t checked_crc[STORAGE_MAP_SLOTS];
static bool checked_valid[STORAGE_MAP_SLOTS];

static int counting_erase(void *ctx, enum hal_region region)
{
    erases++;
    return real_erase(ctx, region);
}

static int counting_write(void *ctx, enum hal_region region, uint32_t offset, const void *buf, size_t len)
{
    writes++;
    return real_write(ctx, region, offset, buf, len);
}

static void boot(void)
{
    fake_hal_power_on(f);
    app_init(&f->hal);
    boot_us = f->now_us;
    erases_at_boot = erases;
    erased_in_window = false;
    memset(checked_valid, 0, sizeof checked_valid);
    run_ms(1);
}

static uint8_t our_address(void) { return app_get()->mb.address; }

/* ---------------------------------------------------------------- the inverse core's stand-in */

int tr_fit_bins(const uint8_t *table, size_t len, const float *in, size_t n, float *out, uint16_t *flags)
{
    const app_t *a = app_get();
    int slot = storage_map_active(&a->storage);
    if (slot < 0 || table != f->map[slot] || len != a->storage.map[slot].length) abort();
    if (n == 0) return table[84] == 'x' ? TR_FIT_ERR_TABLE : TR_FIT_OK; /* a table "of another format" */
    if (a->fit.status != TRIMETER_FIT_STATUS_BUSY || n > FIT_BINS_PER_POLL || !in || !out || !flags) abort();
    uint32_t stored = (uint32_t)(table[len - 4] | table[len - 3] << 8 | table[len - 2] << 16 |
                                 (uint32_t)table[len - 1] << 24);
    if (map_table_check(table, (uint32_t)len, crc32_update(0, table, len - 4), stored) != MAP_TABLE_OK) abort();
    for (size_t i = 0; i < n; i++) {
        const float *b = &in[i * TR_FIT_IN_PER_BIN];
        flags[i] = 0;
        for (int k = 0; k < TR_FIT_IN_PER_BIN; k++)
            if (b[k] != b[k] || b[k] - b[k] != 0.0f) flags[i] = 1u; /* NaN or inf: NONFINITE_INPUT */
        for (int k = 0; k < TR_FIT_OUT_PER_BIN; k++) out[i * TR_FIT_OUT_PER_BIN + k] = flags[i] ? b[k] - b[k] : b[k];
    }
    return table[85] == 'x' ? TR_FIT_ERR_ARGS : TR_FIT_OK; /* a core failing mid-run */
}

/* ---------------------------------------------------------------- invariants */

static bool window_open(const app_t *a)
{
    return a->unlock_open && (uint32_t)f->now_us - a->unlock_us < APP_UNLOCK_WINDOW_US;
}

static void check_reply(const uint8_t *adu)
{
    if (adu[0] == MB_ADDRESS_BROADCAST || adu[0] != our_address()) {
        if (f->tx_len) abort();
        return;
    }
    if (f->tx_len == 0) return; /* e.g. a request the framer dropped */
    const uint8_t *r = f->tx;
    if (f->tx_len < 4 || f->tx_len > MB_ADU_MAX || crc16_modbus(r, f->tx_len) != 0 || r[0] != our_address()) abort();
    if (r[1] & 0x80u) {
        if (f->tx_len != 5 || r[1] != (adu[1] | 0x80u)) abort();
        if (!((r[2] >= 1 && r[2] <= 4) || r[2] == MB_EX_SERVER_DEVICE_BUSY)) abort();
    } else if (r[1] != adu[1]) {
        abort();
    }
}

/* Erases in one request: only with an unlock window open before it, one per window; never broadcast. */
static void check_erases(const uint8_t *adu, uint64_t erases_before, uint64_t writes_before, bool open_before,
                         uint32_t unlock_us_before)
{
    uint64_t n = erases - erases_before;
    if (adu[0] == MB_ADDRESS_BROADCAST && (n || writes != writes_before)) abort();
    const app_t *a = app_get();
    if (adu[0] == MB_ADDRESS_BROADCAST && window_open(a) && (!open_before || a->unlock_us != unlock_us_before))
        abort();
    if (!n) return;
    if (!open_before || n > 1) abort();
    if (erased_in_window && window_us == unlock_us_before) abort();
    erased_in_window = true;
    window_us = unlock_us_before;
}

static void check_state(void)
{
    if ((unsigned)app_state() > TRIMETER_STATE_FAULT || (unsigned)app_fault() > TRIMETER_FAULT_STORAGE) abort();
    const fit_t *fit = &app_get()->fit;
    if ((unsigned)fit->status > TRIMETER_FIT_STATUS_ERROR_CORE || fit->done > fit->count || fit->count > FIT_MAX_BINS)
        abort();
    const c12880_t *sp = &app_get()->spectro;
    if ((unsigned)sp->status > TRIMETER_SPECTRO_STATUS_ERROR_NO_SENSOR || sp->frames_done > sp->frames) abort();
    if (f->spectro_frames && (f->spectro_timing.st_high_clocks < C12880_ST_HIGH_MIN_CLOCKS ||
                              f->spectro_timing.st_low_clocks < C12880_ST_LOW_MIN_CLOCKS ||
                              f->spectro_timing.pixels != C12880_PIXELS))
        abort();
    if (!c12880_wavelengths_valid(app_get()->cfg.spectro_wl)) abort();
    const standalone_t *sa = &app_get()->standalone;
    if ((unsigned)sa->status > TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED || sa->bins > STANDALONE_BINS) abort();
    /* a calibration press ends calibrated with its check passed, or refused with the check that refused it */
    if ((unsigned)sa->check > TRIMETER_STANDALONE_CHECK_BEAM_CHANGED) abort();
    if ((sa->status == TRIMETER_STANDALONE_STATUS_CALIBRATED) != (sa->check == TRIMETER_STANDALONE_CHECK_NONE) &&
        (sa->status == TRIMETER_STANDALONE_STATUS_CALIBRATED || sa->status == TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED))
        abort();
    if (sa->status == TRIMETER_STANDALONE_STATUS_LAMP_CHANGED) {
        bool changed = false;
        for (int l = 0; l < HAL_LED_COUNT; l++)
            changed = changed || fabsf(sa->lamp_level[l] - 1.0f) > STANDALONE_LAMP_TOLERANCE; /* NaN: false */
        if (!changed) abort();
    }
    for (int k = 0; k < STANDALONE_SETUPS; k++)
        if (sa->status != TRIMETER_STANDALONE_STATUS_NONE && sa->integration_us[k] &&
            (sa->integration_us[k] < REG_HR_SPECTRO_INTEGRATION_US_MIN || sa->integration_us[k] > REG_HR_SPECTRO_INTEGRATION_US_MAX))
            abort();
    /* the rate limit: a burst, then one per refill interval */
    uint64_t budget = STORAGE_ERASE_BURST + (f->now_us - boot_us) / STORAGE_ERASE_REFILL_US;
    if (erases - erases_at_boot > budget) abort();
    const storage_t *st = &app_get()->storage;
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++) {
        if (!st->map_valid[s] || (checked_valid[s] && checked_crc[s] == st->map[s].crc32)) continue;
        uint32_t len = st->map[s].length;
        const uint8_t *bytes = f->map[s];
        if (len < 4 || len > HAL_MAP_REGION_SIZE) abort();
        uint32_t stored = (uint32_t)(bytes[len - 4] | bytes[len - 3] << 8 | bytes[len - 2] << 16 |
                                     (uint32_t)bytes[len - 1] << 24);
        if (map_table_check(bytes, len, crc32_update(0, bytes, len - 4), stored) != MAP_TABLE_OK) abort();
        checked_valid[s] = true;
        checked_crc[s] = st->map[s].crc32;
    }
}

/* ---------------------------------------------------------------- frames */

/* One ADU (address .. PDU; the CRC is appended here) through the UART, then silence. */
static void deliver(uint8_t *adu, size_t len)
{
    uint16_t crc = crc16_modbus(adu, len);
    adu[len] = (uint8_t)crc;
    adu[len + 1] = (uint8_t)(crc >> 8);
    const app_t *a = app_get();
    bool open_before = window_open(a);
    uint32_t unlock_us_before = a->unlock_us;
    uint64_t erases_before = erases, writes_before = writes;
    memcpy(f->rx, adu, len + 2);
    f->rx_len = len + 2;
    f->rx_pos = 0;
    f->tx_len = 0;
    run_ms(app_get()->mb.t35_us / 1000u + 2u); /* the bytes, then silence > t3.5 */
    check_reply(adu);
    check_erases(adu, erases_before, writes_before, open_before, unlock_us_before);
}

static void write_regs(uint8_t address, uint16_t reg, uint16_t n, const uint16_t *vals)
{
    uint8_t adu[MB_ADU_MAX + 2] = {address, 0x10, (uint8_t)(reg >> 8), (uint8_t)reg, 0, (uint8_t)n, (uint8_t)(2 * n)};
    for (uint16_t i = 0; i < n; i++) {
        adu[7 + 2 * i] = (uint8_t)(vals[i] >> 8);
        adu[8 + 2 * i] = (uint8_t)vals[i];
    }
    deliver(adu, 7u + 2u * n);
}

/* one register as an FC 0x10 frame through the slave (the fixture's write_reg calls the callback directly) */
static void framed_write_reg(uint16_t reg, uint16_t v) { write_regs(our_address(), reg, 1, &v); }

static void unlock(void) { framed_write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY); }

/* FC 0x15: `n` records (<= 120) of the open upload from linear record index k. */
static void write_records(uint32_t k, const uint8_t *bytes, uint32_t nbytes)
{
    uint8_t adu[MB_ADU_MAX + 2];
    uint16_t n = (uint16_t)((nbytes + 1) / 2);
    uint16_t file = (uint16_t)(k / TRIMETER_MAP_RECORDS_PER_FILE + 1), rec = (uint16_t)(k % TRIMETER_MAP_RECORDS_PER_FILE);
    uint8_t head[] = {our_address(), 0x15, (uint8_t)(7 + 2 * n), 6, (uint8_t)(file >> 8), (uint8_t)file,
                      (uint8_t)(rec >> 8), (uint8_t)rec, (uint8_t)(n >> 8), (uint8_t)n};
    memcpy(adu, head, sizeof head);
    memset(adu + sizeof head, 0, 2u * n);
    memcpy(adu + sizeof head, bytes, nbytes);
    deliver(adu, sizeof head + 2u * n);
}

/* ---------------------------------------------------------------- the input program */

typedef struct {
    const uint8_t *p;
    size_t n;
} cursor_t;

static uint8_t take(cursor_t *c)
{
    if (!c->n) return 0;
    c->n--;
    return *c->p++;
}

static uint16_t take16(cursor_t *c) { return (uint16_t)(take(c) << 8 | take(c)); }

static uint8_t pick_address(uint8_t sel)
{
    switch (sel & 3u) {
    case 0: return MB_ADDRESS_BROADCAST;
    case 3: return (uint8_t)(our_address() % 247u + 1u); /* another slave */
    default: return our_address();
    }
}

static void op_frame(cursor_t *c)
{
    uint8_t adu[MB_ADU_MAX + 2];
    adu[0] = pick_address(take(c));
    size_t len = 2u + take(c) % 90u; /* address + PDU */
    for (size_t i = 1; i < len; i++) adu[i] = take(c);
    deliver(adu, len);
}

static void op_write_holding(cursor_t *c)
{
    uint16_t vals[16];
    uint8_t address = pick_address(take(c));
    uint16_t reg = take(c) % REG_HR_SPAN, n = (uint16_t)(1u + take(c) % 16u);
    for (uint16_t i = 0; i < n; i++) vals[i] = take16(c);
    write_regs(address, reg, n, vals);
}

static void op_raw(cursor_t *c)
{
    size_t len = take(c);
    if (len > FAKE_UART_SIZE) len = FAKE_UART_SIZE;
    size_t i = 0;
    for (; i < len && c->n; i++) f->rx[i] = take(c);
    f->rx_len = i;
    f->rx_pos = 0;
    f->tx_len = 0;
    run_ms(6);
}

static void op_time(cursor_t *c)
{
    uint8_t t = take(c);
    if (t & 0x80u && !f->timer_running) {
        f->now_us += (uint64_t)(t & 0x7Fu) * 1000000u; /* idle: jump (the unlock window, the erase refill) */
        app_poll();
    } else {
        run_ms(4u * (t & 0x7Fu));
    }
}

static void op_power_cut(cursor_t *c)
{
    f->power_budget = f->bytes_programmed + (long)take(c) * 8; /* power returns at the next reboot */
}

static void op_plant(cursor_t *c)
{
    uint8_t b = take(c);
    f->button = b & 1u;
    f->endstop_broken = b & 2u;
    f->stuck = b & 4u;
    f->has_stall_output = b & 8u;
    if (b & 16u) /* the lamp-monitor photodiodes read anything the ADC can */
        for (int l = 0; l < HAL_LED_COUNT; l++) f->lamp_adc[l] = (uint16_t)(take16(c) % 4096u);
}

static void op_unlocked_command(cursor_t *c)
{
    static const uint16_t commands[] = {TRIMETER_COMMAND_SAVE_CONFIG, TRIMETER_COMMAND_LOAD_DEFAULTS,
                                        TRIMETER_COMMAND_HOME, TRIMETER_COMMAND_CLEAR_FAULT};
    static const uint16_t map_commands[] = {TRIMETER_MAP_COMMAND_BEGIN_WRITE, TRIMETER_MAP_COMMAND_VERIFY,
                                            TRIMETER_MAP_COMMAND_ACTIVATE, TRIMETER_MAP_COMMAND_ABORT};
    uint8_t sel = take(c);
    if (!(sel & 0x40u)) unlock();
    if (sel & 0x80u) framed_write_reg(REG_HR_MAP_COMMAND, map_commands[sel % 4u]);
    else framed_write_reg(REG_HR_COMMAND, commands[sel % 4u]);
    if (sel & 0x20u) framed_write_reg(REG_HR_COMMAND, commands[sel % 4u]); /* a retry or a second try */
}

/* A whole upload, as `trimeter map flash` does it, of a fixture table with a few bytes changed. */
static void op_upload_table(cursor_t *c)
{
    static uint8_t table[4096];
    uint8_t how = take(c);
    uint32_t len = fixture_table(table, sizeof table, (uint16_t)(2u + how % 5u), take(c));
    for (uint8_t edits = take(c) % 4u; edits; edits--) {
        uint16_t at = take16(c) % len;
        table[at] = take(c);
    }
    if (how & 0x08u) fixture_table_fix_crc(table, len);
    uint16_t params[7];
    regmap_put_u32(&params[0], len);
    regmap_put_u32(&params[2], crc32_update(0, table, len));
    params[4] = how;
    params[5] = TRIMETER_MAP_SLOT_NONE;
    params[6] = TRIMETER_MAP_COMMAND_BEGIN_WRITE;
    unlock();
    write_regs(our_address(), REG_HR_MAP_EXPECTED_LENGTH, 7, params);
    for (uint32_t off = 0; off < len; off += 240) write_records(off / 2, table + off, len - off < 240 ? len - off : 240);
    framed_write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY);
    if (!(how & 0x10u)) unlock();
    framed_write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE);
}

/* Bins into file fit_input (raw words from the input, so NaN, inf and anything else), then one FC 0x10 of
 * count, thickness (the fixture tables' 0.4 mm, or raw) and fit_command, some time, and a read of results. */
static void op_fit(cursor_t *c)
{
    uint8_t how = take(c);
    uint16_t bins = (uint16_t)(1u + take(c) % 24u), first = (uint16_t)(how & 0x20u ? take16(c) % 300u : 0u);
    for (uint16_t b = 0; b < bins; b += 12) {
        uint16_t n = (uint16_t)((bins - b < 12 ? bins - b : 12) * TRIMETER_FIT_INPUT_WORD_STRIDE);
        uint16_t rec = (uint16_t)((first + b) * TRIMETER_FIT_INPUT_WORD_STRIDE);
        uint8_t adu[MB_ADU_MAX + 2] = {pick_address(how >> 6), 0x15, (uint8_t)(7 + 2 * n), 6, 0,
                                       TRIMETER_FIT_FILE_INPUT, (uint8_t)(rec >> 8), (uint8_t)rec, 0, (uint8_t)n};
        for (uint16_t i = 0; i < n; i++) {
            uint16_t w = take16(c);
            adu[10 + 2 * i] = (uint8_t)(w >> 8);
            adu[11 + 2 * i] = (uint8_t)w;
        }
        deliver(adu, 10u + 2u * n);
    }
    uint16_t params[REG_HR_FIT_COMMAND - REG_HR_FIT_BIN_COUNT + 1];
    params[0] = how & 0x10u ? take16(c) : (uint16_t)(first + bins);
    if (how & 0x01u) regmap_put_f32(&params[REG_HR_FIT_THICKNESS_MM - REG_HR_FIT_BIN_COUNT], 0.4f);
    else regmap_put_u32(&params[REG_HR_FIT_THICKNESS_MM - REG_HR_FIT_BIN_COUNT], (uint32_t)take16(c) << 16 | take16(c));
    params[REG_HR_FIT_COMMAND - REG_HR_FIT_BIN_COUNT] = how & 0x02u ? TRIMETER_FIT_COMMAND_ABORT : TRIMETER_FIT_COMMAND_RUN;
    write_regs(pick_address(how >> 2), REG_HR_FIT_BIN_COUNT, (uint16_t)(sizeof params / sizeof *params), params);
    run_ms(take(c) % 64u);
    uint16_t rec = (uint16_t)(take(c) * 3u), n = (uint16_t)(1u + take(c) % 120u);
    uint8_t read[] = {our_address(), 0x14, 7, 6, 0, how & 0x08u ? TRIMETER_FIT_FILE_INPUT : TRIMETER_FIT_FILE_OUTPUT,
                      (uint8_t)(rec >> 8), (uint8_t)rec, 0, (uint8_t)n, 0, 0};
    deliver(read, 10);
}

/* The micro-spectrometer: a board with or without it, a chip that loses EOS or saturates, raw parameter
 * words (any integration time, frame count, gain, wavelength coefficient), a command, some time, a file read
 * at raw records. */
static void op_spectro(cursor_t *c)
{
    static const uint32_t clocks[4] = {0u, 200000u, 500000u, 5000000u};
    uint8_t how = take(c);
    if (!app_get()->spectro.running) f->spectro_clock_hz = clocks[how & 3u]; /* a board keeps its clock mid-frame */
    f->spectro_no_eos = how & 4u;
    uint16_t level = how & 8u ? 4095u : take16(c) % 4096u;
    for (unsigned p = 0; p < 288; p++) f->spectro_video[p] = level;
    uint16_t params[REG_HR_SPECTRO_GAIN - REG_HR_SPECTRO_COMMAND + 1];
    for (unsigned i = 0; i < sizeof params / sizeof *params; i++) params[i] = take16(c);
    if (how & 0x10u) { /* mostly valid parameters, so that captures run */
        params[REG_HR_SPECTRO_FRAMES - REG_HR_SPECTRO_COMMAND] = (uint16_t)(1u + params[1] % 8u);
        regmap_put_u32(&params[REG_HR_SPECTRO_INTEGRATION_US - REG_HR_SPECTRO_COMMAND], 100u + params[2] % 50000u);
        params[REG_HR_SPECTRO_GAIN - REG_HR_SPECTRO_COMMAND] = (uint16_t)(1u << (params[4] % 4u));
        params[0] = (uint16_t)(params[0] % 4u);
    }
    write_regs(pick_address(how >> 6), REG_HR_SPECTRO_COMMAND, (uint16_t)(sizeof params / sizeof *params), params);
    if (how & 0x20u) { /* a wavelength coefficient, raw */
        uint16_t w[2] = {take16(c), take16(c)};
        write_regs(our_address(), (uint16_t)(REG_HR_SPECTRO_WL_A0 + 2u * (take(c) % C12880_WL_COEFFS)), 2, w);
    }
    run_ms(take(c) % 128u);
    uint16_t rec = take16(c) % 400u, n = (uint16_t)(1u + take(c) % 125u);
    uint8_t read[] = {our_address(), 0x14, 7, 6, 0, how & 0x01u ? TRIMETER_SPECTRO_FILE_DARK : TRIMETER_SPECTRO_FILE_LIGHT,
                      (uint8_t)(rec >> 8), (uint8_t)rec, 0, (uint8_t)n, 0, 0};
    deliver(read, 10);
}

/* A standalone press: a warm-up of a few seconds at most (the default's minutes would keep every press
 * waiting), a mode (raw or valid), the button held some time, some time, a read of file standalone_result
 * at raw records. */
static void op_standalone(cursor_t *c)
{
    uint8_t how = take(c);
    uint16_t warmup = take(c) % 4u;
    write_regs(our_address(), REG_HR_STANDALONE_WARMUP_S, 1, &warmup);
    uint16_t mode = how & 0x01u ? take16(c) : (uint16_t)(how >> 1) % 3u;
    write_regs(pick_address(how >> 6), REG_HR_STANDALONE_MODE, 1, &mode);
    f->button = true;
    run_ms(20u + take(c) % 64u);
    f->button = false;
    run_ms(take(c) * 64u); /* up to 16 s: a whole press (home, three set-ups, the fit) fits in */
    uint16_t rec = take16(c) % 4000u, n = (uint16_t)(1u + take(c) % 125u);
    uint8_t read[] = {our_address(), 0x14, 7, 6, 0, TRIMETER_STANDALONE_FILE_RESULT, (uint8_t)(rec >> 8), (uint8_t)rec,
                      0, (uint8_t)n, 0, 0};
    deliver(read, 10);
}

static void run_op(cursor_t *c)
{
    switch (take(c) % 13u) {
    case 0: op_frame(c); break;
    case 1: op_write_holding(c); break;
    case 2: op_raw(c); break;
    case 3: op_time(c); break;
    case 4: boot(); break;
    case 5: op_power_cut(c); break;
    case 6: op_plant(c); break;
    case 7: op_unlocked_command(c); break;
    case 8: op_upload_table(c); break;
    case 10: op_fit(c); break;
    case 11: op_spectro(c); break;
    case 12: op_standalone(c); break;
    default: /* factory-fresh flash: lets the fuzzer get out of a state it cannot leave */
        if (take(c) == 0xA5u) {
            memset(f->config, 0xFF, sizeof f->config);
            memset(f->map, 0xFF, sizeof f->map);
            boot();
        }
        break;
    }
    check_state();
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (!f) {
        f = fixture_fresh_hal();
        if (!f) abort();
        f->carriage_steps = 3000;
        f->endstop_steps = 0;
        f->hard_stop_steps = -40;
        real_erase = f->hal.storage_erase;
        real_write = f->hal.storage_write;
        f->hal.storage_erase = counting_erase;
        f->hal.storage_write = counting_write;
        boot();
    }
    cursor_t c = {data, size};
    for (int ops = 0; c.n && ops < 64; ops++) run_op(&c);
    return 0;
}
