/* Standalone presses through the app: a press with standalone_mode set homes, captures the black, white
 * and open set-ups (each with its own auto-exposed integration time and dark), calibrates or fits against
 * the stand-in inverse core (standin/fit_core_standin.c, linked into this test only; transparent:
 * alpha = I_b, sigma_t = 10 I_w, g = I_c - rho_b - rho_w) and keeps the result in file standalone_result;
 * the refusals, the LED and the bins' arithmetic; the lamps' warm-up before a press and their photodiodes
 * against the calibration's. */
#include <math.h>
#include <string.h>

#include "../core/app.h"
#include "../core/crc.h"
#include "fit_core.h"
#include "table_fit.h"
#include "../core/regmap.h"
#include "../core/standalone.h"
#include "check.h"
#include "fake_hal.h"
#include "app_fixture.h"
#include "table_fixture.h"

#define MAP_GRID 4
#define MAP_BYTES 940
#define DARK_COUNTS 100u
#define UNLIT_PIXELS 10u          /* the first pixels see no light in any set-up */

static fake_hal_t *f;
static uint8_t map_data[MAP_BYTES];

/* ---- a plant for the chip: each set-up's light, counts per ms of integration, by slot and shutters */
static struct {
    float black, white, open; /* panels on the black / white slot, the beam through the open slot */
} light;
/* each lamp's emission relative to nominal (an aged LED: < 1); it scales the chip's light and the lamp's
 * photodiode alike; monitor_missing: a board without lamp-monitor photodiodes (they read 0) */
static float emission[HAL_LED_COUNT] = {1.0f, 1.0f, 1.0f};
static bool monitor_missing;
#define MONITOR_DARK_COUNTS 60.0f
#define MONITOR_SPAN_COUNTS 3000.0f

static void feed_chip(void)
{
    const app_t *a = app_get();
    uint16_t slot = TRIMETER_SLOT_UNKNOWN;
    uint16_t w = 0;
    app_read_regs(NULL, MB_TABLE_INPUT_REGISTERS, REG_IR_POSITION_SLOT, 1, &w);
    slot = w;
    float rate = 0.0f; /* counts per ms */
    bool panels = a->act.shutter_open[HAL_SHUTTER_PANEL_LEFT] && a->act.led_on[HAL_LED_PANEL_LEFT];
    bool beam = a->act.shutter_open[HAL_SHUTTER_COLLIMATED] && a->act.led_on[HAL_LED_COLLIMATED];
    float panel_emission = emission[HAL_LED_PANEL_LEFT];
    if (panels && slot == TRIMETER_SLOT_BLACK) rate += light.black * panel_emission;
    if (panels && slot == TRIMETER_SLOT_WHITE) rate += light.white * panel_emission;
    if (beam && slot == TRIMETER_SLOT_OPEN) rate += light.open * emission[HAL_LED_COLLIMATED];
    for (int l = 0; l < HAL_LED_COUNT; l++) {
        bool lit = a->act.shutter_open[l] && a->act.led_on[l];
        f->lamp_adc[l] = monitor_missing ? 0u : (uint16_t)(MONITOR_DARK_COUNTS + (lit ? MONITOR_SPAN_COUNTS * emission[l] : 0.0f));
    }
    float ms = (float)a->standalone.integration_us[a->press_setup < STANDALONE_SETUPS ? a->press_setup : 0] / 1000.0f;
    for (unsigned p = 0; p < C12880_PIXELS; p++) {
        float v = DARK_COUNTS + (p < UNLIT_PIXELS ? 0.0f : rate * ms);
        f->spectro_video[p] = (uint16_t)(v > C12880_ADC_FULL_SCALE ? C12880_ADC_FULL_SCALE : v);
    }
}

/* Time passing with nothing to capture, in coarse steps (the warm-up's minutes). */
static void idle_s(uint32_t s)
{
    for (uint32_t i = 0; i < 100u * s; i++) {
        fake_hal_run_until(f, f->now_us + 10000, fixture_step_isr, NULL);
        app_poll();
    }
}

static void fresh_device(bool spectrometer)
{
    f = fixture_fresh_hal();
    f->spectro_clock_hz = spectrometer ? 1000000u : 0u;
    for (int l = 0; l < HAL_LED_COUNT; l++) emission[l] = 1.0f;
    monitor_missing = false;
    fixture_each_ms(feed_chip); /* the chip sees each set-up's light as the main loop runs */
    fixture_boot();
}

/* Uploads, verifies and activates the fixture table as `trimeter map flash` does. */
static void activate_table(void)
{
    CHECK_EQ_INT(fixture_table(map_data, MAP_BYTES, MAP_GRID, 3), MAP_BYTES);
    CHECK_EQ_INT(fixture_activate_table(map_data, MAP_BYTES), 0);
}

/* A press of the button, then the main loop until the press ended (or limit_ms). */
static uint16_t press(uint32_t limit_ms)
{
    f->button = true;
    run_ms(60);
    f->button = false;
    for (uint32_t i = 0; i < limit_ms && (i < 100 || ir(REG_IR_STANDALONE_STATUS) == TRIMETER_STANDALONE_STATUS_BUSY); i++)
        run_ms(1);
    return ir(REG_IR_STANDALONE_STATUS);
}

static float result_f32(unsigned bin, unsigned word)
{
    uint16_t w[2] = {0};
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_STANDALONE_FILE_RESULT,
                               (uint16_t)(bin * TRIMETER_STANDALONE_WORD_STRIDE + word), 2, w),
                 MB_OK);
    return regmap_get_f32(w);
}

static uint16_t result_u16(unsigned bin, unsigned word)
{
    uint16_t w = 0;
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_STANDALONE_FILE_RESULT,
                               (uint16_t)(bin * TRIMETER_STANDALONE_WORD_STRIDE + word), 1, &w),
                 MB_OK);
    return w;
}

static bool near(float a, float b, float rel) { return fabsf(a - b) <= rel * fabsf(b); }

/* ---------------------------------------------------------------- tests */

static void test_mode_off_leaves_presses_to_the_host(void)
{
    fresh_device(true);
    activate_table();
    press(200);
    CHECK_EQ_INT(ir(REG_IR_BUTTON_EVENTS), 1);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_STATUS), TRIMETER_STANDALONE_STATUS_NONE);
    CHECK(!app_get()->motion.homed && !motion_busy(&app_get()->motion));
}

static void test_refusals(void)
{
    fresh_device(true); /* no table */
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    CHECK_EQ_INT(press(200), TRIMETER_STANDALONE_STATUS_ERROR_NO_TABLE);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_FAST_BLINK);
    activate_table();
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_MEASURE), MB_OK);
    CHECK_EQ_INT(press(200), TRIMETER_STANDALONE_STATUS_ERROR_NO_CALIBRATION);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_BINS), 0);
    uint16_t w;
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_STANDALONE_FILE_RESULT, 0, 1, &w), MB_EX_ILLEGAL_DATA_ADDRESS);

    fresh_device(false); /* a board without the spectrometer */
    activate_table();
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    CHECK_EQ_INT(press(200), TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO);
}

static void test_calibration_then_measurement(void)
{
    fresh_device(true);
    activate_table();
    uint16_t it[2];
    regmap_put_u32(it, 4000);
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_SPECTRO_INTEGRATION_US, 2, it), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_FRAMES, 2), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_WARMUP_S, 0), MB_OK); /* test_a_press_waits_for_warm_lamps */
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    light.black = 25.0f, light.white = 250.0f, light.open = 400.0f;

    f->button = true;
    run_ms(60);
    f->button = false;
    run_ms(200);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_STATUS), TRIMETER_STANDALONE_STATUS_BUSY);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_SLOW_BLINK);
    CHECK_EQ_INT(write_reg(REG_HR_COMMAND, TRIMETER_COMMAND_GOTO_WHITE), MB_EX_SERVER_DEVICE_BUSY); /* the press moves */
    uint16_t status = TRIMETER_STANDALONE_STATUS_BUSY;
    for (int i = 0; i < 120000 && status == TRIMETER_STANDALONE_STATUS_BUSY; i++) {
        run_ms(1);
        status = ir(REG_IR_STANDALONE_STATUS);
    }
    CHECK_EQ_INT(status, TRIMETER_STANDALONE_STATUS_CALIBRATED);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_ON);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_CALIBRATED), 1);
    CHECK_EQ_INT(app_get()->hr[REG_HR_STANDALONE_MODE], TRIMETER_STANDALONE_MODE_MEASURE);
    /* auto-exposure: each set-up doubled from 4 ms until its brightest pixel was >= 40 % of full scale */
    CHECK_EQ_INT(ir32(REG_IR_STANDALONE_INTEGRATION_BLACK_US), 64000);
    CHECK_EQ_INT(ir32(REG_IR_STANDALONE_INTEGRATION_WHITE_US), 8000);
    CHECK_EQ_INT(ir32(REG_IR_STANDALONE_INTEGRATION_OPEN_US), 4000);
    /* every shutter closed after the press, every lamp still on (warm for the next press) */
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) CHECK(!app_get()->act.shutter_open[s] && app_get()->act.led_on[s]);
    CHECK(near(result_f32(20, TRIMETER_STANDALONE_WORD_DIFFUSE), 250e3f / 0.99f, 1e-3f));
    CHECK(near(result_f32(20, TRIMETER_STANDALONE_WORD_COLLIMATED), 400e3f, 1e-3f));
    CHECK(near(result_f32(20, TRIMETER_STANDALONE_WORD_RHO_BLACK), 25.0f * 0.99f / 250.0f, 1e-3f));
    CHECK_EQ_INT(result_u16(2, TRIMETER_STANDALONE_WORD_CAPTURE_FLAGS), STANDALONE_CAPTURE_NO_REFERENCE_LIGHT);
    CHECK_EQ_INT(result_u16(20, TRIMETER_STANDALONE_WORD_CAPTURE_FLAGS), 0);

    /* a sample in the holder: less light everywhere */
    light.black = 30.0f, light.white = 200.0f, light.open = 100.0f;
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_DONE);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_ON);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_BINS), STANDALONE_BINS);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_FLAGGED_BINS), 0);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_SEQUENCE), 2);
    CHECK(ir32(REG_IR_STANDALONE_TABLE_CRC32) != 0);
    float diffuse = 250e3f / 0.99f, rho_b = 25.0f * 0.99f / 250.0f;
    for (unsigned b = UNLIT_PIXELS / 2; b < STANDALONE_BINS; b += 37) {
        CHECK(near(result_f32(b, TRIMETER_STANDALONE_WORD_BLACK), 30e3f, 1e-3f));
        CHECK(near(result_f32(b, TRIMETER_STANDALONE_WORD_ALPHA), 30e3f / diffuse, 1e-3f));
        CHECK(near(result_f32(b, TRIMETER_STANDALONE_WORD_SIGMA_T), 10.0f * 200e3f / diffuse, 1e-3f));
        CHECK(fabsf(result_f32(b, TRIMETER_STANDALONE_WORD_G) - (100.0f / 400.0f - rho_b - 0.99f)) < 1e-3f);
        CHECK_EQ_INT(result_u16(b, TRIMETER_STANDALONE_WORD_FIT_FLAGS), 0);
    }
    /* an unlit bin: NaN inputs, flagged by the fit, not counted as a flagged result */
    CHECK(isnan(result_f32(0, TRIMETER_STANDALONE_WORD_ALPHA)));
    CHECK_EQ_INT(result_u16(0, TRIMETER_STANDALONE_WORD_FIT_FLAGS), TM_FLAG_NONFINITE_INPUT);
    /* wavelengths: the mean of each pair's, increasing */
    float wl0 = result_f32(0, TRIMETER_STANDALONE_WORD_WAVELENGTH_NM);
    float want0 = 0.5f * (c12880_wavelength_nm(app_get()->cfg.spectro_wl, 1) + c12880_wavelength_nm(app_get()->cfg.spectro_wl, 2));
    CHECK(fabsf(wl0 - want0) < 1e-3f);
    CHECK(result_f32(STANDALONE_BINS - 1, TRIMETER_STANDALONE_WORD_WAVELENGTH_NM) > wl0);
    /* the file: read-only, nothing past the last bin */
    uint16_t w[2] = {0};
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_STANDALONE_FILE_RESULT, 0, 1, w), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_STANDALONE_FILE_RESULT,
                               (uint16_t)(STANDALONE_BINS * TRIMETER_STANDALONE_WORD_STRIDE - 1), 2, w),
                 MB_EX_ILLEGAL_DATA_ADDRESS);
}

static float ir_f32(uint16_t addr)
{
    uint16_t w[2];
    CHECK_EQ_INT(app_read_regs(NULL, MB_TABLE_INPUT_REGISTERS, addr, 2, w), MB_OK);
    return regmap_get_f32(w);
}

/* A device calibrated with warm lamps (no warm-up wait: standalone_warmup_s 0), ready to measure. */
static void calibrated_device(bool monitor)
{
    fresh_device(true);
    monitor_missing = !monitor;
    activate_table();
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_WARMUP_S, 0), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    light.black = 25.0f, light.white = 250.0f, light.open = 400.0f;
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_CALIBRATED);
    CHECK(isnan(ir_f32(REG_IR_STANDALONE_LAMP_COLLIMATED))); /* a calibration compares nothing */
    light.black = 30.0f, light.white = 200.0f, light.open = 100.0f; /* a sample in the holder */
}

static void test_a_press_waits_for_warm_lamps(void)
{
    fresh_device(true);
    activate_table();
    CHECK_EQ_INT(app_get()->hr[REG_HR_STANDALONE_WARMUP_S], 300);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_WARMUP_REMAINING_S), 300);
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    for (int l = 0; l < HAL_LED_COUNT; l++) CHECK(app_get()->act.led_on[l]); /* the mode switches the lamps on */
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) CHECK(!app_get()->act.shutter_open[s]);
    idle_s(100);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_WARMUP_REMAINING_S), 200);
    light.black = 25.0f, light.white = 250.0f, light.open = 400.0f;
    f->button = true;
    run_ms(60);
    f->button = false;
    idle_s(190); /* pressed 100 s into the warm-up: it waits, busy, nothing moves */
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_STATUS), TRIMETER_STANDALONE_STATUS_BUSY);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_SLOW_BLINK);
    CHECK(!app_get()->motion.homed && !motion_busy(&app_get()->motion));
    CHECK(ir(REG_IR_STANDALONE_WARMUP_REMAINING_S) > 0 && ir(REG_IR_STANDALONE_WARMUP_REMAINING_S) <= 10);
    CHECK_EQ_INT(press(0), TRIMETER_STANDALONE_STATUS_BUSY); /* a second press while it waits: ignored */
    idle_s(12);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_WARMUP_REMAINING_S), 0);
    CHECK(app_get()->motion.homed || motion_busy(&app_get()->motion)); /* warm: the press went on */
    uint16_t status = TRIMETER_STANDALONE_STATUS_BUSY;
    for (int i = 0; i < 120000 && status == TRIMETER_STANDALONE_STATUS_BUSY; i++) {
        run_ms(1);
        status = ir(REG_IR_STANDALONE_STATUS);
    }
    CHECK_EQ_INT(status, TRIMETER_STANDALONE_STATUS_CALIBRATED);

    /* a lamp switched off by a host starts the warm-up again: the next press waits for it */
    uint8_t off = 0;
    CHECK_EQ_INT(app_write_bits(NULL, REG_COIL_LED_COLLIMATED_ON, 1, &off), MB_OK);
    run_ms(2);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_WARMUP_REMAINING_S), 300);
    f->button = true;
    run_ms(60);
    f->button = false;
    idle_s(5);
    CHECK(app_get()->act.led_on[HAL_LED_COLLIMATED]); /* the press switched it on again */
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_STATUS), TRIMETER_STANDALONE_STATUS_BUSY);
    CHECK(ir(REG_IR_STANDALONE_WARMUP_REMAINING_S) >= 294);
}

static void test_a_lamp_changed_since_the_calibration_flags_the_result(void)
{
    calibrated_device(true);
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_DONE); /* unchanged lamps */
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_LAMP_PANEL_LEFT) - 1.0f) < 1e-3f);
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_LAMP_COLLIMATED) - 1.0f) < 1e-3f);

    emission[HAL_LED_PANEL_LEFT] = emission[HAL_LED_PANEL_RIGHT] = 0.97f; /* the panels dimmed by 3 % */
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_LAMP_CHANGED);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_DOUBLE_BLINK);
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_LAMP_PANEL_RIGHT) - 0.97f) < 1e-3f);
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_LAMP_COLLIMATED) - 1.0f) < 1e-3f);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_FLAGGED_BINS), 0); /* the bins fitted; the lamps make it unreliable */
    CHECK(ir(REG_IR_STANDALONE_BINS) == STANDALONE_BINS && !isnan(result_f32(20, TRIMETER_STANDALONE_WORD_ALPHA)));

    emission[HAL_LED_PANEL_LEFT] = emission[HAL_LED_PANEL_RIGHT] = 0.99f; /* within the tolerance */
    emission[HAL_LED_COLLIMATED] = 1.015f;
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_DONE);
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_LAMP_COLLIMATED) - 1.015f) < 1e-3f);

    emission[HAL_LED_COLLIMATED] = 1.03f; /* brighter counts too: the ratio is off either way */
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_LAMP_CHANGED);

    /* a board without lamp-monitor photodiodes: nothing to compare, nothing flagged (NaN levels) */
    calibrated_device(false);
    emission[HAL_LED_COLLIMATED] = 0.9f;
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_DONE);
    CHECK(isnan(ir_f32(REG_IR_STANDALONE_LAMP_COLLIMATED)));
}

/* Captures straight into a standalone_t, 1 ms each: white and open 1000 + p counts above the dark, black
 * `black` counts, the open slot's beam scaled by `beam`; the first UNLIT_PIXELS dark in every set-up. */
static void references(standalone_t *s, unsigned black, float beam)
{
    for (int k = 0; k < STANDALONE_SETUPS; k++) {
        s->integration_us[k] = 1000;
        for (unsigned p = 0; p < C12880_PIXELS; p++) {
            float v = k == STANDALONE_BLACK ? (float)black : (float)(1000u + p) * (k == STANDALONE_OPEN ? beam : 1.0f);
            s->dark[k][p] = 16u * DARK_COUNTS;
            s->light[k][p] = (uint16_t)(16.0f * ((float)DARK_COUNTS + (p < UNLIT_PIXELS ? 0.0f : v)));
        }
    }
}

static void test_a_flagged_lit_bin_flags_the_result(void)
{
    static standalone_t s;
    standalone_init(&s);
    static const float wl[C12880_WL_COEFFS] = {300.0f, 2.0f, 0, 0, 0, 0};
    references(&s, 50u, 1.0f);
    s.light[STANDALONE_WHITE][100] = 16u * C12880_ADC_FULL_SCALE; /* saturated in the calibration */
    standalone_reduce(&s, wl);
    /* a bin is its pair's mean rate: pixels 20, 21 at 1020, 1021 counts in 1 ms */
    CHECK(near(regmap_get_f32(&s.words[10 * TRIMETER_STANDALONE_WORD_STRIDE + TRIMETER_STANDALONE_WORD_WHITE]),
               1020.5e3f, 1e-5f));
    CHECK(near(regmap_get_f32(&s.words[10 * TRIMETER_STANDALONE_WORD_STRIDE + TRIMETER_STANDALONE_WORD_WAVELENGTH_NM]),
               300.0f + 2.0f * 21.5f, 1e-5f));
    CHECK(standalone_calibrate(&s, 0.99f, true));
    CHECK(s.calibration_saturated[50] && !s.lit[50] && s.lit[60] && !s.lit[0]);
    s.light[STANDALONE_WHITE][100] = s.light[STANDALONE_WHITE][99];
    standalone_reduce(&s, wl);
    static uint16_t in[STANDALONE_BINS * TRIMETER_FIT_INPUT_WORD_STRIDE], out[STANDALONE_BINS * TRIMETER_FIT_OUTPUT_WORD_STRIDE];
    CHECK_EQ_INT(standalone_fit_input(&s, in), STANDALONE_BINS);
    CHECK(isnan(regmap_get_f32(&in[50 * TRIMETER_FIT_INPUT_WORD_STRIDE + TRIMETER_FIT_INPUT_WORD_I_B])));
    CHECK(near(regmap_get_f32(&in[60 * TRIMETER_FIT_INPUT_WORD_STRIDE + TRIMETER_FIT_INPUT_WORD_I_W]), 0.99f, 1e-5f));
    memset(out, 0, sizeof out);
    standalone_take_fit(&s, out, STANDALONE_BINS);
    CHECK_EQ_INT(s.status, TRIMETER_STANDALONE_STATUS_FLAGGED); /* the calibration's saturated bin */
    CHECK_EQ_INT(s.flagged_bins, 1);
    CHECK_EQ_INT(s.words[50 * TRIMETER_STANDALONE_WORD_STRIDE + TRIMETER_STANDALONE_WORD_CAPTURE_FLAGS],
                 STANDALONE_CAPTURE_SATURATED);
    CHECK(standalone_calibrate(&s, 0.99f, true)); /* a clean calibration, agreeing with the first */
    standalone_fit_input(&s, in);
    out[0 * TRIMETER_FIT_OUTPUT_WORD_STRIDE + TRIMETER_FIT_OUTPUT_WORD_FLAGS] = TM_FLAG_NONFINITE_INPUT; /* unlit bin */
    standalone_take_fit(&s, out, STANDALONE_BINS);
    CHECK_EQ_INT(s.status, TRIMETER_STANDALONE_STATUS_DONE);
    out[70 * TRIMETER_FIT_OUTPUT_WORD_STRIDE + TRIMETER_FIT_OUTPUT_WORD_FLAGS] = 0x10u; /* a lit bin's fit flag */
    standalone_take_fit(&s, out, STANDALONE_BINS);
    CHECK_EQ_INT(s.status, TRIMETER_STANDALONE_STATUS_FLAGGED);
    CHECK_EQ_INT(standalone_pattern(TRIMETER_STANDALONE_STATUS_FLAGGED), TRIMETER_STATUS_PATTERN_DOUBLE_BLINK);
    CHECK_EQ_INT(standalone_pattern(TRIMETER_STANDALONE_STATUS_ERROR_FIT), TRIMETER_STATUS_PATTERN_FAST_BLINK);
}

/* The empty-holder check of a calibration press, on the captures alone: each refusal keeps the calibration. */
static void test_a_calibration_checks_for_an_empty_holder(void)
{
    static standalone_t s;
    static const float wl[C12880_WL_COEFFS] = {300.0f, 2.0f, 0, 0, 0, 0};
    standalone_init(&s);
    CHECK(isnan(s.check_value) && s.check == TRIMETER_STANDALONE_CHECK_NONE);

    references(&s, 400u, 1.0f); /* a sample in the holder: its own I_b/I_w ~ 0.3 on the black slot */
    standalone_reduce(&s, wl);
    CHECK(!standalone_calibrate(&s, 0.99f, true));
    CHECK_EQ_INT(s.status, TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED);
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_HOLDER_NOT_EMPTY);
    CHECK(s.check_value > 0.25f && s.check_value < 0.45f);
    CHECK(!s.calibrated);
    CHECK(isnan(regmap_get_f32(&s.words[20 * TRIMETER_STANDALONE_WORD_STRIDE + TRIMETER_STANDALONE_WORD_DIFFUSE])));
    CHECK_EQ_INT(standalone_pattern(s.status), TRIMETER_STATUS_PATTERN_TRIPLE_BLINK);

    references(&s, 1500u, 1.0f); /* black brighter than white: the slots are swapped */
    standalone_reduce(&s, wl);
    CHECK(!standalone_calibrate(&s, 0.99f, true));
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_SLOTS_SWAPPED);

    references(&s, 30u, 1.0f);
    for (unsigned p = 0; p < 200; p++) s.light[STANDALONE_WHITE][p] = 16u * DARK_COUNTS; /* most bins without panels */
    standalone_reduce(&s, wl);
    CHECK(!standalone_calibrate(&s, 0.99f, true));
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_LITTLE_LIGHT);
    CHECK(s.check_value < 0.5f);

    references(&s, 30u, 1.0f); /* the empty holder: rho_black ~ 0.02, accepted */
    standalone_reduce(&s, wl);
    CHECK(standalone_calibrate(&s, 0.99f, true));
    CHECK_EQ_INT(s.status, TRIMETER_STANDALONE_STATUS_CALIBRATED);
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_NONE);
    CHECK(s.check_value > 0.01f && s.check_value < 0.05f);
    float diffuse = s.diffuse[60];

    /* against the kept calibration: a clear sample raises rho_black within the empty-holder bound */
    references(&s, 100u, 1.0f);
    standalone_reduce(&s, wl);
    CHECK(!standalone_calibrate(&s, 0.99f, true));
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_RHO_BLACK_CHANGED);
    CHECK(s.check_value > 0.03f && s.check_value < 0.1f);
    CHECK(s.calibrated && s.diffuse[60] == diffuse); /* the kept calibration still holds, and the file shows it */
    CHECK(regmap_get_f32(&s.words[60 * TRIMETER_STANDALONE_WORD_STRIDE + TRIMETER_STANDALONE_WORD_DIFFUSE]) == diffuse);

    references(&s, 30u, 0.8f); /* something in the beam only */
    standalone_reduce(&s, wl);
    CHECK(!standalone_calibrate(&s, 0.99f, true));
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_BEAM_CHANGED);
    CHECK(fabsf(s.check_value - 0.8f) < 0.01f);
    /* ... unless its LED's own photodiode saw it dim as much: an aged LED, no sample */
    s.lamp_span[HAL_LED_COLLIMATED] = 1000.0f;
    s.lamp_dark[HAL_LED_COLLIMATED] = 50u, s.lamp_lit[HAL_LED_COLLIMATED] = 850u;
    CHECK(standalone_calibrate(&s, 0.99f, true));

    /* the operator's word (standalone_mode calibrate_force): the kept calibration is not compared */
    references(&s, 100u, 1.0f);
    standalone_reduce(&s, wl);
    CHECK(standalone_calibrate(&s, 0.99f, false));
    CHECK_EQ_INT(s.check, TRIMETER_STANDALONE_CHECK_NONE);
}

/* Through the app: a refused press keeps the mode (the next press calibrates again) and says why. */
static void test_a_refused_calibration_press(void)
{
    fresh_device(true);
    activate_table();
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_WARMUP_S, 0), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    light.black = 80.0f, light.white = 200.0f, light.open = 100.0f; /* a sample left in the holder */
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_CHECK), TRIMETER_STANDALONE_CHECK_HOLDER_NOT_EMPTY);
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_CHECK_VALUE) - 80.0f * 0.99f / 200.0f) < 1e-3f);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_CALIBRATED), 0);
    CHECK_EQ_INT(app_get()->act.pattern, STATUS_TRIPLE_BLINK);
    CHECK_EQ_INT(app_get()->hr[REG_HR_STANDALONE_MODE], TRIMETER_STANDALONE_MODE_CALIBRATE);
    light.black = 25.0f, light.white = 250.0f, light.open = 400.0f; /* emptied */
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_CALIBRATED);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_CHECK), TRIMETER_STANDALONE_CHECK_NONE);
    CHECK_EQ_INT(app_get()->hr[REG_HR_STANDALONE_MODE], TRIMETER_STANDALONE_MODE_MEASURE);

    /* a replaced collimated LED on a board without photodiodes: refused, then forced */
    monitor_missing = true;
    light.open = 280.0f;
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE), MB_OK);
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED);
    CHECK_EQ_INT(ir(REG_IR_STANDALONE_CHECK), TRIMETER_STANDALONE_CHECK_BEAM_CHANGED);
    CHECK(fabsf(ir_f32(REG_IR_STANDALONE_CHECK_VALUE) - 0.7f) < 0.01f);
    CHECK(near(result_f32(20, TRIMETER_STANDALONE_WORD_COLLIMATED), 400e3f, 1e-3f)); /* the kept one */
    CHECK_EQ_INT(write_reg(REG_HR_STANDALONE_MODE, TRIMETER_STANDALONE_MODE_CALIBRATE_FORCE), MB_OK);
    CHECK_EQ_INT(press(120000), TRIMETER_STANDALONE_STATUS_CALIBRATED);
    CHECK(near(result_f32(20, TRIMETER_STANDALONE_WORD_COLLIMATED), 280e3f, 1e-3f));
    CHECK_EQ_INT(app_get()->hr[REG_HR_STANDALONE_MODE], TRIMETER_STANDALONE_MODE_MEASURE);
}

int main(void)
{
    RUN_TEST(test_mode_off_leaves_presses_to_the_host);
    RUN_TEST(test_refusals);
    RUN_TEST(test_calibration_then_measurement);
    RUN_TEST(test_a_press_waits_for_warm_lamps);
    RUN_TEST(test_a_lamp_changed_since_the_calibration_flags_the_result);
    RUN_TEST(test_a_flagged_lit_bin_flags_the_result);
    RUN_TEST(test_a_calibration_checks_for_an_empty_holder);
    RUN_TEST(test_a_refused_calibration_press);
    fixture_free_hal();
    return CHECK_SUMMARY();
}
