/* The lamp monitor's readings: one photodiode per LED channel (hal.h lamp_monitor), sampled every
 * LAMP_MONITOR_PERIOD_US and smoothed by an exponential average over ~LAMP_MONITOR_AVERAGE samples.
 * The average takes out the ADC's noise and the LED PWM ripple the photodiode stage leaves, while a
 * shutter move (hundreds of ms) still shows within a few tens of ms. Polled from the main loop. */
#ifndef TRIMETER_LAMP_MONITOR_H
#define TRIMETER_LAMP_MONITOR_H

#include <stdbool.h>
#include <stdint.h>

#include "hal.h"

#define LAMP_MONITOR_PERIOD_US 1000u
#define LAMP_MONITOR_AVERAGE 16u /* samples; a power of two (the average is a shift) */

typedef struct lamp_monitor {
    uint32_t sum[HAL_LED_COUNT]; /* LAMP_MONITOR_AVERAGE × the running average, in counts */
    uint32_t last_us;
    bool started;
} lamp_monitor_t;

void lamp_monitor_init(lamp_monitor_t *m);
/* Takes one sample of each photodiode when a period has passed since the last (no-op without a monitor). */
void lamp_monitor_poll(lamp_monitor_t *m, const hal_t *hal, uint32_t now_us);
/* The averaged reading in ADC counts, rounded. */
uint16_t lamp_monitor_counts(const lamp_monitor_t *m, enum hal_led lamp);

#endif
