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
    static const float slots_mm[3] = {REG_HR_SLOT_BLACK_MM_DEFAULT, REG_HR_SLOT_WHITE_MM_DEFAULT,
                                      REG_HR_SLOT_OPEN_MM_DEFAULT};
    static const char *const names[3] = {"\"black\"", "\"white\"", "\"open\""};
    double mm = p->position_steps / p->steps_per_mm;
    for (int s = 0; s < 3; s++)
        if (fabs(mm - slots_mm[s]) <= SLOT_TOLERANCE_MM) return names[s];
    return "null";
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
            if (strcmp(fields[i].key, "stuck_slider") && strcmp(fields[i].key, "endstop_broken") &&
                strcmp(fields[i].key, "button"))
                return reply_error("unknown field for set (stuck_slider, endstop_broken, button)", out, cap);
            if (fields[i].type != J_BOOL) return reply_error("set fields take true/false", out, cap);
        }
        for (int i = 0; i < count; i++) {
            if (!strcmp(fields[i].key, "stuck_slider")) p->stuck_slider = fields[i].boolean;
            if (!strcmp(fields[i].key, "endstop_broken")) p->endstop_broken = fields[i].boolean;
            if (!strcmp(fields[i].key, "button")) p->button_held = fields[i].boolean;
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
