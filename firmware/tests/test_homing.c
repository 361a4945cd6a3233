/* Homing: endstop found and backed off, timeouts, stall detection, endstop hit outside homing. */
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
        .homing_timeout_ms = 20000,
        .max_travel_steps = 12000,
        .backoff_steps = 160,
        .soft_min_steps = 200,
        .soft_max_steps = 11000,
        .stall_tolerance_steps = 40,
    };
}

/* A fresh, unhomed motion with the carriage at `carriage` steps (endstop at <= 0). */
static void setup(int32_t carriage)
{
    motion_config_t cfg = config();
    if (f) fake_hal_free(f);
    f = fake_hal_new();
    f->carriage_steps = carriage;
    f->endstop_steps = 0;
    f->hard_stop_steps = -20;
    motion_init(&m, &f->hal, &cfg);
}

/* Runs in 10 ms slices, calling motion_poll as the app's main loop would. */
static void run(uint64_t limit_us)
{
    uint64_t end = f->now_us + limit_us;
    while (f->timer_running && f->now_us < end) {
        fake_hal_run_until(f, f->now_us + 10000, isr, &m);
        motion_poll(&m, (uint32_t)f->now_us);
    }
}

static void test_homing_finds_endstop_and_backs_off(void)
{
    setup(5000);
    CHECK_EQ_INT(motion_home(&m), MOTION_OK);
    CHECK(motion_busy(&m)); /* returns at once */
    run(30000000);
    CHECK(!motion_busy(&m));
    CHECK_EQ_INT(m.fault, MOTION_FAULT_NONE);
    CHECK(m.homed);
    CHECK_EQ_INT(m.position, 160);        /* zero at the trigger, then the back-off */
    CHECK_EQ_INT(f->carriage_steps, 160); /* and that's where the carriage really is */
    CHECK(!f->hal.endstop_active(f));
    /* Seek speed: 5000 steps at 800 steps/s ≈ 6.25 s of simulated time. */
    CHECK(f->now_us > 6250000 && f->now_us < 6700000);
}

static void test_homing_when_already_on_endstop(void)
{
    setup(-3); /* switch pressed at power-on */
    CHECK_EQ_INT(motion_home(&m), MOTION_OK);
    run(5000000);
    CHECK(m.homed);
    CHECK_EQ_INT(m.position, 160);
    CHECK_EQ_INT(f->carriage_steps, 157); /* the position is relative to where the switch trips */
}

static void test_homing_timeout_by_time(void)
{
    setup(5000);
    f->endstop_broken = true;
    motion_config_t cfg = config();
    cfg.homing_timeout_ms = 2000; /* < 12000 steps / 800 sps = 15 s: the clock fires first */
    CHECK_EQ_INT(motion_configure(&m, &cfg), MOTION_OK);
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(m.state, MOTION_FAULT);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_HOMING_TIMEOUT);
    CHECK(f->now_us >= 2000000 && f->now_us <= 2020000);
    CHECK(!f->timer_running);
    CHECK(!f->enabled); /* driver off after a fault */
    CHECK(!m.homed);
}

static void test_homing_timeout_by_travel(void)
{
    setup(5000);
    f->endstop_broken = true;
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_HOMING_TIMEOUT);
    CHECK_EQ_INT(f->pulses, 12000); /* never more than the maximum travel */
}

static void test_fault_latches_until_cleared(void)
{
    setup(5000);
    f->endstop_broken = true;
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(motion_home(&m), MOTION_ERR_FAULTED);
    CHECK_EQ_INT(motion_move_to(&m, 1000), MOTION_ERR_FAULTED);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_HOMING_TIMEOUT); /* still there */
    motion_clear_fault(&m);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_NONE);
    CHECK_EQ_INT(motion_move_to(&m, 1000), MOTION_ERR_NOT_HOMED); /* must home again */
    f->endstop_broken = false;
    CHECK_EQ_INT(motion_home(&m), MOTION_OK);
    run(30000000);
    CHECK(m.homed);
}

static void test_endstop_hit_outside_homing(void)
{
    setup(5000);
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(motion_move_to(&m, 8000), MOTION_OK);
    run(30000000);
    /* Lose 7900 steps' worth of position: the carriage is really near home, then move towards it. */
    f->carriage_steps = 100;
    CHECK_EQ_INT(motion_move_to(&m, 500), MOTION_OK);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_ENDSTOP_HIT);
    CHECK_EQ_INT(f->carriage_steps, 0); /* stopped on the first pulse that found the switch */
    CHECK(!motion_busy(&m));
}

static void test_stuck_carriage_on_the_endstop_is_a_stall(void)
{
    setup(0);
    f->stuck = true;
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_STALL); /* the back-off never released the switch */
    CHECK(!m.homed);
}

static void test_rehoming_detects_lost_steps(void)
{
    setup(5000);
    motion_home(&m);
    run(30000000);
    motion_move_to(&m, 6000);
    run(30000000);
    CHECK_EQ_INT(f->carriage_steps, 6000);
    f->carriage_steps = 3000; /* jammed earlier: 3000 steps lost */
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_STALL);
    /* within tolerance it's fine */
    motion_clear_fault(&m);
    motion_home(&m);
    run(30000000);
    CHECK(m.homed);
    motion_move_to(&m, 6000);
    run(30000000);
    f->carriage_steps += 30; /* 30 < 40 steps of tolerance */
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_NONE);
    CHECK(m.homed);
}

static void test_driver_stall_output_catches_a_jam_mid_travel(void)
{
    setup(5000);
    motion_home(&m);
    run(30000000);
    CHECK_EQ_INT(motion_move_to(&m, 6000), MOTION_OK);
    run(30000000);
    /* without a stall output a jam between slots goes unnoticed ... */
    f->stuck = true;
    CHECK_EQ_INT(motion_move_to(&m, 8000), MOTION_OK);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_NONE);
    CHECK_EQ_INT(f->carriage_steps, 6000);
    /* ... with one, the first pulse after the jam stops the move */
    f->has_stall_output = true;
    uint32_t pulses = f->pulses;
    CHECK_EQ_INT(motion_move_to(&m, 9000), MOTION_OK);
    run(30000000);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_STALL);
    CHECK(f->pulses - pulses <= 1); /* at the latest on the first pulse after the jam */
    CHECK(!m.homed);
}

static void test_stop_during_homing_leaves_unhomed(void)
{
    setup(5000);
    motion_home(&m);
    fake_hal_run_until(f, 1000000, isr, &m);
    motion_stop(&m);
    CHECK(!motion_busy(&m));
    CHECK(!m.homed);
    CHECK_EQ_INT(m.fault, MOTION_FAULT_NONE);
}

int main(void)
{
    RUN_TEST(test_homing_finds_endstop_and_backs_off);
    RUN_TEST(test_homing_when_already_on_endstop);
    RUN_TEST(test_homing_timeout_by_time);
    RUN_TEST(test_homing_timeout_by_travel);
    RUN_TEST(test_fault_latches_until_cleared);
    RUN_TEST(test_endstop_hit_outside_homing);
    RUN_TEST(test_stuck_carriage_on_the_endstop_is_a_stall);
    RUN_TEST(test_rehoming_detects_lost_steps);
    RUN_TEST(test_driver_stall_output_catches_a_jam_mid_travel);
    RUN_TEST(test_stop_during_homing_leaves_unhomed);
    fake_hal_free(f);
    return CHECK_SUMMARY();
}
