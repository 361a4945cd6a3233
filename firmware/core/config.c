/* Configuration decoding, cross-checks and persistence; see config.h. */
#include "config.h"

#include <string.h>

#include "regmap.h"

void config_defaults(uint16_t hr[REG_HR_SPAN]) { regmap_fill_defaults(REGMAP_HOLDING_REGISTER, hr, REG_HR_SPAN); }

void config_decode(const uint16_t hr[REG_HR_SPAN], config_t *c)
{
    c->steps_per_mm = regmap_get_f32(&hr[REG_HR_STEPS_PER_MM]);
    c->slot_mm[CONFIG_SLOT_BLACK] = regmap_get_f32(&hr[REG_HR_SLOT_BLACK_MM]);
    c->slot_mm[CONFIG_SLOT_WHITE] = regmap_get_f32(&hr[REG_HR_SLOT_WHITE_MM]);
    c->slot_mm[CONFIG_SLOT_OPEN] = regmap_get_f32(&hr[REG_HR_SLOT_OPEN_MM]);
    c->speed_mm_s = regmap_get_f32(&hr[REG_HR_SPEED_MM_S]);
    c->accel_mm_s2 = regmap_get_f32(&hr[REG_HR_ACCEL_MM_S2]);
    c->homing_direction = (int16_t)hr[REG_HR_HOMING_DIRECTION];
    c->homing_timeout_ms = hr[REG_HR_HOMING_TIMEOUT_MS];
    c->homing_speed_mm_s = regmap_get_f32(&hr[REG_HR_HOMING_SPEED_MM_S]);
    c->homing_backoff_mm = regmap_get_f32(&hr[REG_HR_HOMING_BACKOFF_MM]);
    c->servo_open_us[HAL_SHUTTER_PANEL_LEFT] = hr[REG_HR_SERVO_PANEL_LEFT_OPEN_US];
    c->servo_closed_us[HAL_SHUTTER_PANEL_LEFT] = hr[REG_HR_SERVO_PANEL_LEFT_CLOSED_US];
    c->servo_open_us[HAL_SHUTTER_PANEL_RIGHT] = hr[REG_HR_SERVO_PANEL_RIGHT_OPEN_US];
    c->servo_closed_us[HAL_SHUTTER_PANEL_RIGHT] = hr[REG_HR_SERVO_PANEL_RIGHT_CLOSED_US];
    c->servo_open_us[HAL_SHUTTER_COLLIMATED] = hr[REG_HR_SERVO_COLLIMATED_OPEN_US];
    c->servo_closed_us[HAL_SHUTTER_COLLIMATED] = hr[REG_HR_SERVO_COLLIMATED_CLOSED_US];
    c->shutter_settle_ms = hr[REG_HR_SHUTTER_SETTLE_MS];
    c->motion_settle_ms = hr[REG_HR_MOTION_SETTLE_MS];
    c->led_settle_ms = hr[REG_HR_LED_SETTLE_MS];
    c->led_pwm_hz = hr[REG_HR_LED_PWM_HZ];
    c->modbus_address = (uint8_t)hr[REG_HR_MODBUS_ADDRESS];
    c->modbus_baud = regmap_get_u32(&hr[REG_HR_MODBUS_BAUD]);
    static const uint16_t wl[C12880_WL_COEFFS] = {REG_HR_SPECTRO_WL_A0, REG_HR_SPECTRO_WL_B1, REG_HR_SPECTRO_WL_B2,
                                                  REG_HR_SPECTRO_WL_B3, REG_HR_SPECTRO_WL_B4, REG_HR_SPECTRO_WL_B5};
    for (int i = 0; i < C12880_WL_COEFFS; i++) c->spectro_wl[i] = regmap_get_f32(&hr[wl[i]]);
}

static int32_t mm_to_steps(float mm, float steps_per_mm)
{
    float s = mm * steps_per_mm;
    return (int32_t)(s < 0 ? s - 0.5f : s + 0.5f);
}

static float homing_speed(const config_t *c)
{
    return c->homing_speed_mm_s < c->speed_mm_s ? c->homing_speed_mm_s : c->speed_mm_s;
}

void config_motion(const config_t *c, motion_config_t *m)
{
    float homing = homing_speed(c);
    float spm = c->steps_per_mm;
    *m = (motion_config_t){
        .max_speed_sps = (uint32_t)(c->speed_mm_s * spm + 0.5f),
        .accel_sps2 = (uint32_t)(c->accel_mm_s2 * spm + 0.5f),
        .homing_speed_sps = (uint32_t)(homing * spm + 0.5f),
        .homing_timeout_ms = c->homing_timeout_ms,
        .max_travel_steps = mm_to_steps(CONFIG_TRAVEL_MM + CONFIG_SEEK_MARGIN_MM, spm),
        .backoff_steps = mm_to_steps(c->homing_backoff_mm, spm),
        .soft_min_steps = mm_to_steps(c->homing_backoff_mm, spm),
        .soft_max_steps = mm_to_steps(CONFIG_TRAVEL_MM, spm),
        .stall_tolerance_steps = mm_to_steps(CONFIG_STALL_TOLERANCE_MM, spm),
        .home_is_positive = c->homing_direction > 0,
    };
}

int32_t config_slot_steps(const config_t *c, enum config_slot slot)
{
    return mm_to_steps(c->slot_mm[slot], c->steps_per_mm);
}

bool config_check(const config_t *c, const char **field)
{
    static const char *const slot_names[CONFIG_SLOT_COUNT] = {"slot_black_mm", "slot_white_mm", "slot_open_mm"};
    const char *bad = NULL;
    motion_config_t m;
    config_motion(c, &m);
    if (c->homing_direction != -1 && c->homing_direction != 1) bad = "homing_direction";
    else if (!(c->steps_per_mm >= REG_HR_STEPS_PER_MM_MIN && c->steps_per_mm <= REG_HR_STEPS_PER_MM_MAX))
        bad = "steps_per_mm";
    else if (m.max_speed_sps == 0 || motion_config_valid(&m) != MOTION_OK) bad = "speed_mm_s";
    else if (m.accel_sps2 == 0) bad = "accel_mm_s2";
    else if (c->modbus_address < 1 || c->modbus_address > 247) bad = "modbus_address";
    /* a seek over the whole travel that can't end before the timeout would fail every homing */
    else if (!((CONFIG_TRAVEL_MM + CONFIG_SEEK_MARGIN_MM) / homing_speed(c) * 1000.0f < (float)c->homing_timeout_ms))
        bad = "homing_timeout_ms";
    else if (!c12880_wavelengths_valid(c->spectro_wl)) bad = "spectro_wl_a0";
    for (int s = 0; !bad && s < CONFIG_SLOT_COUNT; s++) {
        /* inside the back-off the endstop would trip a normal move */
        int32_t steps = config_slot_steps(c, (enum config_slot)s);
        if (!(c->slot_mm[s] >= c->homing_backoff_mm) || steps < m.soft_min_steps || steps > m.soft_max_steps)
            bad = slot_names[s];
    }
    if (field) *field = bad;
    return bad == NULL;
}

/* Every persisted register within its declared range (storage is not trusted). */
static bool saved_words_in_range(const uint16_t hr[REG_HR_SPAN])
{
    for (unsigned i = 0; i < REGMAP_ENTRY_COUNT; i++) {
        const regmap_entry_t *e = &regmap_entries[i];
        if (e->table != REGMAP_HOLDING_REGISTER || e->address < STORAGE_CONFIG_FIRST) continue;
        if (regmap_check_write_regs(e->address, e->words, &hr[e->address]) != 0) return false;
    }
    return true;
}

trimeter_config_source_t config_load(uint16_t hr[REG_HR_SPAN], storage_t *st)
{
    trimeter_config_source_t source =
        st->config_valid ? TRIMETER_CONFIG_SOURCE_REFUSED
        : st->config_other_map ? TRIMETER_CONFIG_SOURCE_OTHER_REGISTER_MAP : TRIMETER_CONFIG_SOURCE_DEFAULTS;
    config_defaults(hr);
    if (st->config_valid) {
        static uint16_t candidate[REG_HR_SPAN];
        config_t c;
        memcpy(candidate, hr, sizeof candidate);
        memcpy(&candidate[STORAGE_CONFIG_FIRST], st->config, sizeof st->config);
        config_decode(candidate, &c);
        if (saved_words_in_range(candidate) && config_check(&c, NULL)) {
            memcpy(hr, candidate, sizeof candidate);
            return TRIMETER_CONFIG_SOURCE_SAVED;
        }
    }
    memcpy(st->config, &hr[STORAGE_CONFIG_FIRST], sizeof st->config);
    st->config_stored = false; /* what runs is not what is saved */
    return source;
}

int config_save(const uint16_t hr[REG_HR_SPAN], storage_t *st)
{
    /* the saved copy already says this: no erase, no program (flash wears out by erases) */
    if (st->config_stored && memcmp(st->config, &hr[STORAGE_CONFIG_FIRST], sizeof st->config) == 0) return STORAGE_OK;
    uint16_t previous[STORAGE_CONFIG_WORDS];
    memcpy(previous, st->config, sizeof previous);
    memcpy(st->config, &hr[STORAGE_CONFIG_FIRST], sizeof st->config);
    int rc = storage_commit(st);
    if (rc != STORAGE_OK) memcpy(st->config, previous, sizeof previous);
    return rc;
}
