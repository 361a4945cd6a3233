/* Shutters (servos with a settle time), LEDs (on/off + PWM level, settle time), the front button
 * (debounced, with an event counter), the status LED (patterns) and the watchdog.
 * All time-driven work happens in actuators_poll(); nothing here blocks. */
#ifndef TRIMETER_ACTUATORS_H
#define TRIMETER_ACTUATORS_H

#include <stdbool.h>
#include <stdint.h>

#include "hal.h"
#include "registers_gen.h"

#define ACTUATORS_DEBOUNCE_MS 20u /* the button must read the same for this long */

/* the status_pattern register's values (hardware/registers.toml), so that app.c can hand it over as is */
enum status_pattern {
    STATUS_OFF = TRIMETER_STATUS_PATTERN_OFF,
    STATUS_ON = TRIMETER_STATUS_PATTERN_ON,
    STATUS_SLOW_BLINK = TRIMETER_STATUS_PATTERN_SLOW_BLINK,
    STATUS_FAST_BLINK = TRIMETER_STATUS_PATTERN_FAST_BLINK,
    STATUS_DOUBLE_BLINK = TRIMETER_STATUS_PATTERN_DOUBLE_BLINK,
    STATUS_TRIPLE_BLINK = TRIMETER_STATUS_PATTERN_TRIPLE_BLINK,
};

typedef struct actuators {
    const hal_t *hal;
    bool shutter_open[HAL_SHUTTER_COUNT];
    bool led_on[HAL_LED_COUNT];
    uint16_t led_level_permille[HAL_LED_COUNT];
    /* busy until this time (valid while settling) */
    bool settling;
    uint32_t settle_until_us;
    /* button */
    bool button_raw;
    bool button_stable;
    uint32_t button_changed_us;
    uint16_t button_events;
    /* status LED */
    enum status_pattern pattern;
    bool status_lit;
} actuators_t;

void actuators_init(actuators_t *a, const hal_t *hal, uint32_t now_us);
/* Commands the servo to its open or closed pulse width; busy for settle_ms from now. */
void actuators_set_shutter(actuators_t *a, enum hal_shutter s, bool open, uint16_t pulse_us, uint16_t settle_ms,
                           uint32_t now_us);
/* LED on/off at a level (permille); busy for settle_ms if the light output changed. */
void actuators_set_led(actuators_t *a, enum hal_led led, bool on, uint16_t level_permille, uint16_t settle_ms,
                       uint32_t now_us);
/* Extends busy to at least now + ms (used for the slider's settle after arrival). */
void actuators_settle(actuators_t *a, uint16_t ms, uint32_t now_us);
void actuators_set_pattern(actuators_t *a, enum status_pattern p);
/* Settle timers, button debounce, status LED blinking, watchdog kick. */
void actuators_poll(actuators_t *a, uint32_t now_us);

static inline bool actuators_busy(const actuators_t *a) { return a->settling; }

#endif
