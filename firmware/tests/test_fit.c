/* The on-device fit's plumbing through the app's Modbus callbacks, against a stand-in for the inverse core
 * (defined here, so only this test binary has one; test_app.c sees the build without it): bins in and out
 * over file records in the register map's layout, the run a few bins per main-loop turn, the table read
 * in place from the active slot, and every refusal with its exception and fit_status. */
#include <math.h>
#include <string.h>

#include "../core/app.h"
#include "../core/crc.h"
#include "fit_core.h"
#include "table_fit.h"
#include "../core/regmap.h"
#include "check.h"
#include "fake_hal.h"
#include "app_fixture.h"
#include "table_fixture.h"

#define MAP_GRID 4
#define MAP_BYTES 940

static fake_hal_t *f;
static uint8_t map_data[MAP_BYTES];

/* ---- the stand-in core: a transparent function of the inputs, and a record of how it was called */
static struct {
    bool reject_table;
    int fail_after_calls; /* >= 0: that many bin calls succeed, then TR_FIT_ERR_ARGS */
    int bin_calls;
    size_t max_n;
    const uint8_t *table;
    size_t len;
} core;

int tr_fit_bins(const uint8_t *table, size_t len, const float *in, size_t n, float *out, uint16_t *flags)
{
    core.table = table;
    core.len = len;
    if (core.reject_table) return TR_FIT_ERR_TABLE;
    if (n == 0) return TR_FIT_OK;
    if (core.fail_after_calls >= 0 && core.bin_calls >= core.fail_after_calls) return TR_FIT_ERR_ARGS;
    core.bin_calls++;
    if (n > core.max_n) core.max_n = n;
    for (size_t i = 0; i < n; i++) {
        const float *b = &in[i * TR_FIT_IN_PER_BIN];
        float *o = &out[i * TR_FIT_OUT_PER_BIN];
        bool finite = true;
        for (int k = 0; k < TR_FIT_IN_PER_BIN; k++) finite = finite && isfinite(b[k]);
        flags[i] = (uint16_t)((finite ? 0u : TM_FLAG_NONFINITE_INPUT) |
                              (b[TR_FIT_IN_RHO_B] < b[TR_FIT_IN_RHO_W] ? 0u : TM_FLAG_BAD_BACKGROUND));
        o[TR_FIT_OUT_ALPHA] = finite ? b[TR_FIT_IN_I_B] : NAN;
        o[TR_FIT_OUT_SIGMA_T] = b[TR_FIT_IN_I_W] * 10.0f;
        o[TR_FIT_OUT_G] = b[TR_FIT_IN_I_C] - b[TR_FIT_IN_RHO_B] - b[TR_FIT_IN_RHO_W];
    }
    return TR_FIT_OK;
}

/* ---- helpers over the app's callbacks */
/* One FC 0x10 over 24..27, as the host sends it: count, thickness, then the command. */
static uint8_t fit_command(uint16_t count, float thickness_mm, uint16_t command)
{
    uint16_t w[REG_HR_FIT_COMMAND - REG_HR_FIT_BIN_COUNT + 1] = {0};
    w[0] = count;
    regmap_put_f32(&w[REG_HR_FIT_THICKNESS_MM - REG_HR_FIT_BIN_COUNT], thickness_mm);
    w[REG_HR_FIT_COMMAND - REG_HR_FIT_BIN_COUNT] = command;
    return app_write_regs(NULL, REG_HR_FIT_BIN_COUNT, (uint16_t)(sizeof w / sizeof *w), w);
}

static void fresh_device(void)
{
    f = fixture_fresh_hal();
    memset(&core, 0, sizeof core);
    core.fail_after_calls = -1;
    fixture_boot();
}

/* Uploads, verifies and activates the fixture table (thickness 0.4 mm) as `trimeter map flash` does. */
static void activate_table(void)
{
    CHECK_EQ_INT(fixture_table(map_data, MAP_BYTES, MAP_GRID, 3), MAP_BYTES);
    CHECK_EQ_INT(fixture_activate_table(map_data, MAP_BYTES), 0);
}

/* Bin k's inputs, distinct per bin and per field. */
static void bin_inputs(unsigned k, float v[TR_FIT_IN_PER_BIN])
{
    v[TR_FIT_IN_I_B] = 0.01f * (float)k;
    v[TR_FIT_IN_I_W] = 0.5f + 0.001f * (float)k;
    v[TR_FIT_IN_I_C] = 0.25f;
    v[TR_FIT_IN_RHO_B] = 0.02f;
    v[TR_FIT_IN_RHO_W] = 0.95f;
}

/* Writes bins 0..count-1 into file fit_input, 12 bins per request as the host does. */
static void write_bins(unsigned count)
{
    static const uint16_t word[TR_FIT_IN_PER_BIN] = {
        [TR_FIT_IN_I_B] = TRIMETER_FIT_INPUT_WORD_I_B,     [TR_FIT_IN_I_W] = TRIMETER_FIT_INPUT_WORD_I_W,
        [TR_FIT_IN_I_C] = TRIMETER_FIT_INPUT_WORD_I_C,     [TR_FIT_IN_RHO_B] = TRIMETER_FIT_INPUT_WORD_RHO_B,
        [TR_FIT_IN_RHO_W] = TRIMETER_FIT_INPUT_WORD_RHO_W,
    };
    uint16_t words[12 * TRIMETER_FIT_INPUT_WORD_STRIDE];
    for (unsigned first = 0; first < count; first += 12) {
        unsigned n = count - first < 12 ? count - first : 12;
        memset(words, 0, sizeof words);
        for (unsigned i = 0; i < n; i++) {
            float v[TR_FIT_IN_PER_BIN];
            bin_inputs(first + i, v);
            for (int k = 0; k < TR_FIT_IN_PER_BIN; k++)
                regmap_put_f32(&words[i * TRIMETER_FIT_INPUT_WORD_STRIDE + word[k]], v[k]);
        }
        CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_INPUT, (uint16_t)(first * TRIMETER_FIT_INPUT_WORD_STRIDE),
                                    (uint16_t)(n * TRIMETER_FIT_INPUT_WORD_STRIDE), words),
                     MB_OK);
    }
}

static void test_a_run_fits_every_bin_a_few_per_turn_with_the_table_in_place(void)
{
    fresh_device();
    activate_table();
    enum { BINS = 37 };
    write_bins(BINS);
    CHECK_EQ_INT(ir(REG_IR_FIT_AVAILABLE), 1);
    CHECK_EQ_INT(fit_command(BINS, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_BUSY);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), 0);
    /* the core reads the active slot's flash where it lies, the committed length of it */
    CHECK(core.table == f->map[0]);
    CHECK_EQ_INT(core.len, MAP_BYTES);
    CHECK_EQ_INT(ir32(REG_IR_FIT_TABLE_CRC32), crc32_update(0, map_data, MAP_BYTES - 4)); /* the table's own */
    uint16_t out[7 * 17];
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, 0, 1, out), MB_EX_ILLEGAL_DATA_ADDRESS); /* none yet */
    run_ms(1);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), FIT_BINS_PER_POLL);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_BUSY);
    run_ms(BINS);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_DONE);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), BINS);
    CHECK_EQ_INT(core.max_n, FIT_BINS_PER_POLL);
    CHECK_EQ_INT(core.bin_calls, (BINS + FIT_BINS_PER_POLL - 1) / FIT_BINS_PER_POLL);
    for (unsigned first = 0; first < BINS; first += 17) {
        unsigned n = BINS - first < 17 ? BINS - first : 17;
        CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, (uint16_t)(first * TRIMETER_FIT_OUTPUT_WORD_STRIDE),
                                   (uint16_t)(n * TRIMETER_FIT_OUTPUT_WORD_STRIDE), out),
                     MB_OK);
        for (unsigned i = 0; i < n; i++) {
            float v[TR_FIT_IN_PER_BIN];
            bin_inputs(first + i, v);
            const uint16_t *w = &out[i * TRIMETER_FIT_OUTPUT_WORD_STRIDE];
            CHECK(regmap_get_f32(&w[TRIMETER_FIT_OUTPUT_WORD_ALPHA]) == v[TR_FIT_IN_I_B]);
            CHECK(regmap_get_f32(&w[TRIMETER_FIT_OUTPUT_WORD_SIGMA_T]) == v[TR_FIT_IN_I_W] * 10.0f);
            CHECK(regmap_get_f32(&w[TRIMETER_FIT_OUTPUT_WORD_G]) ==
                  v[TR_FIT_IN_I_C] - v[TR_FIT_IN_RHO_B] - v[TR_FIT_IN_RHO_W]);
            CHECK_EQ_INT(w[TRIMETER_FIT_OUTPUT_WORD_FLAGS], 0);
        }
    }
    /* past the run's bins, and past the capacity */
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, BINS * TRIMETER_FIT_OUTPUT_WORD_STRIDE - 1, 2, out),
                 MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_INPUT, FIT_MAX_BINS * TRIMETER_FIT_INPUT_WORD_STRIDE - 1, 2, out),
                 MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_INPUT, FIT_MAX_BINS * TRIMETER_FIT_INPUT_WORD_STRIDE, 1, out),
                 MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_OUTPUT, 0, 1, out), MB_EX_ILLEGAL_DATA_ADDRESS);
    /* the inputs read back as written */
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_INPUT, 5 * TRIMETER_FIT_INPUT_WORD_STRIDE, 2, out), MB_OK);
    float v5[TR_FIT_IN_PER_BIN];
    bin_inputs(5, v5);
    CHECK(regmap_get_f32(out) == v5[TR_FIT_IN_I_B]);
}

static void test_nan_and_impossible_inputs_reach_the_core_and_come_back_flagged(void)
{
    fresh_device();
    activate_table();
    write_bins(2);
    uint16_t w[2];
    regmap_put_f32(w, NAN);
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_INPUT, TRIMETER_FIT_INPUT_WORD_I_C, 2, w), MB_OK);
    regmap_put_f32(w, 1.5f); /* rho_b above rho_w */
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_INPUT,
                                TRIMETER_FIT_INPUT_WORD_STRIDE + TRIMETER_FIT_INPUT_WORD_RHO_B, 2, w),
                 MB_OK);
    CHECK_EQ_INT(fit_command(2, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_OK);
    run_ms(2);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_DONE);
    uint16_t out[2 * TRIMETER_FIT_OUTPUT_WORD_STRIDE];
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, 0, 2 * TRIMETER_FIT_OUTPUT_WORD_STRIDE, out), MB_OK);
    CHECK_EQ_INT(out[TRIMETER_FIT_OUTPUT_WORD_FLAGS], TM_FLAG_NONFINITE_INPUT);
    CHECK(isnan(regmap_get_f32(&out[TRIMETER_FIT_OUTPUT_WORD_ALPHA])));
    CHECK_EQ_INT(out[TRIMETER_FIT_OUTPUT_WORD_STRIDE + TRIMETER_FIT_OUTPUT_WORD_FLAGS], TM_FLAG_BAD_BACKGROUND);
}

static void test_run_is_refused_with_its_reason_before_any_bin_is_fitted(void)
{
    fresh_device();
    write_bins(3);
    CHECK_EQ_INT(fit_command(3, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ERROR_NO_TABLE);
    activate_table();
    CHECK_EQ_INT(fit_command(3, 0.8f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_DATA_VALUE); /* the table's ℓ is 0.4 */
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ERROR_GEOMETRY);
    CHECK_EQ_INT(fit_command(3, 0.0f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_DATA_VALUE); /* unstated */
    CHECK_EQ_INT(fit_command(3, 0.4001f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_DATA_VALUE);
    core.reject_table = true;
    CHECK_EQ_INT(fit_command(3, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ERROR_TABLE);
    core.reject_table = false;
    /* counts outside 1..capacity and a NaN thickness never reach the fit (register map: 03) */
    CHECK_EQ_INT(fit_command(0, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(fit_command(FIT_MAX_BINS + 1, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(fit_command(3, NAN, TRIMETER_FIT_COMMAND_RUN), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ERROR_TABLE); /* unchanged by those */
    run_ms(5);
    CHECK_EQ_INT(core.bin_calls, 0);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), 0);
}

static void test_while_a_fit_runs_its_inputs_and_table_are_left_alone(void)
{
    fresh_device();
    activate_table();
    write_bins(40);
    CHECK_EQ_INT(fit_command(40, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_OK);
    run_ms(1);
    uint16_t w[2] = {0, 0};
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_INPUT, 0, 2, w), MB_EX_SERVER_DEVICE_BUSY);
    CHECK_EQ_INT(fit_command(40, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_EX_SERVER_DEVICE_BUSY);
    /* a begin_write now could erase the slot the run reads after an activation: refused */
    CHECK_EQ_INT(write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_BEGIN_WRITE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_STATE);
    CHECK_EQ_INT(ir32(REG_IR_ERASE_COUNT_MAP_B), 0);
    /* abort: what is done stays readable, nothing more is fitted */
    CHECK_EQ_INT(fit_command(40, 0.4f, TRIMETER_FIT_COMMAND_ABORT), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ABORTED);
    uint16_t done = ir(REG_IR_FIT_BINS_DONE);
    CHECK(done > 0 && done < 40);
    run_ms(20);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), done);
    uint16_t out[TRIMETER_FIT_OUTPUT_WORD_STRIDE];
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, (uint16_t)((done - 1) * TRIMETER_FIT_OUTPUT_WORD_STRIDE),
                               TRIMETER_FIT_OUTPUT_WORD_STRIDE, out),
                 MB_OK);
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_FIT_FILE_INPUT, 0, 2, w), MB_OK); /* writable again */
}

static void test_a_broadcast_neither_writes_bins_nor_runs_a_fit(void)
{
    fresh_device();
    activate_table();
    write_bins(1);
    /* FC 0x15 to address 0: one record of file fit_input */
    const uint8_t bins[] = {0, 0x15, 9, 6, 0, TRIMETER_FIT_FILE_INPUT, 0, 0, 0, 1, 0x12, 0x34};
    send_frame(bins, sizeof bins);
    CHECK_EQ_INT(f->tx_len, 0);
    uint16_t back;
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_INPUT, 0, 1, &back), MB_OK);
    CHECK(back != 0x1234);
    /* FC 0x10 to address 0 over 24..27: count 1, 0.4 mm (0x3ECCCCCD), run */
    const uint8_t run[] = {0, 0x10, 0, REG_HR_FIT_BIN_COUNT, 0, 4, 8, 0, 1, 0x3E, 0xCC, 0xCC, 0xCD,
                           0, TRIMETER_FIT_COMMAND_RUN};
    send_frame(run, sizeof run);
    CHECK_EQ_INT(f->tx_len, 0);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_IDLE);
    CHECK_EQ_INT(core.bin_calls, 0);
    /* the same run from our address works: the frame was right, only the broadcast was refused */
    uint8_t unicast[sizeof run];
    memcpy(unicast, run, sizeof run);
    unicast[0] = app_get()->mb.address;
    send_frame(unicast, sizeof unicast);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_DONE);
    CHECK_EQ_INT(core.bin_calls, 1);
}

static void test_a_core_failure_mid_run_stops_it_with_error_core(void)
{
    fresh_device();
    activate_table();
    write_bins(20);
    core.fail_after_calls = 2;
    CHECK_EQ_INT(fit_command(20, 0.4f, TRIMETER_FIT_COMMAND_RUN), MB_OK);
    run_ms(10);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ERROR_CORE);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), 2 * FIT_BINS_PER_POLL);
    uint16_t out[1];
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, 2 * FIT_BINS_PER_POLL * TRIMETER_FIT_OUTPUT_WORD_STRIDE, 1,
                               out),
                 MB_EX_ILLEGAL_DATA_ADDRESS);
}

int main(void)
{
    RUN_TEST(test_a_run_fits_every_bin_a_few_per_turn_with_the_table_in_place);
    RUN_TEST(test_nan_and_impossible_inputs_reach_the_core_and_come_back_flagged);
    RUN_TEST(test_run_is_refused_with_its_reason_before_any_bin_is_fitted);
    RUN_TEST(test_while_a_fit_runs_its_inputs_and_table_are_left_alone);
    RUN_TEST(test_a_core_failure_mid_run_stops_it_with_error_core);
    RUN_TEST(test_a_broadcast_neither_writes_bins_nor_runs_a_fit);
    fixture_free_hal();
    return CHECK_SUMMARY();
}
