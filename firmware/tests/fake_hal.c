/* The fake HAL; see fake_hal.h. */
#include "fake_hal.h"

#include <stdlib.h>
#include <string.h>

static size_t f_uart_read(void *ctx, uint8_t *buf, size_t max)
{
    fake_hal_t *f = ctx;
    size_t n = f->rx_len - f->rx_pos;
    if (n > max) n = max;
    memcpy(buf, f->rx + f->rx_pos, n);
    f->rx_pos += n;
    return n;
}

static size_t f_uart_write(void *ctx, const uint8_t *buf, size_t len)
{
    fake_hal_t *f = ctx;
    size_t room = FAKE_UART_SIZE - f->tx_len;
    if (len > room) len = room;
    memcpy(f->tx + f->tx_len, buf, len);
    f->tx_len += len;
    return len;
}

static uint32_t f_now_us(void *ctx) { return (uint32_t)((fake_hal_t *)ctx)->now_us; }
static void f_enable(void *ctx, bool on) { ((fake_hal_t *)ctx)->enabled = on; }
static void f_dir(void *ctx, bool away) { ((fake_hal_t *)ctx)->dir_away = away; }

static void f_step(void *ctx)
{
    fake_hal_t *f = ctx;
    if (f->record_pulses && f->pulses < FAKE_MAX_PULSES) f->pulse_times_us[f->pulses] = f->now_us;
    f->pulses++;
    if (f->enabled && !f->stuck) f->carriage_steps += f->dir_away ? 1 : -1;
    f->stalled = f->enabled && f->stuck;
    if (f->carriage_steps < f->hard_stop_steps) f->carriage_steps = f->hard_stop_steps;
}

static bool f_endstop(void *ctx)
{
    fake_hal_t *f = ctx;
    return !f->endstop_broken && f->carriage_steps <= f->endstop_steps;
}

static bool f_stalled(void *ctx)
{
    fake_hal_t *f = ctx;
    return f->has_stall_output && f->stalled;
}

static void f_timer_start(void *ctx, uint32_t first_us)
{
    fake_hal_t *f = ctx;
    f->timer_running = true;
    f->timer_due_us = f->now_us + first_us;
}

static void f_timer_stop(void *ctx) { ((fake_hal_t *)ctx)->timer_running = false; }

static void f_servo(void *ctx, enum hal_shutter s, uint16_t us) { ((fake_hal_t *)ctx)->servo_us[s] = us; }
static void f_led(void *ctx, enum hal_led l, uint16_t pm) { ((fake_hal_t *)ctx)->led_permille[l] = pm; }
static void f_status(void *ctx, bool on) { ((fake_hal_t *)ctx)->status_led = on; }
static bool f_button(void *ctx) { return ((fake_hal_t *)ctx)->button; }
static void f_kick(void *ctx) { ((fake_hal_t *)ctx)->watchdog_kicks++; }
static uint16_t f_lamp(void *ctx, enum hal_led l)
{
    fake_hal_t *f = ctx;
    f->lamp_samples++;
    return f->lamp_adc[l];
}

static uint8_t *region(fake_hal_t *f, enum hal_region r, uint32_t offset, size_t len)
{
    size_t size = r <= HAL_REGION_CONFIG_B ? HAL_CONFIG_REGION_SIZE : HAL_MAP_REGION_SIZE;
    if ((unsigned)r >= HAL_REGION_COUNT || offset > size || len > size - offset) return NULL;
    uint8_t *base = r <= HAL_REGION_CONFIG_B ? f->config[r] : f->map[r - HAL_REGION_MAP_A];
    return base + offset;
}

static int f_read(void *ctx, enum hal_region r, uint32_t offset, void *buf, size_t len)
{
    uint8_t *p = region(ctx, r, offset, len);
    if (!p) return -1;
    memcpy(buf, p, len);
    return 0;
}

/* One more byte of programming work; false once the power is gone. */
static bool spend(fake_hal_t *f)
{
    if (f->power_lost) return false;
    if (f->power_budget >= 0 && f->bytes_programmed >= f->power_budget) {
        f->power_lost = true;
        return false;
    }
    f->bytes_programmed++;
    return true;
}

static int f_write(void *ctx, enum hal_region r, uint32_t offset, const void *buf, size_t len)
{
    fake_hal_t *f = ctx;
    uint8_t *p = region(f, r, offset, len);
    const uint8_t *src = buf;
    if (!p) return -1;
    for (size_t i = 0; i < len; i++) {
        if (!spend(f)) {
            p[i] &= (uint8_t)(src[i] | 0xA5); /* the byte being programmed at the cut: some bits */
            return -1;
        }
        p[i] &= src[i]; /* NOR: programming only clears bits */
    }
    return 0;
}

static int f_erase(void *ctx, enum hal_region r)
{
    fake_hal_t *f = ctx;
    size_t size = r <= HAL_REGION_CONFIG_B ? HAL_CONFIG_REGION_SIZE : HAL_MAP_REGION_SIZE;
    uint8_t *p = region(f, r, 0, size);
    if (!p) return -1;
    /* Erase is counted as one unit of work per 256 bytes (a cut leaves a half-erased region). */
    for (size_t i = 0; i < size; i += 256) {
        if (!spend(f)) return -1;
        memset(p + i, 0xFF, 256);
    }
    return 0;
}

static const uint8_t *f_map_bytes(void *ctx, enum hal_region r)
{
    return r == HAL_REGION_MAP_A || r == HAL_REGION_MAP_B ? region(ctx, r, 0, HAL_MAP_REGION_SIZE) : NULL;
}

static uint32_t f_spectro_clock(void *ctx) { return ((fake_hal_t *)ctx)->spectro_clock_hz; }

static int f_spectro_start(void *ctx, const hal_spectro_timing_t *t)
{
    fake_hal_t *f = ctx;
    if (f->spectro_running) return -1;
    f->spectro_timing = *t;
    f->spectro_running = true;
    f->spectro_frames++;
    uint64_t clocks = (uint64_t)t->st_high_clocks + t->st_low_clocks;
    f->spectro_done_us = f->now_us + (clocks * 1000000u + f->spectro_clock_hz - 1u) / f->spectro_clock_hz;
    return 0;
}

static enum hal_spectro_result f_spectro_read(void *ctx, uint16_t *video, size_t pixels)
{
    fake_hal_t *f = ctx;
    if (!f->spectro_running) return HAL_SPECTRO_NO_EOS;
    if (f->now_us < f->spectro_done_us) return HAL_SPECTRO_PENDING;
    f->spectro_running = false;
    if (f->spectro_no_eos || pixels > 288) return HAL_SPECTRO_NO_EOS;
    for (size_t i = 0; i < pixels; i++)
        video[i] = (uint16_t)(f->spectro_video[i] + (f->spectro_ramp ? f->spectro_frames - 1u : 0u));
    return HAL_SPECTRO_OK;
}

fake_hal_t *fake_hal_new(void)
{
    fake_hal_t *f = calloc(1, sizeof *f);
    if (!f) return NULL;
    f->pulse_times_us = calloc(FAKE_MAX_PULSES, sizeof *f->pulse_times_us);
    if (!f->pulse_times_us) {
        free(f);
        return NULL;
    }
    memset(f->config, 0xFF, sizeof f->config);
    memset(f->map, 0xFF, sizeof f->map);
    f->power_budget = -1;
    f->hard_stop_steps = INT32_MIN;
    f->hal = (hal_t){
        .ctx = f,
        .uart_read = f_uart_read,
        .uart_write = f_uart_write,
        .now_us = f_now_us,
        .stepper_enable = f_enable,
        .stepper_dir = f_dir,
        .stepper_step = f_step,
        .endstop_active = f_endstop,
        .stepper_stalled = f_stalled,
        .step_timer_start = f_timer_start,
        .step_timer_stop = f_timer_stop,
        .servo_pulse_us = f_servo,
        .led_level = f_led,
        .status_led = f_status,
        .button_pressed = f_button,
        .lamp_monitor = f_lamp,
        .spectro_clock_hz = f_spectro_clock,
        .spectro_start = f_spectro_start,
        .spectro_read = f_spectro_read,
        .storage_read = f_read,
        .storage_write = f_write,
        .storage_erase = f_erase,
        .storage_map_bytes = f_map_bytes,
        .watchdog_kick = f_kick,
    };
    return f;
}

void fake_hal_free(fake_hal_t *f)
{
    if (!f) return;
    free(f->pulse_times_us);
    free(f);
}

void fake_hal_power_on(fake_hal_t *f)
{
    f->power_budget = -1;
    f->power_lost = false;
}

void fake_hal_run_until(fake_hal_t *f, uint64_t until_us, fake_isr_fn isr, void *ctx)
{
    while (f->timer_running && f->timer_due_us <= until_us) {
        f->now_us = f->timer_due_us;
        uint32_t next = isr(ctx);
        /* The ISR may have stopped or restarted the timer itself; otherwise its return value rules. */
        if (!f->timer_running) continue;
        if (next == 0)
            f->timer_running = false;
        else if (f->timer_due_us == f->now_us)
            f->timer_due_us = f->now_us + next;
    }
    if (until_us > f->now_us) f->now_us = until_us;
}

bool fake_hal_run_idle(fake_hal_t *f, uint64_t limit_us, fake_isr_fn isr, void *ctx)
{
    uint64_t end = f->now_us + limit_us;
    while (f->timer_running && f->timer_due_us <= end) fake_hal_run_until(f, f->timer_due_us, isr, ctx);
    return !f->timer_running;
}
