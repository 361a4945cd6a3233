/* Microseconds since boot from SysTick: SysTick_Handler counts milliseconds, the 24-bit counter
 * counts down the current one (reload - 1 .. 0). Kept apart from main.c so the host test
 * (firmware/tests/test_stm32_timebase.c) can run it against a fake SysTick.
 *
 * A counter wrap the handler has not counted yet (it can't run while a higher-priority ISR or
 * masked interrupts hold it off) shows as SysTick's pending bit (ICSR.PENDSTSET): then the
 * millisecond count is one short, and the counter must be read again after the wrap. This is the
 * wrap flag to trust: SYST_CSR.COUNTFLAG also marks the wrap but clears when read, so of two
 * readers in one millisecond only the first would see it. Exact unless the handler is held off for
 * more than a millisecond (a second wrap can't be seen), or the caller preempted SysTick_Handler
 * before its one store (no ISR above SysTick calls now_us). */
#ifndef TRIMETER_STM32F405_TIMEBASE_H
#define TRIMETER_STM32F405_TIMEBASE_H

#include <stdbool.h>
#include <stdint.h>

typedef struct {
    uint32_t (*ms_ticks)(void);   /* the handler's count */
    uint32_t (*counter)(void);    /* SYST_CVR */
    bool (*wrap_pending)(void);   /* SCB_ICSR & PENDSTSET */
} systick_source_t;

/* ticks_per_ms: SYST_RVR + 1, a multiple of 1000 */
static inline uint32_t systick_now_us(const systick_source_t *s, uint32_t ticks_per_ms)
{
    uint32_t ms, counter;
    bool wrapped;
    do {
        ms = s->ms_ticks();
        counter = s->counter();
        wrapped = s->wrap_pending();
        if (wrapped) counter = s->counter(); /* the wrap may have come after the first read */
    } while (ms != s->ms_ticks()); /* the handler ran meanwhile: it counted the wrap; read again */
    uint32_t elapsed_ticks = ticks_per_ms - 1u - counter;
    return (ms + wrapped) * 1000u + elapsed_ticks / (ticks_per_ms / 1000u);
}

#endif
