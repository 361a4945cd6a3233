/* The micro-spectrometer driver: its frame timing against the C12880MA datasheet's limits, the capture
 * through the register map (averaging, dark with the shutters closed, EOS, saturation) and its refusals. */
#include <math.h>
#include <stdlib.h>

#include "../core/app.h"
#include "../core/c12880.h"
#include "../core/regmap.h"
#include "app_fixture.h"
#include "check.h"
#include "fake_hal.h"

/* The datasheet's numbers (KACC1226E pp. 2, 7-8), restated here on purpose: the test checks the driver
 * against them, not against its own constants. */
#define DS_CLOCK_MIN_HZ 200000.0
#define DS_CLOCK_MAX_HZ 5000000.0
#define DS_ST_HIGH_MIN 6u
#define DS_ST_LOW_MIN 375u
#define DS_ST_CYCLE_MIN 381u /* tpi(ST) */
#define DS_INTEGRATION_EXTRA 48u
#define DS_FIRST_VIDEO 89u
#define DS_PIXELS 288u

static fake_hal_t *f;

static void boot(uint32_t clock_hz)
{
    f->spectro_clock_hz = clock_hz;
    f->spectro_no_eos = f->spectro_ramp = false;
    f->spectro_frames = 0;
    f->spectro_running = false;
    fixture_boot();
}


static uint8_t set_integration(uint32_t us)
{
    uint16_t w[2];
    regmap_put_u32(w, us);
    return app_write_regs(NULL, REG_HR_SPECTRO_INTEGRATION_US, 2, w);
}

static void run_until_capture_ends(uint32_t limit_ms)
{
    for (uint32_t i = 0; i < limit_ms && ir(REG_IR_SPECTRO_STATUS) == TRIMETER_SPECTRO_STATUS_BUSY; i++) run_ms(1);
}

/* ---------------------------------------------------------------- timing against the datasheet */

static void check_timing(uint32_t clock_hz, uint32_t integration_us)
{
    hal_spectro_timing_t t;
    CHECK(c12880_plan(clock_hz, integration_us, 1, &t));
    CHECK(clock_hz >= DS_CLOCK_MIN_HZ && clock_hz <= DS_CLOCK_MAX_HZ);
    CHECK(t.st_high_clocks >= DS_ST_HIGH_MIN);
    CHECK(t.st_low_clocks >= DS_ST_LOW_MIN);
    CHECK(t.st_high_clocks + t.st_low_clocks >= DS_ST_CYCLE_MIN);
    CHECK_EQ_INT(t.pixels, DS_PIXELS);
    CHECK_EQ_INT(t.first_video_clock, DS_FIRST_VIDEO);
    CHECK_EQ_INT(t.eos_clock, DS_FIRST_VIDEO + DS_PIXELS); /* EOS right after the last pixel */
    CHECK(t.st_low_clocks > t.eos_clock);                  /* ST stays low until EOS was seen */
    /* the integration time is ST high + 48 CLK, within half a CLK period of the request */
    double got_us = (t.st_high_clocks + DS_INTEGRATION_EXTRA) * 1e6 / clock_hz;
    CHECK(fabs(got_us - integration_us) <= 0.5e6 / clock_hz + 1e-9);
}

static void test_timing_within_datasheet_limits(void)
{
    static const uint32_t clocks[] = {200000u, 500000u, 1000000u, 5000000u};
    static const uint32_t times[] = {11u, 108u, 1000u, 10000u, 123457u, 1000000u};
    for (size_t c = 0; c < sizeof clocks / sizeof *clocks; c++)
        for (size_t i = 0; i < sizeof times / sizeof *times; i++) {
            /* the shortest integration a clock allows: (6 + 48) CLK periods */
            double min_us = (DS_ST_HIGH_MIN + DS_INTEGRATION_EXTRA) * 1e6 / clocks[c];
            hal_spectro_timing_t t;
            if (times[i] + 0.5e6 / clocks[c] < min_us) CHECK(!c12880_plan(clocks[c], times[i], 1, &t));
            else check_timing(clocks[c], times[i]);
        }
}

static void test_plan_refuses_clock_out_of_range(void)
{
    hal_spectro_timing_t t;
    CHECK(!c12880_plan(199999u, 10000u, 1, &t));
    CHECK(!c12880_plan(5000001u, 10000u, 1, &t));
    CHECK(!c12880_plan(0u, 10000u, 1, &t));
    CHECK(c12880_plan(500000u, 108u, 1, &t)); /* exactly 54 CLK */
    CHECK_EQ_INT(t.st_high_clocks, DS_ST_HIGH_MIN);
    CHECK(!c12880_plan(500000u, 106u, 1, &t)); /* 53 CLK: ST high 5 < 6 */
}

static void test_port_sees_the_planned_timing(void)
{
    boot(500000u);
    CHECK_EQ_INT(set_integration(2000u), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_FRAMES, 3), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_OK);
    run_until_capture_ends(200);
    CHECK_EQ_INT(f->spectro_frames, 3);
    CHECK_EQ_INT(f->spectro_timing.st_high_clocks, 1000u - DS_INTEGRATION_EXTRA);
    CHECK(f->spectro_timing.st_low_clocks >= DS_ST_LOW_MIN);
    CHECK_EQ_INT(f->spectro_timing.pixels, DS_PIXELS);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_PIXELS), DS_PIXELS);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_CLOCK_HZ + 1), 500000u & 0xFFFFu);
}

/* ---------------------------------------------------------------- captures */

static void test_frames_are_averaged(void)
{
    boot(500000u);
    for (unsigned p = 0; p < 288; p++) f->spectro_video[p] = (uint16_t)(100 + p);
    f->spectro_ramp = true; /* frame k reads video + k: the mean of 0..3 is 1.5 */
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_FRAMES, 4), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_BUSY);
    uint16_t rec[125];
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_LIGHT, 0, 1, rec), MB_EX_SERVER_DEVICE_BUSY);
    run_until_capture_ends(500);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_DONE);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_FRAMES_DONE), 4);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_SEQUENCE), 1);
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_LIGHT, 0, 125, rec), MB_OK);
    CHECK_EQ_INT(rec[0], (100 * 4 + 6) * 16 / 4);   /* (100 + 1.5) x 16 */
    CHECK_EQ_INT(rec[124], (224 * 4 + 6) * 16 / 4);
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_LIGHT, 250, 38, rec), MB_OK);
    CHECK_EQ_INT(rec[37], (387 * 4 + 6) * 16 / 4);   /* pixel 288 */
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_PEAK_COUNTS), 388); /* floor of 388.5 */
    /* past the 288 pixels: 02; never a dark capture: 01; the spectra are read-only: 02 */
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_LIGHT, 250, 39, rec), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_DARK, 0, 1, rec), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(app_write_file(NULL, TRIMETER_SPECTRO_FILE_LIGHT, 0, 1, rec), MB_EX_ILLEGAL_DATA_ADDRESS);
}

static void test_dark_closes_the_shutters_first(void)
{
    boot(500000u);
    const app_t *a = app_get();
    uint8_t open = 1;
    CHECK_EQ_INT(app_write_bits(NULL, REG_COIL_SHUTTER_COLLIMATED_OPEN, 1, &open), MB_OK);
    run_ms(2000);
    CHECK(a->act.shutter_open[HAL_SHUTTER_COLLIMATED]);
    uint32_t frames_before = f->spectro_frames;
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE_DARK), MB_OK);
    CHECK(!a->act.shutter_open[HAL_SHUTTER_COLLIMATED]);
    run_ms(5);
    CHECK_EQ_INT(f->spectro_frames, frames_before); /* waits for the blades to settle */
    run_until_capture_ends(3000);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_DONE);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_DARK_VALID), 1);
    CHECK(ir(REG_IR_SPECTRO_CAPTURE_US + 1) > 0 || ir(REG_IR_SPECTRO_CAPTURE_US) > 0);
    uint16_t rec;
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_DARK, 0, 1, &rec), MB_OK);
}

static void test_missing_eos_fails_the_capture(void)
{
    boot(500000u);
    f->spectro_no_eos = true;
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_OK);
    run_until_capture_ends(500);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_ERROR_NO_EOS);
    uint16_t rec;
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_SPECTRO_FILE_LIGHT, 0, 1, &rec), MB_EX_SERVER_DEVICE_FAILURE);
}

static void test_saturated_frame_is_flagged(void)
{
    boot(500000u);
    for (unsigned p = 0; p < 288; p++) f->spectro_video[p] = 1000;
    f->spectro_video[140] = 4095;
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_OK);
    run_until_capture_ends(500);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_SATURATED);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_PEAK_COUNTS), 4095);
}

static void test_refusals(void)
{
    boot(500000u);
    CHECK_EQ_INT(set_integration(10u), MB_EX_ILLEGAL_DATA_VALUE);      /* below the register's range */
    CHECK_EQ_INT(set_integration(1000001u), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(set_integration(100u), MB_OK);                        /* in range, but < 54 CLK at 500 kHz */
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_IDLE);
    CHECK_EQ_INT(set_integration(10000u), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_GAIN, 3), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_FRAMES, 0), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_EX_SERVER_DEVICE_BUSY);
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_ABORT), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_ABORTED);
    boot(0u); /* a board without the chip */
    CHECK_EQ_INT(write_reg(REG_HR_SPECTRO_COMMAND, TRIMETER_SPECTRO_COMMAND_CAPTURE), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_STATUS), TRIMETER_SPECTRO_STATUS_ERROR_NO_SENSOR);
    CHECK_EQ_INT(ir(REG_IR_SPECTRO_PIXELS), 0);
}

static uint8_t write_f32(uint16_t addr, float v)
{
    uint16_t w[2];
    regmap_put_f32(w, v);
    return app_write_regs(NULL, addr, 2, w);
}

static void test_wavelength_polynomial(void)
{
    boot(500000u);
    const app_t *a = app_get();
    float lam1 = c12880_wavelength_nm(a->cfg.spectro_wl, 1), lam288 = c12880_wavelength_nm(a->cfg.spectro_wl, 288);
    CHECK(lam1 > 300.0f && lam1 < 340.0f);   /* the defaults: a typical unit covers 340-850 nm and a bit more */
    CHECK(lam288 > 850.0f && lam288 < 900.0f);
    CHECK(c12880_wavelengths_valid(a->cfg.spectro_wl));
    /* a polynomial that turns back (not monotonic) is refused whole */
    CHECK_EQ_INT(write_f32(REG_HR_SPECTRO_WL_B2, -0.02f), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK(a->cfg.spectro_wl[2] == REG_HR_SPECTRO_WL_B2_DEFAULT);
    CHECK_EQ_INT(write_f32(REG_HR_SPECTRO_WL_B1, -2.7f), MB_EX_ILLEGAL_DATA_VALUE); /* decreasing */
    CHECK_EQ_INT(write_f32(REG_HR_SPECTRO_WL_A0, 2000.0f), MB_EX_ILLEGAL_DATA_VALUE); /* out of any C12880's range */
    CHECK_EQ_INT(write_f32(REG_HR_SPECTRO_WL_A0, 310.0f), MB_OK);
    CHECK(fabsf(c12880_wavelength_nm(a->cfg.spectro_wl, 1) - (lam1 + 310.0f - REG_HR_SPECTRO_WL_A0_DEFAULT)) < 1e-3f);
    float flat[C12880_WL_COEFFS] = {500.0f, 0, 0, 0, 0, 0};
    CHECK(!c12880_wavelengths_valid(flat));
    float nan_coeff[C12880_WL_COEFFS] = {NAN, 2.7f, 0, 0, 0, 0};
    CHECK(!c12880_wavelengths_valid(nan_coeff));
}

int main(void)
{
    f = fixture_fresh_hal();
    if (!f) return 2;
    RUN_TEST(test_timing_within_datasheet_limits);
    RUN_TEST(test_plan_refuses_clock_out_of_range);
    RUN_TEST(test_port_sees_the_planned_timing);
    RUN_TEST(test_frames_are_averaged);
    RUN_TEST(test_dark_closes_the_shutters_first);
    RUN_TEST(test_missing_eos_fails_the_capture);
    RUN_TEST(test_saturated_frame_is_flagged);
    RUN_TEST(test_refusals);
    RUN_TEST(test_wavelength_polynomial);
    fixture_free_hal();
    return CHECK_SUMMARY();
}
