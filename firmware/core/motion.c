/* Trapezoidal step generation and homing; see motion.h for the contract.
 *
 * Profile of an N-step move with acceleration a and cruise speed v (steps, seconds):
 *   ramp     n_a = min(floor(v² / 2a), floor(N / 2)) pulses, T(k) = sqrt(2k / a)       for k ≤ n_a
 *   cruise   T(k) = T(n_a) + (k − n_a) / v                                              up to N − n_a
 *   decel    mirror of the ramp: T(k) = T(N) − sqrt(2(N − k) / a)
 * Moves too short to reach v are triangles (no cruise). Each ISR call computes one T(k) with one
 * integer square root; intervals are differences of exact times, so rounding never accumulates.
 *
 * Stall detection without an encoder: the driver's stall output (hal->stepper_stalled, checked
 * before every pulse) catches a jam anywhere; the endstop adds two checks that need no driver help:
 *   - leaving home: after the homing back-off (and during any move away from home) the endstop
 *     must be released; still active means the carriage did not move;
 *   - re-homing: when the position was known, the endstop must trigger within
 *     stall_tolerance_steps of the believed position; elsewhere steps were lost.
 * Without a stall output, a carriage jammed between slots is invisible until the next homing. */
#include "motion.h"

#define US_PER_S 1000000ull
/* 2·1e12: T(k)[µs] = sqrt(2k/a)·1e6 = sqrt(2k·1e12 / a). */
#define TWO_US2_PER_S2 2000000000000ull
/* Hard ceiling on a profile so 2k·1e12 stays inside 64 bits and an interval inside 32 bits. */
#define MOTION_MAX_STEPS 1000000u
#define MOTION_MIN_INTERVAL_US 20u /* 50 kHz: beyond any driver we'd use */

static uint32_t isqrt64(uint64_t x)
{
    /* Bitwise integer square root: floor(sqrt(x)), 32 iterations, no division. */
    uint64_t result = 0;
    uint64_t bit = 1ull << 62;
    while (bit > x) bit >>= 2;
    while (bit != 0) {
        if (x >= result + bit) {
            x -= result + bit;
            result = (result >> 1) + bit;
        } else {
            result >>= 1;
        }
        bit >>= 2;
    }
    return (uint32_t)result;
}

static uint64_t ramp_time_us(uint32_t steps, uint32_t accel)
{
    return isqrt64((uint64_t)steps * TWO_US2_PER_S2 / accel);
}

uint64_t motion_profile_time_us(const motion_t *m, uint32_t k)
{
    if (k <= m->accel_steps) return ramp_time_us(k, m->accel_sps2);
    if (k <= m->decel_start)
        return m->t_accel_end_us + (uint64_t)(k - m->accel_steps) * US_PER_S / m->cruise_sps;
    return m->t_end_us - ramp_time_us(m->steps_total - k, m->accel_sps2);
}

int motion_config_valid(const motion_config_t *c)
{
    if (c->accel_sps2 == 0 || c->max_speed_sps == 0 || c->homing_speed_sps == 0) return MOTION_ERR_CONFIG;
    if (c->max_speed_sps > US_PER_S / MOTION_MIN_INTERVAL_US) return MOTION_ERR_CONFIG;
    if (c->homing_speed_sps > c->max_speed_sps) return MOTION_ERR_CONFIG;
    if (c->max_travel_steps <= 0 || (uint32_t)c->max_travel_steps > MOTION_MAX_STEPS) return MOTION_ERR_CONFIG;
    if (c->backoff_steps <= 0 || c->backoff_steps > c->soft_min_steps) return MOTION_ERR_CONFIG;
    if (c->soft_min_steps > c->soft_max_steps || c->soft_max_steps > c->max_travel_steps)
        return MOTION_ERR_CONFIG;
    if (c->stall_tolerance_steps < 0 || c->homing_timeout_ms == 0) return MOTION_ERR_CONFIG;
    return MOTION_OK;
}

void motion_init(motion_t *m, const hal_t *hal, const motion_config_t *cfg)
{
    *m = (motion_t){0};
    m->hal = hal;
    m->cfg = *cfg;
    m->state = MOTION_IDLE;
    hal->stepper_enable(hal->ctx, false);
}

int motion_configure(motion_t *m, const motion_config_t *cfg)
{
    if (motion_busy(m)) return MOTION_ERR_BUSY;
    if (motion_config_valid(cfg) != MOTION_OK) return MOTION_ERR_CONFIG;
    m->cfg = *cfg;
    return MOTION_OK;
}

/* Lays out an N-step profile and sets the outputs; the caller starts the timer (thread context)
 * or returns the first interval (ISR). */
static void setup_profile(motion_t *m, int8_t dir, uint32_t steps, uint32_t speed, enum motion_state state)
{
    uint32_t accel = m->cfg.accel_sps2;
    uint64_t ramp = (uint64_t)speed * speed / (2ull * accel);
    uint32_t na = ramp < steps / 2 ? (uint32_t)ramp : steps / 2;
    m->dir = dir;
    m->steps_total = steps;
    m->steps_done = 0;
    m->accel_steps = na;
    m->decel_start = steps - na;
    m->accel_sps2 = accel;
    m->cruise_sps = speed;
    m->t_accel_end_us = ramp_time_us(na, accel);
    m->t_end_us = 0; /* T(N) needs T(decel_start) first */
    m->t_end_us = motion_profile_time_us(m, m->decel_start) + ramp_time_us(na, accel);
    m->stop_requested = false;
    m->state = state;
    m->hal->stepper_enable(m->hal->ctx, true);
    m->hal->stepper_dir(m->hal->ctx, (dir > 0) != m->cfg.home_is_positive);
    m->t_next_us = motion_profile_time_us(m, 1);
}

static uint32_t latch_fault(motion_t *m, enum motion_fault fault)
{
    m->fault = fault;
    m->state = MOTION_FAULT;
    m->homed = false; /* after any fault the position can't be trusted */
    m->hal->stepper_enable(m->hal->ctx, false);
    return 0;
}

int motion_home(motion_t *m)
{
    if (m->state == MOTION_FAULT) return MOTION_ERR_FAULTED;
    if (motion_busy(m)) return MOTION_ERR_BUSY;
    m->was_homed = m->homed;
    m->believed_position = m->position;
    m->homed = false;
    m->seek_steps = 0;
    m->homing_started_us = m->hal->now_us(m->hal->ctx);
    m->dir = -1;
    m->state = MOTION_HOMING_SEEK;
    m->hal->stepper_enable(m->hal->ctx, true);
    m->hal->stepper_dir(m->hal->ctx, m->cfg.home_is_positive);
    /* The first call checks the endstop before any pulse: a carriage already home is found at once. */
    m->hal->step_timer_start(m->hal->ctx, 1);
    return MOTION_OK;
}

int motion_move_to(motion_t *m, int32_t target)
{
    if (m->state == MOTION_FAULT) return MOTION_ERR_FAULTED;
    if (motion_busy(m)) return MOTION_ERR_BUSY;
    if (!m->homed) return MOTION_ERR_NOT_HOMED;
    if (target < m->cfg.soft_min_steps || target > m->cfg.soft_max_steps) return MOTION_ERR_LIMIT;
    int32_t delta = target - m->position;
    if (delta == 0) return MOTION_OK;
    setup_profile(m, delta > 0 ? 1 : -1, (uint32_t)(delta > 0 ? delta : -delta), m->cfg.max_speed_sps,
                  MOTION_MOVING);
    m->hal->step_timer_start(m->hal->ctx, (uint32_t)m->t_next_us);
    return MOTION_OK;
}

void motion_stop(motion_t *m)
{
    m->hal->step_timer_stop(m->hal->ctx);
    if (m->state == MOTION_HOMING_SEEK || m->state == MOTION_HOMING_BACKOFF) m->homed = false;
    if (motion_busy(m)) m->state = MOTION_IDLE;
}

void motion_stop_smooth(motion_t *m)
{
    if (m->state == MOTION_MOVING) m->stop_requested = true; /* the ISR owns the profile */
    else motion_stop(m);
}

/* ISR: after pulse k, end the profile with the shortest ramp-down from the current speed.
 * The ramp is the mirror of the acceleration, so the pulses before k keep their times. */
static void shorten_profile(motion_t *m, uint32_t k)
{
    m->stop_requested = false;
    if (k >= m->decel_start) return;                 /* already ramping down */
    uint32_t ramp = k < m->accel_steps ? k : m->accel_steps; /* steps the current speed needs */
    uint64_t t_k = motion_profile_time_us(m, k);
    m->steps_total = k + ramp;
    m->decel_start = k;
    if (k < m->accel_steps) m->accel_steps = k;
    m->t_end_us = t_k + ramp_time_us(ramp, m->accel_sps2);
}

void motion_clear_fault(motion_t *m)
{
    if (m->state != MOTION_FAULT) return;
    m->fault = MOTION_FAULT_NONE;
    m->state = MOTION_IDLE;
}

void motion_poll(motion_t *m, uint32_t now_us)
{
    if (m->state != MOTION_HOMING_SEEK) return;
    uint32_t elapsed_us = now_us - m->homing_started_us;
    if (elapsed_us / 1000u >= m->cfg.homing_timeout_ms) {
        m->hal->step_timer_stop(m->hal->ctx);
        if (m->state == MOTION_HOMING_SEEK) latch_fault(m, MOTION_FAULT_HOMING_TIMEOUT);
    }
}

static bool driver_stalled(const hal_t *h) { return h->stepper_stalled && h->stepper_stalled(h->ctx); }

static uint32_t seek_isr(motion_t *m)
{
    const hal_t *h = m->hal;
    if (driver_stalled(h)) return latch_fault(m, MOTION_FAULT_STALL);
    if (h->endstop_active(h->ctx)) {
        if (m->was_homed) {
            int32_t error = m->seek_steps - m->believed_position;
            if (error < 0) error = -error;
            if (error > m->cfg.stall_tolerance_steps) return latch_fault(m, MOTION_FAULT_STALL);
        }
        m->position = 0;
        setup_profile(m, 1, (uint32_t)m->cfg.backoff_steps, m->cfg.max_speed_sps, MOTION_HOMING_BACKOFF);
        return (uint32_t)m->t_next_us;
    }
    if (m->seek_steps >= m->cfg.max_travel_steps) return latch_fault(m, MOTION_FAULT_HOMING_TIMEOUT);
    h->stepper_step(h->ctx);
    m->seek_steps++;
    m->position--;
    return (uint32_t)(US_PER_S / m->cfg.homing_speed_sps);
}

static uint32_t profile_isr(motion_t *m)
{
    const hal_t *h = m->hal;
    if (driver_stalled(h)) return latch_fault(m, MOTION_FAULT_STALL);
    if (h->endstop_active(h->ctx)) {
        /* The back-off starts on the switch: it must have let go by the time the carriage is
         * half-way out; a normal move must never see it at all. */
        if (m->state == MOTION_MOVING)
            return latch_fault(m, m->dir > 0 ? MOTION_FAULT_STALL : MOTION_FAULT_ENDSTOP_HIT);
        if (m->steps_done * 2 >= m->steps_total) return latch_fault(m, MOTION_FAULT_STALL);
    }
    h->stepper_step(h->ctx);
    m->position += m->dir;
    uint32_t k = ++m->steps_done;
    if (m->stop_requested && m->state == MOTION_MOVING) shorten_profile(m, k);
    if (k >= m->steps_total) {
        if (m->state == MOTION_HOMING_BACKOFF) {
            if (h->endstop_active(h->ctx)) return latch_fault(m, MOTION_FAULT_STALL);
            m->homed = true;
        }
        m->state = MOTION_IDLE;
        return 0;
    }
    /* Intervals are differences of exact pulse times, so rounding never accumulates. */
    uint64_t t_next = motion_profile_time_us(m, k + 1);
    uint32_t interval = (uint32_t)(t_next - m->t_next_us);
    m->t_next_us = t_next;
    return interval ? interval : 1;
}

uint32_t motion_isr(motion_t *m)
{
    switch (m->state) {
    case MOTION_HOMING_SEEK: return seek_isr(m);
    case MOTION_HOMING_BACKOFF:
    case MOTION_MOVING: return profile_isr(m);
    default: return 0;
    }
}
