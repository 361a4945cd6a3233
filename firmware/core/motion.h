/* The slider: a stepper driven step/dir with a trapezoidal velocity profile, homed to an endstop.
 *
 * Thread context starts a move or a homing and returns at once (busy flag); the steps themselves
 * come from the step-timer ISR (motion_isr), which emits one pulse per call and returns the
 * interval to the next one, computed from the exact trapezoid with 64-bit integer maths (no
 * floats, no accumulated rounding: every pulse time is T(k) rounded to the microsecond).
 *
 * Positions are in motor steps, 0 = the endstop's trigger point, positive = away from home. */
#ifndef TRIMETER_MOTION_H
#define TRIMETER_MOTION_H

#include <stdbool.h>
#include <stdint.h>

#include "hal.h"

enum motion_fault {
    MOTION_FAULT_NONE = 0,
    MOTION_FAULT_HOMING_TIMEOUT = 1, /* no endstop within the timeout or the maximum travel */
    MOTION_FAULT_ENDSTOP_HIT = 2,    /* endstop active during a normal move (lost steps)      */
    MOTION_FAULT_STALL = 3,          /* the slider did not follow the steps (see motion.c)    */
};

enum motion_state {
    MOTION_IDLE = 0,
    MOTION_HOMING_SEEK,    /* constant slow speed towards home until the endstop */
    MOTION_HOMING_BACKOFF, /* profiled move away from the endstop                 */
    MOTION_MOVING,
    MOTION_FAULT,
};

enum motion_error {
    MOTION_OK = 0,
    MOTION_ERR_BUSY = -1,       /* a move or homing is running               */
    MOTION_ERR_FAULTED = -2,    /* a fault is latched: clear it first         */
    MOTION_ERR_NOT_HOMED = -3,  /* position unknown: home first               */
    MOTION_ERR_LIMIT = -4,      /* target outside the soft limits             */
    MOTION_ERR_CONFIG = -5,     /* parameters impossible (see motion_config_valid) */
};

typedef struct motion_config {
    uint32_t max_speed_sps;        /* cruise speed, steps/s                              */
    uint32_t accel_sps2;           /* acceleration = deceleration, steps/s²              */
    uint32_t homing_speed_sps;     /* constant seek speed towards the endstop            */
    uint32_t homing_timeout_ms;    /* whole seek, wall clock                             */
    int32_t max_travel_steps;      /* the seek gives up after this many steps            */
    int32_t backoff_steps;         /* after the endstop triggers, move this far away     */
    int32_t soft_min_steps;        /* targets allowed in [soft_min, soft_max]            */
    int32_t soft_max_steps;
    int32_t stall_tolerance_steps; /* re-homing: endstop found this far from expected    */
    bool home_is_positive;         /* the endstop is at the motor's positive end         */
} motion_config_t;

typedef struct motion {
    const hal_t *hal;
    motion_config_t cfg;

    volatile enum motion_state state;
    volatile enum motion_fault fault;
    volatile int32_t position; /* steps */
    volatile bool homed;

    /* The running profile (owned by the ISR while a move runs). */
    int8_t dir;              /* +1 away from home, -1 towards */
    uint32_t steps_total;    /* N */
    uint32_t steps_done;     /* k: pulses emitted */
    uint32_t accel_steps;    /* pulses in the acceleration ramp */
    uint32_t decel_start;    /* first pulse index of the deceleration ramp = N - accel_steps */
    uint32_t accel_sps2;
    uint32_t cruise_sps;
    uint64_t t_next_us;      /* T(k+1): when the pending pulse fires */
    uint64_t t_accel_end_us; /* T(accel_steps) */
    uint64_t t_end_us;       /* T(N) */
    volatile bool stop_requested; /* thread → ISR: ramp down now */

    /* Homing bookkeeping. */
    uint32_t homing_started_us;
    int32_t seek_steps;
    bool was_homed;
    int32_t believed_position;
} motion_t;

/* 0 when the parameters can drive the profile safely, else MOTION_ERR_CONFIG. */
int motion_config_valid(const motion_config_t *cfg);

void motion_init(motion_t *m, const hal_t *hal, const motion_config_t *cfg);
/* Takes new parameters; only while idle or faulted (MOTION_ERR_BUSY otherwise). */
int motion_configure(motion_t *m, const motion_config_t *cfg);

int motion_home(motion_t *m);
int motion_move_to(motion_t *m, int32_t target_steps);
/* Immediate stop (no ramp): the position stays counted, a running homing leaves it unhomed. */
void motion_stop(motion_t *m);
/* Decelerating stop of a move: the ISR shortens the profile at its next pulse so the carriage
 * ramps down at the configured deceleration (no lost steps); homing stops at once as above. */
void motion_stop_smooth(motion_t *m);
void motion_clear_fault(motion_t *m);
/* Thread-context housekeeping: the homing timeout. Call often. */
void motion_poll(motion_t *m, uint32_t now_us);

/* The step-timer ISR: emits at most one pulse, returns µs to the next call, 0 = stop the timer. */
uint32_t motion_isr(motion_t *m);

static inline bool motion_busy(const motion_t *m)
{
    return m->state == MOTION_HOMING_SEEK || m->state == MOTION_HOMING_BACKOFF ||
           m->state == MOTION_MOVING;
}

/* Pulse time T(k) of the current profile in µs from its start (exposed for the tests). */
uint64_t motion_profile_time_us(const motion_t *m, uint32_t k);

#endif
