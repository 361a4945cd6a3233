/* The device configuration: the persisted holding registers (steps/mm, slot positions, speeds,
 * servo pulse widths, settle times, Modbus address/baud), decoded and cross-checked.
 *
 * Per-register min/max/allowed come from the register map (regmap_check_write_regs); this file
 * adds what no single register can say (a slot inside the homing back-off, a speed the step timer
 * can't make) and turns the physical values into motion parameters in steps.
 *
 * A few mechanical constants are not (yet) in the register map; they are declared here, once. */
#ifndef TRIMETER_CONFIG_H
#define TRIMETER_CONFIG_H

#include <stdbool.h>
#include <stdint.h>

#include "c12880.h"
#include "hal.h"
#include "motion.h"
#include "registers_gen.h"
#include "storage.h"

/* Mechanics fixed by the slider's design rather than tuned per instrument (homing speed and
 * back-off are registers). */
#define CONFIG_TRAVEL_MM REG_HR_SLOT_OPEN_MM_MAX /* usable travel = the slot positions' range */
#define CONFIG_SEEK_MARGIN_MM 10.0f     /* homing gives up after travel + margin             */
#define CONFIG_STALL_TOLERANCE_MM 1.0f  /* re-homing: endstop this far off = lost steps       */
#define CONFIG_SLOT_TOLERANCE_MM 0.05f  /* position_slot reports a slot within this distance  */

enum config_slot { CONFIG_SLOT_BLACK = 0, CONFIG_SLOT_WHITE = 1, CONFIG_SLOT_OPEN = 2, CONFIG_SLOT_COUNT };

typedef struct config {
    float steps_per_mm;
    float slot_mm[CONFIG_SLOT_COUNT];
    float speed_mm_s;
    float accel_mm_s2;
    int homing_direction; /* -1 or +1 */
    uint16_t homing_timeout_ms;
    float homing_speed_mm_s; /* capped at speed_mm_s */
    float homing_backoff_mm; /* also the soft lower limit */
    uint16_t servo_open_us[HAL_SHUTTER_COUNT];
    uint16_t servo_closed_us[HAL_SHUTTER_COUNT];
    uint16_t shutter_settle_ms;
    uint16_t motion_settle_ms;
    uint16_t led_settle_ms;
    uint16_t led_pwm_hz;
    uint8_t modbus_address;
    uint32_t modbus_baud;
    float spectro_wl[C12880_WL_COEFFS]; /* the spectrometer unit's wavelength polynomial */
} config_t;

/* The persisted words are hr[STORAGE_CONFIG_FIRST .. REG_HR_SPAN). */
void config_defaults(uint16_t hr[REG_HR_SPAN]);
void config_decode(const uint16_t hr[REG_HR_SPAN], config_t *out);
/* true when the whole configuration is usable; on false, *field names the first bad register. */
bool config_check(const config_t *c, const char **field);
void config_motion(const config_t *c, motion_config_t *out);
int32_t config_slot_steps(const config_t *c, enum config_slot slot);

/* Boot: the saved configuration if storage has a valid one that passes config_check, else the
 * register-map defaults (storage->config is set to what is used, so a later commit is sound).
 * Returns where the configuration came from (saved, or defaults and why: input register
 * config_source). */
trimeter_config_source_t config_load(uint16_t hr[REG_HR_SPAN], storage_t *st);
/* Persists the configuration part of hr; on failure the previous saved copy stays valid. Nothing is
 * written (STORAGE_OK) when the newest saved copy already holds exactly these words. */
int config_save(const uint16_t hr[REG_HR_SPAN], storage_t *st);

#endif
