/* The plant model and its JSON-lines control protocol; see README.md (the protocol's contract). */
#include "plant.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "app.h"

#define SERVO_DEG_PER_S 300.0
#define SHUTTER_OPEN_TOLERANCE_DEG 2.0
#define SLOT_TOLERANCE_MM 0.5
#define END_MARGIN_MM 1.0 /* mechanical ends this far beyond the endstop / the travel */
#define MONITOR_DARK_COUNTS 60.0   /* photodiode stage offset + stray light, shutter closed */
#define MONITOR_SPAN_COUNTS 3200.0 /* added by a nominal lamp at full level through an open shutter */
#define MONITOR_NOISE_COUNTS 2.0   /* ADC noise per sample (standard deviation) */
#define MONITOR_ADC_MAX 4095.0
#define LAMP_EMISSION_MAX 2.0

static const char *const shutter_names[HAL_SHUTTER_COUNT] = {"panel_left", "panel_right", "collimated"};

static double pulse_to_deg(uint16_t us) { return (us - 1000.0) * 180.0 / 1000.0; }

void plant_init(plant_t *p, double steps_per_mm, double start_mm)
{
    memset(p, 0, sizeof *p);
    p->steps_per_mm = steps_per_mm;
    p->travel_mm = REG_HR_SLOT_OPEN_MM_MAX;
    p->position_steps = llround(start_mm * steps_per_mm);
    p->min_steps = -llround(END_MARGIN_MM * steps_per_mm);
    p->max_steps = llround((p->travel_mm + END_MARGIN_MM) * steps_per_mm);
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) p->shutter_angle_deg[s] = 0.0;
    for (int l = 0; l < HAL_LED_COUNT; l++) p->lamp_emission[l] = 1.0;
    p->shutter_leaking = -1;
    p->noise_state = 0x9E3779B97F4A7C15ull;
}

void plant_update(plant_t *p, uint64_t now_us)
{
    double dt = (now_us - p->last_update_us) * 1e-6;
    p->last_update_us = now_us;
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) {
        if (p->servo_pulse_us[s] == 0) continue; /* unpowered: holds */
        double target = pulse_to_deg(p->servo_pulse_us[s]);
        double d = target - p->shutter_angle_deg[s], max = SERVO_DEG_PER_S * dt;
        p->shutter_angle_deg[s] += d > max ? max : d < -max ? -max : d;
    }
    if (p->button_release_us && now_us >= p->button_release_us) p->button_release_us = 0;
}

void plant_step(plant_t *p)
{
    p->driver_stalled = p->stepper_enabled && p->stuck_slider;
    if (!p->stepper_enabled || p->stuck_slider) return;
    int64_t next = p->position_steps + (p->dir_positive ? 1 : -1);
    if (next >= p->min_steps && next <= p->max_steps) p->position_steps = next; /* else: against the end */
}

bool plant_endstop(const plant_t *p) { return !p->endstop_broken && p->position_steps <= 0; }

bool plant_button(const plant_t *p, uint64_t now_us)
{
    return p->button_held || (p->button_release_us && now_us < p->button_release_us);
}

/* xorshift64*: uniform in (0, 1) */
static double uniform(plant_t *p)
{
    uint64_t x = p->noise_state;
    x ^= x >> 12, x ^= x << 25, x ^= x >> 27;
    p->noise_state = x;
    return ((x * 0x2545F4914F6CDD1Dull >> 11) + 0.5) / 9007199254740992.0;
}

/* How far the shutter's blade uncovers its aperture: 0 at the closed angle, 1 at the open angle. */
static double shutter_opening(const plant_t *p, int s)
{
    if (s == p->shutter_leaking) return 1.0;
    const app_t *a = app_get();
    double open = pulse_to_deg(a->cfg.servo_open_us[s]), closed = pulse_to_deg(a->cfg.servo_closed_us[s]);
    if (fabs(open - closed) < 1e-9) return 0.0;
    double f = (p->shutter_angle_deg[s] - closed) / (open - closed);
    return f < 0 ? 0 : f > 1 ? 1 : f;
}

double plant_shutter_opening(const plant_t *p, enum hal_shutter s) { return shutter_opening(p, (int)s); }

int plant_slot(const plant_t *p)
{
    static const float slots_mm[3] = {REG_HR_SLOT_BLACK_MM_DEFAULT, REG_HR_SLOT_WHITE_MM_DEFAULT,
                                      REG_HR_SLOT_OPEN_MM_DEFAULT};
    double mm = p->position_steps / p->steps_per_mm;
    for (int s = 0; s < 3; s++)
        if (fabs(mm - slots_mm[s]) <= SLOT_TOLERANCE_MM) return s;
    return -1;
}

uint16_t plant_lamp_monitor(plant_t *p, enum hal_led lamp)
{
    /* each LED channel sits behind the shutter of the same index (hal.h) */
    double light = MONITOR_SPAN_COUNTS * p->led_permille[lamp] / 1000.0 * p->lamp_emission[lamp] *
                   shutter_opening(p, (int)lamp);
    double gauss = sqrt(-2.0 * log(uniform(p))) * cos(6.283185307179586 * uniform(p));
    double counts = MONITOR_DARK_COUNTS + light + MONITOR_NOISE_COUNTS * gauss;
    return (uint16_t)lround(counts < 0 ? 0 : counts > MONITOR_ADC_MAX ? MONITOR_ADC_MAX : counts);
}

/* ---------------------------------------------------------------- a flat JSON object reader */

enum jtype { J_STRING, J_BOOL, J_NUMBER, J_NULL };
typedef struct {
    char key[32];
    enum jtype type;
    char str[64];
    bool boolean;
    double number;
} jfield_t;

static const char *skip_ws(const char *s)
{
    while (*s == ' ' || *s == '\t' || *s == '\r' || *s == '\n') s++;
    return s;
}

/* A JSON string without escapes beyond \" and \\ (all our keys and values are plain words). */
static const char *read_string(const char *s, char *out, size_t cap)
{
    size_t n = 0;
    if (*s++ != '"') return NULL;
    while (*s && *s != '"') {
        char c = *s++;
        if (c == '\\') {
            c = *s++;
            if (c != '"' && c != '\\' && c != '/') return NULL;
        }
        if (n + 1 >= cap) return NULL;
        out[n++] = c;
    }
    if (*s != '"') return NULL;
    out[n] = 0;
    return s + 1;
}

/* Returns the number of fields, or -1 with *error set. */
static int parse_object(const char *s, jfield_t *fields, int max, const char **error)
{
    int count = 0;
    s = skip_ws(s);
    if (*s++ != '{') return *error = "request is not a JSON object", -1;
    s = skip_ws(s);
    if (*s == '}') return skip_ws(s + 1)[0] ? (*error = "trailing data after the object", -1) : 0;
    for (;;) {
        if (count == max) return *error = "too many fields", -1;
        jfield_t *f = &fields[count];
        s = skip_ws(s);
        if (!(s = read_string(s, f->key, sizeof f->key))) return *error = "bad JSON: expected a field name", -1;
        s = skip_ws(s);
        if (*s++ != ':') return *error = "bad JSON: expected ':'", -1;
        s = skip_ws(s);
        if (*s == '"') {
            f->type = J_STRING;
            if (!(s = read_string(s, f->str, sizeof f->str))) return *error = "bad JSON string value", -1;
        } else if (!strncmp(s, "true", 4)) {
            f->type = J_BOOL, f->boolean = true, s += 4;
        } else if (!strncmp(s, "false", 5)) {
            f->type = J_BOOL, f->boolean = false, s += 5;
        } else if (!strncmp(s, "null", 4)) {
            f->type = J_NULL, s += 4;
        } else {
            char *end;
            f->type = J_NUMBER;
            f->number = strtod(s, &end);
            if (end == s || !isfinite(f->number)) return *error = "bad JSON value (objects/arrays not accepted)", -1;
            s = end;
        }
        count++;
        s = skip_ws(s);
        if (*s == ',') {
            s++;
            continue;
        }
        if (*s++ != '}') return *error = "bad JSON: expected ',' or '}'", -1;
        if (*skip_ws(s)) return *error = "trailing data after the object", -1;
        return count;
    }
}

/* ---------------------------------------------------------------- replies */

static const char *fault_name(trimeter_fault_t f)
{
    switch (f) {
    case TRIMETER_FAULT_HOMING_TIMEOUT: return "homing_timeout";
    case TRIMETER_FAULT_ENDSTOP_HIT: return "endstop_hit";
    case TRIMETER_FAULT_STALL: return "stall";
    case TRIMETER_FAULT_SOFT_LIMIT: return "soft_limit";
    case TRIMETER_FAULT_STORAGE: return "storage";
    default: return NULL;
    }
}

static const char *slot_name(const plant_t *p)
{
    static const char *const names[3] = {"\"black\"", "\"white\"", "\"open\""};
    int s = plant_slot(p);
    return s < 0 ? "null" : names[s];
}

static size_t reply_state(const plant_t *p, uint64_t now_us, char *out, size_t cap)
{
    const app_t *a = app_get();
    size_t n = 0;
#define APPEND(...)                                                           \
    do {                                                                      \
        int k_ = snprintf(out + n, n < cap ? cap - n : 0, __VA_ARGS__);       \
        if (k_ > 0) n += (size_t)k_;                                          \
    } while (0)
    APPEND("{\"ok\":true,\"time_s\":%.6f,\"position_mm\":%.4f,\"position_steps\":%lld,\"endstop\":%s,",
           now_us * 1e-6, p->position_steps / p->steps_per_mm, (long long)p->position_steps,
           plant_endstop(p) ? "true" : "false");
    APPEND("\"shutters\":{");
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) {
        double open_deg = pulse_to_deg(a->cfg.servo_open_us[s]);
        bool open = fabs(p->shutter_angle_deg[s] - open_deg) <= SHUTTER_OPEN_TOLERANCE_DEG;
        APPEND("%s\"%s\":{\"angle_deg\":%.2f,\"open\":%s}", s ? "," : "", shutter_names[s], p->shutter_angle_deg[s],
               open ? "true" : "false");
    }
    double left = p->led_permille[HAL_LED_PANEL_LEFT] / 1000.0, right = p->led_permille[HAL_LED_PANEL_RIGHT] / 1000.0;
    APPEND("},\"leds\":{\"panels\":%.3f,\"panel_left\":%.3f,\"panel_right\":%.3f,\"collimated\":%.3f},",
           (left + right) / 2, left, right, p->led_permille[HAL_LED_COLLIMATED] / 1000.0);
    const char *fault = fault_name(app_fault());
    APPEND("\"status_led\":%s,\"status_pattern\":\"%s\",\"button\":%s,", p->status_led ? "true" : "false",
           trimeter_status_pattern_name(a->act.pattern), plant_button(p, now_us) ? "true" : "false");
    if (fault) APPEND("\"fault\":\"%s\",", fault);
    else APPEND("\"fault\":null,");
    APPEND("\"lamp_monitor\":{\"panel_left\":%u,\"panel_right\":%u,\"collimated\":%u},",
           lamp_monitor_counts(&a->lamp_monitor, HAL_LED_PANEL_LEFT),
           lamp_monitor_counts(&a->lamp_monitor, HAL_LED_PANEL_RIGHT),
           lamp_monitor_counts(&a->lamp_monitor, HAL_LED_COLLIMATED));
    APPEND("\"lamp_emission\":{\"panel_left\":%.4f,\"panel_right\":%.4f,\"collimated\":%.4f},",
           p->lamp_emission[HAL_LED_PANEL_LEFT], p->lamp_emission[HAL_LED_PANEL_RIGHT],
           p->lamp_emission[HAL_LED_COLLIMATED]);
    if (p->shutter_leaking >= 0) APPEND("\"shutter_leaking\":\"%s\",", shutter_names[p->shutter_leaking]);
    else APPEND("\"shutter_leaking\":null,");
    APPEND("\"fault_code\":%d,\"state\":\"%s\",\"homed\":%s,\"slot\":%s,\"stuck_slider\":%s,\"endstop_broken\":%s}\n",
           (int)app_fault(), trimeter_state_name(app_state()), a->motion.homed ? "true" : "false", slot_name(p),
           p->stuck_slider ? "true" : "false", p->endstop_broken ? "true" : "false");
#undef APPEND
    return n < cap ? n : cap - 1;
}

static size_t reply_error(const char *msg, char *out, size_t cap)
{
    int n = snprintf(out, cap, "{\"ok\":false,\"error\":\"%s\"}\n", msg);
    return n > 0 && (size_t)n < cap ? (size_t)n : cap - 1;
}

static size_t reply_ok(char *out, size_t cap) { return (size_t)snprintf(out, cap, "{\"ok\":true}\n"); }

static int shutter_index(const char *name)
{
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++)
        if (!strcmp(name, shutter_names[s])) return s;
    return -1;
}

/* "lamp_<LED channel>" → the channel (the LED channels share the shutters' names), else -1. */
static int lamp_field(const char *key)
{
    return strncmp(key, "lamp_", 5) ? -1 : shutter_index(key + 5);
}

size_t plant_handle_request(plant_t *p, const char *line, uint64_t now_us, char *out, size_t cap,
                            bool *reset_requested)
{
    jfield_t fields[8];
    const char *error = NULL;
    *reset_requested = false;
    int count = parse_object(line, fields, 8, &error);
    if (count < 0) return reply_error(error, out, cap);
    const jfield_t *cmd = NULL;
    for (int i = 0; i < count; i++)
        if (!strcmp(fields[i].key, "cmd")) cmd = &fields[i];
    if (!cmd || cmd->type != J_STRING) return reply_error("missing field: cmd (a string)", out, cap);

    if (!strcmp(cmd->str, "state")) {
        if (count != 1) return reply_error("state takes no fields", out, cap);
        return reply_state(p, now_us, out, cap);
    }
    if (!strcmp(cmd->str, "press_button")) {
        double hold_ms = 100;
        for (int i = 0; i < count; i++) {
            if (&fields[i] == cmd) continue;
            if (strcmp(fields[i].key, "hold_ms")) return reply_error("unknown field for press_button", out, cap);
            if (fields[i].type != J_NUMBER || fields[i].number <= 0 || fields[i].number > 600000)
                return reply_error("hold_ms: a number of milliseconds, 0 < hold_ms <= 600000", out, cap);
            hold_ms = fields[i].number;
        }
        p->button_release_us = now_us + (uint64_t)(hold_ms * 1000.0);
        return reply_ok(out, cap);
    }
    if (!strcmp(cmd->str, "set")) {
        /* validate everything first: a bad request changes nothing */
        for (int i = 0; i < count; i++) {
            if (&fields[i] == cmd) continue;
            const char *k = fields[i].key;
            if (lamp_field(k) >= 0) {
                if (fields[i].type != J_NUMBER || fields[i].number < 0 || fields[i].number > LAMP_EMISSION_MAX)
                    return reply_error("lamp_* fields take a number 0..2 (emission relative to nominal)", out, cap);
            } else if (!strcmp(k, "shutter_leaking")) {
                if (fields[i].type != J_NULL && (fields[i].type != J_STRING || shutter_index(fields[i].str) < 0))
                    return reply_error("shutter_leaking: panel_left, panel_right, collimated or null", out, cap);
            } else if (strcmp(k, "stuck_slider") && strcmp(k, "endstop_broken") && strcmp(k, "button")) {
                return reply_error("unknown field for set (stuck_slider, endstop_broken, button, lamp_panel_left, "
                                   "lamp_panel_right, lamp_collimated, shutter_leaking)", out, cap);
            } else if (fields[i].type != J_BOOL) {
                return reply_error("stuck_slider, endstop_broken and button take true/false", out, cap);
            }
        }
        for (int i = 0; i < count; i++) {
            const char *k = fields[i].key;
            if (!strcmp(k, "stuck_slider")) p->stuck_slider = fields[i].boolean;
            if (!strcmp(k, "endstop_broken")) p->endstop_broken = fields[i].boolean;
            if (!strcmp(k, "button")) p->button_held = fields[i].boolean;
            if (lamp_field(k) >= 0) p->lamp_emission[lamp_field(k)] = fields[i].number;
            if (!strcmp(k, "shutter_leaking"))
                p->shutter_leaking = fields[i].type == J_NULL ? -1 : shutter_index(fields[i].str);
        }
        return reply_ok(out, cap);
    }
    if (!strcmp(cmd->str, "reset")) {
        if (count != 1) return reply_error("reset takes no fields", out, cap);
        *reset_requested = true;
        return reply_ok(out, cap);
    }
    return reply_error("unknown cmd (state, press_button, set, reset)", out, cap);
}
