/* The lamp monitor: photodiode samples taken once per period from the main loop, averaged, and
 * served as the lamp_monitor_* input registers; a board without a monitor reads 0. */
#include "../core/app.h"
#include "../core/lamp_monitor.h"
#include "app_fixture.h"
#include "check.h"
#include "fake_hal.h"

static fake_hal_t *f;

static void set_lamps(uint16_t left, uint16_t right, uint16_t collimated)
{
    f->lamp_adc[HAL_LED_PANEL_LEFT] = left;
    f->lamp_adc[HAL_LED_PANEL_RIGHT] = right;
    f->lamp_adc[HAL_LED_COLLIMATED] = collimated;
}

static void test_registers_follow_each_photodiode(void)
{
    set_lamps(3000, 2500, 40);
    fixture_boot();
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_LEFT), 3000); /* the first sample fills the average */
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_RIGHT), 2500);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_COLLIMATED), 40);
    set_lamps(1500, 2500, 3900); /* left dims to half, the collimated shutter opens */
    run_ms(2);
    uint16_t early = ir(REG_IR_LAMP_MONITOR_PANEL_LEFT);
    CHECK(early < 3000 && early > 2500); /* averaged: a step shows gradually */
    run_ms(200);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_LEFT), 1500);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_RIGHT), 2500);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_COLLIMATED), 3900);
}

static void test_one_sample_per_period(void)
{
    app_init(&f->hal);
    f->lamp_samples = 0;
    run_ms(100);
    /* three photodiodes per period, whatever the loop rate (one period may straddle the start) */
    CHECK(f->lamp_samples >= 3u * 99u && f->lamp_samples <= 3u * 101u);
}

static void test_noise_is_averaged(void)
{
    app_init(&f->hal);
    uint32_t seed = 12345u, lo = 0xFFFF, hi = 0;
    for (int i = 0; i < 2000; i++) {
        /* uniform ±8 counts around 2000 every sample */
        seed = seed * 1664525u + 1013904223u;
        uint16_t v = (uint16_t)(1992u + (seed >> 28));
        set_lamps(v, v, v);
        run_ms(1);
        if (i < 100) continue;
        uint16_t r = ir(REG_IR_LAMP_MONITOR_PANEL_LEFT);
        if (r < lo) lo = r;
        if (r > hi) hi = r;
    }
    CHECK(lo >= 1995 && hi <= 2006); /* a ±8-count sample noise shrinks to a few counts */
}

static void test_out_of_range_samples_are_clipped(void)
{
    set_lamps(0xFFFF, 0, 4095);
    app_init(&f->hal);
    run_ms(50);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_LEFT), 4095);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_RIGHT), 0);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_COLLIMATED), 4095);
}

static void test_no_monitor_reads_zero(void)
{
    f->hal.lamp_monitor = NULL;
    set_lamps(3000, 3000, 3000);
    app_init(&f->hal);
    run_ms(20);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_PANEL_LEFT), 0);
    CHECK_EQ_INT(ir(REG_IR_LAMP_MONITOR_COLLIMATED), 0);
}

int main(void)
{
    f = fixture_fresh_hal();
    if (!f) return 1;
    fixture_loop_every_us(250); /* the monitor must still sample once per period, not per loop turn */
    RUN_TEST(test_registers_follow_each_photodiode);
    RUN_TEST(test_one_sample_per_period);
    RUN_TEST(test_noise_is_averaged);
    RUN_TEST(test_out_of_range_samples_are_clipped);
    RUN_TEST(test_no_monitor_reads_zero);
    fixture_free_hal();
    return CHECK_SUMMARY();
}
