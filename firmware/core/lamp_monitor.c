/* See lamp_monitor.h. */
#include "lamp_monitor.h"

#include <string.h>

#define ADC_MAX 4095u

void lamp_monitor_init(lamp_monitor_t *m) { memset(m, 0, sizeof *m); }

void lamp_monitor_poll(lamp_monitor_t *m, const hal_t *hal, uint32_t now_us)
{
    if (!hal->lamp_monitor) return;
    if (m->started && now_us - m->last_us < LAMP_MONITOR_PERIOD_US) return;
    for (int l = 0; l < HAL_LED_COUNT; l++) {
        uint32_t sample = hal->lamp_monitor(hal->ctx, (enum hal_led)l);
        if (sample > ADC_MAX) sample = ADC_MAX; /* a port bug must not overflow the sum */
        if (!m->started) {
            m->sum[l] = sample * LAMP_MONITOR_AVERAGE; /* the first sample fills the average */
        } else {
            /* sum ← sum − average + sample: an exponential average with weight 1/N, in integers; the
             * average is rounded (not floored) so a steady input reads back exactly */
            m->sum[l] = m->sum[l] - (m->sum[l] + LAMP_MONITOR_AVERAGE / 2u) / LAMP_MONITOR_AVERAGE + sample;
        }
    }
    /* Catching up after a long stall would just repeat one sample: the next period starts now. */
    m->last_us = now_us;
    m->started = true;
}

uint16_t lamp_monitor_counts(const lamp_monitor_t *m, enum hal_led lamp)
{
    return (uint16_t)((m->sum[lamp] + LAMP_MONITOR_AVERAGE / 2u) / LAMP_MONITOR_AVERAGE);
}
