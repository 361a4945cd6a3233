/* The STM32F405 port's microsecond clock (ports/stm32f405/timebase.h) against a fake SysTick: a
 * 168 MHz core clock, a counter that wraps every millisecond and pends the SysTick exception, and a
 * handler that runs between two register reads when the caller is thread code, or not at all when
 * the caller is an ISR above SysTick. Every start time around a wrap and every read cost is tried;
 * the reading must lie between the true times at the call's entry and exit. */
#include <stdbool.h>
#include <stdint.h>

#include "check.h"
#include "timebase.h"

#define TICKS_PER_MS 168000u
#define TICKS_PER_US (TICKS_PER_MS / 1000u)

static struct {
    uint64_t t;           /* true core-clock ticks since boot */
    uint32_t ms_ticks;    /* the handler's count */
    bool pending;         /* a wrap the handler hasn't counted */
    bool handler_can_run; /* thread caller: the handler preempts as soon as it is pending */
    uint32_t read_cost;   /* ticks each register read takes */
} sys;

/* Time passes by one read; a wrap pends the exception; a runnable handler counts it. */
static void advance(void)
{
    uint64_t before = sys.t;
    sys.t += sys.read_cost;
    if (sys.t / TICKS_PER_MS != before / TICKS_PER_MS) sys.pending = true;
    if (sys.pending && sys.handler_can_run) {
        sys.ms_ticks++;
        sys.pending = false;
    }
}

static uint32_t fake_ms_ticks(void)
{
    uint32_t v = sys.ms_ticks;
    advance();
    return v;
}

static uint32_t fake_counter(void)
{
    uint32_t v = TICKS_PER_MS - 1u - (uint32_t)(sys.t % TICKS_PER_MS);
    advance();
    return v;
}

static bool fake_wrap_pending(void)
{
    bool v = sys.pending;
    advance();
    return v;
}

static const systick_source_t fake = {fake_ms_ticks, fake_counter, fake_wrap_pending};

/* Starts at t0 with every earlier wrap counted, except one just before t0 when the caller is an
 * ISR that began after it (the handler held off). */
static void start(uint64_t t0, uint32_t read_cost, bool thread, bool wrap_held_off)
{
    sys.t = t0;
    sys.read_cost = read_cost;
    sys.handler_can_run = thread;
    sys.ms_ticks = (uint32_t)(t0 / TICKS_PER_MS);
    sys.pending = false;
    if (wrap_held_off && !thread && t0 % TICKS_PER_MS < 200u) {
        sys.ms_ticks--;
        sys.pending = true;
    }
}

static int check_window(uint64_t t0, uint32_t read_cost, bool thread, bool wrap_held_off)
{
    start(t0, read_cost, thread, wrap_held_off);
    uint64_t entry_us = sys.t / TICKS_PER_US;
    uint32_t us = systick_now_us(&fake, TICKS_PER_MS);
    uint64_t exit_us = sys.t / TICKS_PER_US;
    return (uint64_t)us >= entry_us && (uint64_t)us <= exit_us;
}

static void test_every_start_around_a_wrap(void)
{
    const uint64_t wrap = 5ull * TICKS_PER_MS;
    int bad = 0, runs = 0;
    for (uint64_t t0 = wrap - 120u; t0 < wrap + 120u; t0++)
        for (uint32_t cost = 1; cost <= 24; cost++)
            for (int ctx = 0; ctx < 3; ctx++) {
                bad += !check_window(t0, cost, ctx == 0, ctx == 2);
                runs++;
            }
    CHECK_EQ_INT(bad, 0);
    CHECK(runs > 10000);
}

static void test_consecutive_readings_from_an_isr_never_go_back(void)
{
    /* an ISR above SysTick reads the clock again and again across a wrap it holds off */
    start(7ull * TICKS_PER_MS - 500u, 13, false, false);
    uint32_t last = systick_now_us(&fake, TICKS_PER_MS);
    int backwards = 0;
    for (int i = 0; i < 200; i++) {
        uint32_t us = systick_now_us(&fake, TICKS_PER_MS);
        backwards += us < last;
        last = us;
    }
    CHECK(sys.pending); /* the wrap happened and was never counted by the handler */
    CHECK_EQ_INT(backwards, 0);
    CHECK_EQ_INT(last / 1000u, 7u);
}

static void test_the_32_bit_wrap_after_71_minutes(void)
{
    /* 2^32 µs: the reading wraps like the core expects (it only subtracts readings) */
    uint64_t t0 = (1ull << 32) * TICKS_PER_US - 10u * TICKS_PER_US;
    start(t0, 5, true, false);
    uint32_t before = systick_now_us(&fake, TICKS_PER_MS);
    start(t0 + 20u * TICKS_PER_US, 5, true, false);
    uint32_t after = systick_now_us(&fake, TICKS_PER_MS);
    CHECK(after < before); /* it did wrap */
    CHECK(after - before >= 19u && after - before <= 21u);
}

int main(void)
{
    RUN_TEST(test_every_start_around_a_wrap);
    RUN_TEST(test_consecutive_readings_from_an_isr_never_go_back);
    RUN_TEST(test_the_32_bit_wrap_after_71_minutes);
    return CHECK_SUMMARY();
}
