/* The sim's plant: the physical instrument around the MCU (slider, endstop, shutters, LEDs,
 * status LED, button), driven by the HAL outputs and observed/driven over the plant socket.
 * Time is simulated microseconds, supplied by the caller. See README.md for the model. */
#ifndef TRIMETER_SIM_PLANT_H
#define TRIMETER_SIM_PLANT_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "hal.h"

typedef struct plant {
    double steps_per_mm;
    double travel_mm;          /* slots live in 0..travel_mm */
    int64_t position_steps;    /* 0 = where the endstop trips; positive = DIR pin high */
    int64_t min_steps, max_steps; /* mechanical ends */
    bool stepper_enabled;
    bool dir_positive;
    uint16_t servo_pulse_us[HAL_SHUTTER_COUNT];
    double shutter_angle_deg[HAL_SHUTTER_COUNT];
    uint16_t led_permille[HAL_LED_COUNT];
    bool status_led;
    bool button_held;          /* set{"button":true} */
    uint64_t button_release_us;/* press_button: pressed until this time */
    bool stuck_slider;
    bool driver_stalled;       /* the driver's stall output: stepping against the jam */
    bool endstop_broken;
    /* lamp monitor photodiodes: each lamp's emission at full drive relative to nominal (the twin's lamp
     * model: warm-up droop, a dimmed or dead lamp), and a shutter whose blade passes light whatever its
     * angle (-1: none) */
    double lamp_emission[HAL_LED_COUNT];
    int shutter_leaking;
    uint64_t noise_state;
    uint64_t last_update_us;
} plant_t;

void plant_init(plant_t *p, double steps_per_mm, double start_mm);
/* Advances the servos to simulated time now_us. */
void plant_update(plant_t *p, uint64_t now_us);
void plant_step(plant_t *p);
bool plant_endstop(const plant_t *p);
bool plant_button(const plant_t *p, uint64_t now_us);
/* One ADC sample of the photodiode that watches `lamp` past its shutter: dark offset + light through the
 * shutter's opening × LED level × emission, with ADC noise. */
uint16_t plant_lamp_monitor(plant_t *p, enum hal_led lamp);
/* How far a shutter's blade uncovers its aperture, 0..1 (1 for the leaking one). */
double plant_shutter_opening(const plant_t *p, enum hal_shutter s);
/* The slot within ±0.5 mm of the slider: 0 black, 1 white, 2 open, -1 between slots. */
int plant_slot(const plant_t *p);

/* Handles one request line; writes one reply line (with '\n') into out (size cap). Sets
 * *reset_requested for {"cmd":"reset"} (the caller reboots the firmware before replying). */
size_t plant_handle_request(plant_t *p, const char *line, uint64_t now_us, char *out, size_t cap,
                            bool *reset_requested);

#endif
