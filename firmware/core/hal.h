/* The hardware abstraction the core is written against.
 *
 * A port fills one hal_t and passes it to app_init(); the core never includes a port header and
 * never touches a register. Every function receives the port's `ctx`, so the sim can run several
 * instances and the tests can inspect a fake. All calls are non-blocking. Functions called from the
 * step-timer ISR are marked [ISR]: they must be short and must not call back into the core. */
#ifndef TRIMETER_HAL_H
#define TRIMETER_HAL_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* The three servo-driven shutters. */
enum hal_shutter {
    HAL_SHUTTER_PANEL_LEFT = 0,
    HAL_SHUTTER_PANEL_RIGHT = 1,
    HAL_SHUTTER_COLLIMATED = 2,
    HAL_SHUTTER_COUNT
};

/* The LED PWM channels. */
enum hal_led {
    HAL_LED_PANEL_LEFT = 0,
    HAL_LED_PANEL_RIGHT = 1,
    HAL_LED_COLLIMATED = 2,
    HAL_LED_COUNT
};

/* Storage regions. Semantics are NOR flash: erase sets a whole region to 0xFF, a write can only
 * clear bits, and a power cut may stop an erase or a write after any byte. Sizes are fixed so the
 * layout is the same on every port (the STM32 maps them onto flash sectors 2, 3, 5, 6). */
enum hal_region {
    HAL_REGION_CONFIG_A = 0,
    HAL_REGION_CONFIG_B = 1,
    HAL_REGION_MAP_A = 2,
    HAL_REGION_MAP_B = 3,
    HAL_REGION_COUNT
};
#define HAL_CONFIG_REGION_SIZE (16u * 1024u)
#define HAL_MAP_REGION_SIZE (128u * 1024u)


/* One frame of a CLK/ST/TRG/EOS line sensor (the C12880MA micro-spectrometer; core/c12880.h plans it):
 * ST high for st_high_clocks CLK periods, then low for st_low_clocks; after ST falls, the video of
 * pixel k (0-based) is sampled by the ADC at the TRG rising edge of CLK number first_video_clock + k,
 * and EOS must be high at CLK number eos_clock. */
typedef struct hal_spectro_timing {
    uint32_t st_high_clocks;
    uint32_t st_low_clocks;
    uint16_t first_video_clock;
    uint16_t pixels;
    uint16_t eos_clock;
    uint16_t gain; /* the analog front end's gain: 1, 2, 4, 8 */
} hal_spectro_timing_t;

enum hal_spectro_result {
    HAL_SPECTRO_OK = 0,      /* the frame is in the caller's buffer */
    HAL_SPECTRO_PENDING = 1, /* still integrating / reading out */
    HAL_SPECTRO_NO_EOS = -1, /* the frame ended without EOS at eos_clock (or not `pixels` TRG samples) */
};

typedef struct hal {
    void *ctx;

    /* Modbus UART. read returns the bytes available now (0 if none); write queues up to len
     * bytes and returns how many it took. The port must be able to queue one whole reply
     * (MB_ADU_MAX = 256 bytes) at once: the core hands over each reply in a single call. */
    size_t (*uart_read)(void *ctx, uint8_t *buf, size_t max);
    size_t (*uart_write)(void *ctx, const uint8_t *buf, size_t len);

    /* Monotonic microseconds since boot; 32-bit, wraps after 71 min (the core only ever
     * subtracts two readings). */
    uint32_t (*now_us)(void *ctx);

    /* Stepper driver. [ISR] stepper_step emits one STEP pulse; stepper_dir(true) drives the DIR
     * pin high = the motor's positive direction (which end is home is config: homing_direction). */
    void (*stepper_enable)(void *ctx, bool enabled);
    void (*stepper_dir)(void *ctx, bool positive);             /* [ISR] */
    void (*stepper_step)(void *ctx);                           /* [ISR] */
    bool (*endstop_active)(void *ctx);                         /* [ISR] */
    /* The driver's stall output (e.g. TMC2209 StallGuard on DIAG): true while the motor is being
     * stepped against a jam. NULL when the board has none (then only the endstop checks remain). */
    bool (*stepper_stalled)(void *ctx);                        /* [ISR] */

    /* Step timer: after step_timer_start(first_us) the port calls app_step_isr() once the
     * interval has elapsed; the ISR returns the next interval in µs, 0 stops the timer.
     * step_timer_stop may be called from thread context at any time. */
    void (*step_timer_start)(void *ctx, uint32_t first_interval_us);
    void (*step_timer_stop)(void *ctx);

    /* Actuators. Servo pulse width 0 = no pulses (servo unpowered, holds position). */
    void (*servo_pulse_us)(void *ctx, enum hal_shutter shutter, uint16_t pulse_us);
    void (*led_level)(void *ctx, enum hal_led led, uint16_t permille);
    void (*status_led)(void *ctx, bool on);
    bool (*button_pressed)(void *ctx);

    /* Lamp monitor: one photodiode per LED channel, seen past that channel's shutter (so it reads light
     * only while the shutter is open) and never through the sample. Returns one 12-bit ADC sample
     * (0..4095, dark offset included); may take a few µs (one conversion). NULL when the board has no
     * monitor (the lamp_monitor_* registers then read 0). */
    uint16_t (*lamp_monitor)(void *ctx, enum hal_led lamp);

    /* Micro-spectrometer. spectro_clock_hz: the CLK rate the port generates (a timer), 0 or NULL = no
     * spectrometer on this board. spectro_start begins one frame with this timing (returns 0, or negative
     * when one is still running); spectro_read copies the frame's `pixels` 12-bit ADC samples (taken by the
     * ADC on TRG, by DMA on the MCU) into video once it is complete. Non-blocking. */
    uint32_t (*spectro_clock_hz)(void *ctx);
    int (*spectro_start)(void *ctx, const hal_spectro_timing_t *timing);
    enum hal_spectro_result (*spectro_read)(void *ctx, uint16_t *video, size_t pixels);

    /* Storage. Return 0 on success, negative on an I/O error or out-of-range access. */
    int (*storage_read)(void *ctx, enum hal_region region, uint32_t offset, void *buf, size_t len);
    int (*storage_write)(void *ctx, enum hal_region region, uint32_t offset, const void *buf,
                         size_t len);
    int (*storage_erase)(void *ctx, enum hal_region region);
    /* A map region's HAL_MAP_REGION_SIZE bytes, read in place (memory-mapped flash on the MCU, the storage
     * image in RAM on the sim), so the fit reads its table without a 128 KiB copy. Valid until the next
     * storage_write/erase of that region. NULL for another region, or a port that cannot map it (then
     * the device cannot fit). */
    const uint8_t *(*storage_map_bytes)(void *ctx, enum hal_region region);

    void (*watchdog_kick)(void *ctx);
} hal_t;

#endif
