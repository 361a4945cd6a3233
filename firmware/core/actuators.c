/* Shutters, LEDs, button, status LED, watchdog; see actuators.h. */
#include "actuators.h"

/* Wrap-safe "now is at or after t" for the 32-bit microsecond clock. */
static bool reached(uint32_t now_us, uint32_t t_us) { return (int32_t)(now_us - t_us) >= 0; }

void actuators_init(actuators_t *a, const hal_t *hal, uint32_t now_us)
{
    *a = (actuators_t){.hal = hal, .pattern = STATUS_SLOW_BLINK};
    for (int l = 0; l < HAL_LED_COUNT; l++) hal->led_level(hal->ctx, (enum hal_led)l, 0);
    hal->status_led(hal->ctx, false);
    a->button_raw = a->button_stable = hal->button_pressed(hal->ctx);
    a->button_changed_us = now_us;
}

void actuators_settle(actuators_t *a, uint16_t ms, uint32_t now_us)
{
    uint32_t until = now_us + (uint32_t)ms * 1000u;
    if (!a->settling || reached(until, a->settle_until_us)) a->settle_until_us = until;
    a->settling = true;
}

void actuators_set_shutter(actuators_t *a, enum hal_shutter s, bool open, uint16_t pulse_us, uint16_t settle_ms,
                           uint32_t now_us)
{
    a->shutter_open[s] = open;
    a->hal->servo_pulse_us(a->hal->ctx, s, pulse_us);
    /* Re-commanding the same position still waits: the servo may not be there yet after a reset. */
    actuators_settle(a, settle_ms, now_us);
}

void actuators_set_led(actuators_t *a, enum hal_led led, bool on, uint16_t level_permille, uint16_t settle_ms,
                       uint32_t now_us)
{
    uint16_t before = a->led_on[led] ? a->led_level_permille[led] : 0;
    uint16_t after = on ? level_permille : 0;
    a->led_on[led] = on;
    a->led_level_permille[led] = level_permille;
    a->hal->led_level(a->hal->ctx, led, after);
    if (after != before) actuators_settle(a, settle_ms, now_us);
}

void actuators_set_pattern(actuators_t *a, enum status_pattern p) { a->pattern = p; }

static void poll_button(actuators_t *a, uint32_t now_us)
{
    bool raw = a->hal->button_pressed(a->hal->ctx);
    if (raw != a->button_raw) {
        a->button_raw = raw;
        a->button_changed_us = now_us;
    } else if (raw != a->button_stable && now_us - a->button_changed_us >= ACTUATORS_DEBOUNCE_MS * 1000u) {
        a->button_stable = raw;
        if (raw) a->button_events++;
    }
}

static void poll_status(actuators_t *a, uint32_t now_us)
{
    bool lit;
    switch (a->pattern) {
    case STATUS_ON: lit = true; break;
    case STATUS_SLOW_BLINK: lit = (now_us / 500000u) & 1u; break;  /* 1 Hz */
    case STATUS_FAST_BLINK: lit = (now_us / 100000u) & 1u; break;  /* 5 Hz */
    case STATUS_DOUBLE_BLINK: {                                      /* two 150 ms flashes per 1.5 s */
        uint32_t phase = (now_us / 150000u) % 10u;
        lit = phase == 0u || phase == 2u;
        break;
    }
    case STATUS_TRIPLE_BLINK: {                                      /* three 150 ms flashes per 2.1 s */
        uint32_t phase = (now_us / 150000u) % 14u;
        lit = phase == 0u || phase == 2u || phase == 4u;
        break;
    }
    default: lit = false; break;
    }
    if (lit != a->status_lit) {
        a->status_lit = lit;
        a->hal->status_led(a->hal->ctx, lit);
    }
}

void actuators_poll(actuators_t *a, uint32_t now_us)
{
    if (a->settling && reached(now_us, a->settle_until_us)) a->settling = false;
    poll_button(a, now_us);
    poll_status(a, now_us);
    a->hal->watchdog_kick(a->hal->ctx);
}
