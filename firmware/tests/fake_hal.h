/* A fake HAL for the host-side C tests: simulated time, a step-timer the test drives, a minimal
 * plant (carriage counted from the pulses, endstop at the home end, fault injection), NOR-flash
 * storage that can lose power after any byte, and in-memory UART buffers. Tests only. */
#ifndef TRIMETER_FAKE_HAL_H
#define TRIMETER_FAKE_HAL_H

#include <stdbool.h>
#include <stdint.h>

#include "../core/hal.h"

#define FAKE_MAX_PULSES 200000
#define FAKE_UART_SIZE 1024

typedef struct fake_hal {
    hal_t hal;
    uint64_t now_us;

    /* step timer */
    bool timer_running;
    uint64_t timer_due_us;

    /* stepper + plant */
    bool enabled;
    bool dir_away;              /* DIR pin high: the carriage's steps increase */
    int32_t carriage_steps;     /* physical position; the endstop is active at <= endstop_steps */
    int32_t endstop_steps;
    int32_t hard_stop_steps;    /* the carriage can't go below this (mechanical end); pulses lost */
    bool stuck;                 /* pulses don't move the carriage */
    bool has_stall_output;      /* the driver reports stepping against a jam (hal.stepper_stalled) */
    bool stalled;
    bool endstop_broken;        /* endstop never active */
    uint32_t pulses;
    uint64_t *pulse_times_us;   /* FAKE_MAX_PULSES entries, one per pulse while recording */
    bool record_pulses;

    /* actuators */
    uint16_t servo_us[HAL_SHUTTER_COUNT];
    uint16_t led_permille[HAL_LED_COUNT];
    bool status_led;
    bool button;
    uint32_t watchdog_kicks;
    uint16_t lamp_adc[HAL_LED_COUNT]; /* what each lamp-monitor photodiode's ADC sample reads */
    uint32_t lamp_samples;            /* lamp_monitor calls */

    /* micro-spectrometer: the CLK rate (0 = none), the timing of every frame started, and what a frame
     * reads: spectro_video, or spectro_video + frame number when spectro_ramp (to check the averaging);
     * spectro_no_eos: frames end without EOS. A frame takes its planned time. */
    uint32_t spectro_clock_hz;
    hal_spectro_timing_t spectro_timing;
    uint32_t spectro_frames;
    bool spectro_running, spectro_no_eos, spectro_ramp;
    uint64_t spectro_done_us;
    uint16_t spectro_video[288];

    /* storage: NOR flash with a power-cut budget (bytes programmed/erased before power is lost;
     * negative = unlimited). After the cut every write/erase fails and changes nothing. */
    uint8_t config[2][HAL_CONFIG_REGION_SIZE];
    uint8_t map[2][HAL_MAP_REGION_SIZE];
    long power_budget;
    bool power_lost;
    long bytes_programmed;

    /* UART: the test writes requests into rx, the core's replies land in tx */
    uint8_t rx[FAKE_UART_SIZE];
    size_t rx_len, rx_pos;
    uint8_t tx[FAKE_UART_SIZE];
    size_t tx_len;
} fake_hal_t;

/* Allocates (the storage is large); returns NULL on failure. */
fake_hal_t *fake_hal_new(void);
void fake_hal_free(fake_hal_t *f);
/* Power comes back: the budget is unlimited again; storage contents are kept. */
void fake_hal_power_on(fake_hal_t *f);

/* Advances simulated time to `until_us`, calling isr(ctx) at every due step-timer tick and
 * reprogramming the timer from its return value, as a port's timer interrupt does. */
typedef uint32_t (*fake_isr_fn)(void *ctx);
void fake_hal_run_until(fake_hal_t *f, uint64_t until_us, fake_isr_fn isr, void *ctx);
/* Runs until the step timer stops (or `limit_us` of simulated time passed); returns true if it stopped. */
bool fake_hal_run_idle(fake_hal_t *f, uint64_t limit_us, fake_isr_fn isr, void *ctx);

#endif
