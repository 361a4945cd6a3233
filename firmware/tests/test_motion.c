/* The trapezoid: ramp / cruise / ramp timing against the analytic profile, exact step counts,
 * short moves that never reach cruise speed. */
#include <math.h>
#include <stdlib.h>

#include "../core/motion.h"
#include "check.h"
#include "fake_hal.h"

static fake_hal_t *f;
static motion_t m;

static uint32_t isr(void *ctx) { return motion_isr(ctx); }

static motion_config_t config(void)
{
    return (motion_config_t){
        .max_speed_sps = 4000,
        .accel_sps2 = 20000,
        .homing_speed_sps = 800,
        .homing_timeout_ms = 30000,
        .max_travel_steps = 100000,
        .backoff_steps = 160,
        .soft_min_steps = 160,
        .soft_max_steps = 90000,
        .stall_tolerance_steps = 40,
    };
}

/* A homed motion at `pos` steps, with the carriage really there, and pulse recording on. */
static void setup_at(int32_t pos, motion_config_t cfg)
{
    if (f) fake_hal_free(f);
    f = fake_hal_new();
    f->endstop_steps = -1000000; /* far away: these tests don't touch the endstop */
    motion_init(&m, &f->hal, &cfg);
    m.position = pos;
    m.homed = true;
    f->carriage_steps = pos;
    f->record_pulses = true;
}

/* Analytic pulse time of pulse k (1-based) for an N-step move, in seconds. */
static double ideal_time(uint32_t k, uint32_t n, double v, double a)
{
    double na = floor(v * v / (2 * a));
    if (na > n / 2) na = n / 2;
    double t_ramp = sqrt(2 * na / a);
    double t_end = 2 * t_ramp + (n - 2 * na) / v;
    if (k <= na) return sqrt(2.0 * k / a);
    if (k <= n - na) return t_ramp + (k - na) / v;
    return t_end - sqrt(2.0 * (n - k) / a);
}

static void check_move(uint32_t n)
{
    motion_config_t cfg = config();
    setup_at(1000, cfg);
    uint64_t t0 = f->now_us;
    CHECK_EQ_INT(motion_move_to(&m, 1000 + (int32_t)n), MOTION_OK);
    CHECK(motion_busy(&m));
    CHECK(fake_hal_run_idle(f, 60000000, isr, &m));
    CHECK(!motion_busy(&m));
    CHECK_EQ_INT(f->pulses, n);                  /* exact step count */
    CHECK_EQ_INT(m.position, 1000 + (int32_t)n);
    CHECK_EQ_INT(f->carriage_steps, 1000 + (int32_t)n);
    /* Every pulse within 1 µs of the ideal (integer µs rounding only, never accumulating). */
    double worst = 0;
    for (uint32_t k = 1; k <= n; k++) {
        double err = fabs((double)(f->pulse_times_us[k - 1] - t0) - 1e6 * ideal_time(k, n, cfg.max_speed_sps, cfg.accel_sps2));
        if (err > worst) worst = err;
    }
    CHECK(worst <= 1.0);
    if (worst > 1.0) fprintf(stderr, "  N=%u worst pulse-time error %.2f us\n", n, worst);
}

static void test_long_move_has_ramp_cruise_ramp(void)
{
    /* v²/2a = 400 steps of ramp at each end, 4200 steps of cruise. */
    check_move(5000);
    uint64_t *t = f->pulse_times_us;
    uint64_t t0 = f->pulse_times_us[0] - motion_profile_time_us(&m, 1); /* the move's start */
    /* ramp: intervals shrink */
    CHECK(t[1] - t[0] > t[399] - t[398]);
    CHECK(t[10] - t[9] > t[11] - t[10]);
    /* cruise: 1/4000 s = 250 µs (±1 µs of rounding) */
    for (int k = 450; k < 4500; k += 97) CHECK(llabs((long long)(t[k + 1] - t[k]) - 250) <= 1);
    /* decel mirrors the ramp */
    CHECK(t[4999] - t[4998] > t[4600] - t[4599]);
    CHECK(llabs((long long)(t[4999] - t[4998]) - (long long)(t[0] - t0)) <= 2);
    CHECK(llabs((long long)(t[4998] - t[4997]) - (long long)(t[1] - t[0])) <= 2);
    /* total time: 2·v/a + (N − v²/a)/v = 2·0.2 + 1.05 s */
    CHECK(llabs((long long)(t[4999] - t0) - 1450000) <= 1);
}

static void test_short_move_never_reaches_cruise(void)
{
    check_move(300); /* < 2·400: a triangle */
    uint64_t *t = f->pulse_times_us;
    uint64_t shortest = UINT64_MAX;
    for (int k = 0; k < 299; k++)
        if (t[k + 1] - t[k] < shortest) shortest = t[k + 1] - t[k];
    CHECK(shortest > 250); /* never as fast as cruise */
    /* peak is in the middle: interval at 150 shorter than at 50 and at 250 */
    CHECK(t[150] - t[149] < t[50] - t[49]);
    CHECK(t[150] - t[149] < t[250] - t[249]);
}

static void test_tiny_moves(void)
{
    check_move(1);
    check_move(2);
    check_move(3);
    check_move(801); /* exactly ramp + 1 + ramp */
}

static void test_move_back_and_direction(void)
{
    setup_at(5000, config());
    CHECK_EQ_INT(motion_move_to(&m, 2000), MOTION_OK);
    CHECK(!f->dir_away);
    CHECK(fake_hal_run_idle(f, 60000000, isr, &m));
    CHECK_EQ_INT(m.position, 2000);
    CHECK_EQ_INT(f->carriage_steps, 2000);
}

/* A smooth stop ramps down at the configured deceleration from wherever the move is. */
static void check_smooth_stop(uint64_t after_us, bool cruising)
{
    setup_at(1000, config());
    uint64_t t0 = f->now_us;
    CHECK_EQ_INT(motion_move_to(&m, 9000), MOTION_OK);
    fake_hal_run_until(f, t0 + after_us, isr, &m);
    uint32_t at_stop = f->pulses;
    motion_stop_smooth(&m);
    CHECK(motion_busy(&m)); /* still ramping down */
    CHECK(fake_hal_run_idle(f, 10000000, isr, &m));
    uint32_t extra = f->pulses - at_stop;
    /* The request is seen at the pulse in flight (k = at_stop + 1); ramping down from there takes
     * as many steps as reaching that speed took: min(k, v²/2a = 400). */
    uint32_t k = at_stop + 1;
    CHECK_EQ_INT(extra, 1 + (k < 400 ? k : 400));
    CHECK(cruising == (k > 400));
    CHECK_EQ_INT(m.position, 1000 + (int32_t)f->pulses); /* every pulse counted */
    CHECK(m.homed);
    /* the last intervals grow (deceleration), the very last one is the first ramp step's */
    uint64_t *t = f->pulse_times_us;
    uint32_t n = f->pulses;
    CHECK(t[n - 1] - t[n - 2] > t[n - 2] - t[n - 3]);
    CHECK(llabs((long long)(t[n - 1] - t[n - 2]) - (long long)motion_profile_time_us(&m, 1)) <= 2);
}

static void test_smooth_stop(void)
{
    check_smooth_stop(500000, true);  /* cruising */
    check_smooth_stop(100000, false); /* still accelerating, ~100 steps in */
}

static void test_commands_refused(void)
{
    setup_at(1000, config());
    CHECK_EQ_INT(motion_move_to(&m, 100), MOTION_ERR_LIMIT);   /* below soft min */
    CHECK_EQ_INT(motion_move_to(&m, 90001), MOTION_ERR_LIMIT); /* above soft max */
    CHECK_EQ_INT(motion_move_to(&m, 1000), MOTION_OK);         /* no-op */
    CHECK(!motion_busy(&m));
    CHECK_EQ_INT(motion_move_to(&m, 3000), MOTION_OK);
    CHECK_EQ_INT(motion_move_to(&m, 4000), MOTION_ERR_BUSY); /* returns at once, refused */
    CHECK_EQ_INT(motion_home(&m), MOTION_ERR_BUSY);
    motion_stop(&m);
    CHECK(!motion_busy(&m));
    CHECK(!f->timer_running);
    m.homed = false;
    CHECK_EQ_INT(motion_move_to(&m, 3000), MOTION_ERR_NOT_HOMED);
}

static void test_config_validation(void)
{
    motion_config_t c = config();
    CHECK_EQ_INT(motion_config_valid(&c), MOTION_OK);
    c.accel_sps2 = 0;
    CHECK_EQ_INT(motion_config_valid(&c), MOTION_ERR_CONFIG);
    c = config();
    c.max_speed_sps = 60000; /* faster than the 20 µs floor */
    CHECK_EQ_INT(motion_config_valid(&c), MOTION_ERR_CONFIG);
    c = config();
    c.soft_min_steps = 10; /* inside the back-off: the endstop could be hit by a normal move */
    CHECK_EQ_INT(motion_config_valid(&c), MOTION_ERR_CONFIG);
    c = config();
    c.soft_max_steps = 200000;
    CHECK_EQ_INT(motion_config_valid(&c), MOTION_ERR_CONFIG);
    setup_at(1000, config());
    c = config();
    c.accel_sps2 = 0;
    CHECK_EQ_INT(motion_configure(&m, &c), MOTION_ERR_CONFIG);
    CHECK_EQ_INT(m.cfg.accel_sps2, 20000); /* nothing changed */
}

int main(void)
{
    RUN_TEST(test_long_move_has_ramp_cruise_ramp);
    RUN_TEST(test_short_move_never_reaches_cruise);
    RUN_TEST(test_tiny_moves);
    RUN_TEST(test_move_back_and_direction);
    RUN_TEST(test_smooth_stop);
    RUN_TEST(test_commands_refused);
    RUN_TEST(test_config_validation);
    fake_hal_free(f);
    return CHECK_SUMMARY();
}
