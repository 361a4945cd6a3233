/* The application; see app.h for the command semantics. */
#include "app.h"

#include <string.h>

#include "map_table.h"
#include "regmap.h"

static app_t app;

const app_t *app_get(void) { return &app; }

static uint32_t now(void) { return app.hal->now_us(app.hal->ctx); }

/* ---------------------------------------------------------------- Modbus byte I/O */

static size_t io_read(void *ctx, uint8_t *buf, size_t max)
{
    const hal_t *h = ctx;
    return h->uart_read(h->ctx, buf, max);
}

static void io_write(void *ctx, const uint8_t *buf, size_t n)
{
    /* The port buffers a whole reply (hal.h); a short write would be a port bug, and dropping the
     * tail makes the master see a CRC error and retry rather than hang here. */
    const hal_t *h = ctx;
    (void)h->uart_write(h->ctx, buf, n);
}

static uint32_t io_now(void *ctx)
{
    const hal_t *h = ctx;
    return h->now_us(h->ctx);
}

/* ---------------------------------------------------------------- state */

trimeter_fault_t app_fault(void)
{
    if (app.motion.fault != MOTION_FAULT_NONE) return (trimeter_fault_t)app.motion.fault;
    return app.app_fault;
}

bool app_busy(void) { return motion_busy(&app.motion) || actuators_busy(&app.act) || app.pending_command; }

trimeter_state_t app_state(void)
{
    if (app_fault() != TRIMETER_FAULT_NONE) return TRIMETER_STATE_FAULT;
    switch (app.motion.state) {
    case MOTION_HOMING_SEEK:
    case MOTION_HOMING_BACKOFF: return TRIMETER_STATE_HOMING;
    case MOTION_MOVING: return TRIMETER_STATE_MOVING;
    default: break;
    }
    if (app.pending_command) return TRIMETER_STATE_MOVING;
    return actuators_busy(&app.act) ? TRIMETER_STATE_SETTLING : TRIMETER_STATE_IDLE;
}

static trimeter_slot_t believed_slot(void)
{
    if (!app.motion.homed || motion_busy(&app.motion)) return TRIMETER_SLOT_UNKNOWN;
    int32_t tolerance = (int32_t)(CONFIG_SLOT_TOLERANCE_MM * app.cfg.steps_per_mm + 0.5f);
    for (int s = 0; s < CONFIG_SLOT_COUNT; s++) {
        int32_t d = app.motion.position - config_slot_steps(&app.cfg, (enum config_slot)s);
        if (d >= -tolerance && d <= tolerance) return (trimeter_slot_t)(TRIMETER_SLOT_BLACK + s);
    }
    return TRIMETER_SLOT_UNKNOWN;
}

/* ---------------------------------------------------------------- outputs */

static uint16_t led_level(enum hal_led led)
{
    return led == HAL_LED_COLLIMATED ? app.hr[REG_HR_LED_COLLIMATED_LEVEL] : app.hr[REG_HR_LED_PANELS_LEVEL];
}

static void refresh_leds(void)
{
    for (int l = 0; l < HAL_LED_COUNT; l++)
        actuators_set_led(&app.act, (enum hal_led)l, app.act.led_on[l], led_level((enum hal_led)l),
                          app.cfg.led_settle_ms, now());
}

static void set_shutter(enum hal_shutter s, bool open)
{
    uint16_t pulse = open ? app.cfg.servo_open_us[s] : app.cfg.servo_closed_us[s];
    actuators_set_shutter(&app.act, s, open, pulse, app.cfg.shutter_settle_ms, now());
}

/* Every lamp on (a lamp that was off starts its warm-up again); the shutters are left as they are. */
static void lamps_on(void)
{
    for (int l = 0; l < HAL_LED_COUNT; l++)
        actuators_set_led(&app.act, (enum hal_led)l, true, led_level((enum hal_led)l), app.cfg.led_settle_ms, now());
}

static bool lamps_lit(void)
{
    for (int l = 0; l < HAL_LED_COUNT; l++)
        if (!app.act.led_on[l]) return false;
    return true;
}

static uint16_t warmup_remaining_s(void)
{
    uint16_t warmup = app.hr[REG_HR_STANDALONE_WARMUP_S];
    return app.lamps_lit_s >= warmup ? 0u : (uint16_t)(warmup - app.lamps_lit_s);
}

/* ---------------------------------------------------------------- unlock window */

static bool unlock_window_open(void) { return app.unlock_open && now() - app.unlock_us < APP_UNLOCK_WINDOW_US; }

/* This destructive write just ran in the open window: a retry, acknowledged without running it. */
static bool unlock_repeat(uint16_t reg, uint16_t value)
{
    bool repeat = app.retry_candidate && unlock_window_open() && app.unlock_spent && app.spent_reg == reg &&
                  app.spent_value == value;
    if (repeat) app.spent_was_last = true;
    return repeat;
}

/* May this destructive write run now? Consumes the window. */
static bool unlock_take(uint16_t reg, uint16_t value)
{
    if (!unlock_window_open() || app.unlock_spent || mb_request_is_broadcast(&app.mb)) return false;
    app.unlock_spent = app.spent_was_last = true;
    app.spent_reg = reg;
    app.spent_value = value;
    return true;
}

static void unlock_close(void) { app.unlock_open = app.unlock_spent = app.spent_was_last = false; }

/* Every write the device takes starts here: only a write right after the destructive one can be its retry. */
static void write_arrives(void)
{
    app.retry_candidate = app.spent_was_last;
    app.spent_was_last = false;
}

static bool destructive_command(uint16_t command)
{
    return command == TRIMETER_COMMAND_SAVE_CONFIG || command == TRIMETER_COMMAND_LOAD_DEFAULTS;
}

/* ---------------------------------------------------------------- commands */

static uint8_t start_motion(int command)
{
    motion_config_t mc;
    config_motion(&app.cfg, &mc);
    if (motion_configure(&app.motion, &mc) != MOTION_OK) return MB_EX_SERVER_DEVICE_FAILURE;
    int rc;
    if (command == TRIMETER_COMMAND_HOME) {
        rc = motion_home(&app.motion);
    } else {
        enum config_slot slot = (enum config_slot)(command - TRIMETER_COMMAND_GOTO_BLACK);
        rc = motion_move_to(&app.motion, config_slot_steps(&app.cfg, slot));
    }
    switch (rc) {
    case MOTION_OK: return MB_OK;
    case MOTION_ERR_LIMIT:
    case MOTION_ERR_CONFIG: return MB_EX_ILLEGAL_DATA_VALUE;
    default: return MB_EX_ILLEGAL_FUNCTION; /* faulted, not homed: the wrong state for this */
    }
}

static uint8_t run_command(uint16_t command)
{
    switch (command) {
    case TRIMETER_COMMAND_NONE: return MB_OK;
    case TRIMETER_COMMAND_HOME:
    case TRIMETER_COMMAND_GOTO_BLACK:
    case TRIMETER_COMMAND_GOTO_WHITE:
    case TRIMETER_COMMAND_GOTO_OPEN:
        if (app_fault() != TRIMETER_FAULT_NONE) return MB_EX_ILLEGAL_FUNCTION;
        if (app.press_step) return MB_EX_SERVER_DEVICE_BUSY; /* a standalone press moves the slider */
        if (motion_busy(&app.motion)) {
            app.pending_command = command; /* runs when the current motion ends */
            return MB_OK;
        }
        if (command != TRIMETER_COMMAND_HOME && !app.motion.homed) return MB_EX_ILLEGAL_FUNCTION;
        return start_motion(command);
    case TRIMETER_COMMAND_STOP:
        app.pending_command = 0;
        motion_stop_smooth(&app.motion); /* ramps down: no lost steps, position stays true */
        return MB_OK;
    case TRIMETER_COMMAND_CLEAR_FAULT:
        motion_clear_fault(&app.motion);
        app.app_fault = TRIMETER_FAULT_NONE;
        return MB_OK;
    case TRIMETER_COMMAND_SAVE_CONFIG: {
        if (unlock_repeat(REG_HR_COMMAND, command)) return MB_OK;
        if (motion_busy(&app.motion)) return MB_EX_ILLEGAL_FUNCTION;
        if (!unlock_take(REG_HR_COMMAND, command)) return MB_EX_ILLEGAL_FUNCTION;
        int rc = config_save(app.hr, &app.storage);
        if (rc != STORAGE_OK) unlock_close();
        if (rc == STORAGE_ERR_BUSY) return MB_EX_SERVER_DEVICE_BUSY; /* nothing erased: not a fault */
        if (rc != STORAGE_OK) {
            app.app_fault = TRIMETER_FAULT_STORAGE;
            return MB_EX_SERVER_DEVICE_FAILURE;
        }
        app.config_source = TRIMETER_CONFIG_SOURCE_SAVED;
        return MB_OK;
    }
    case TRIMETER_COMMAND_LOAD_DEFAULTS: {
        if (unlock_repeat(REG_HR_COMMAND, command)) return MB_OK;
        if (!unlock_take(REG_HR_COMMAND, command)) return MB_EX_ILLEGAL_FUNCTION;
        static uint16_t defaults[REG_HR_SPAN];
        config_defaults(defaults);
        memcpy(&app.hr[STORAGE_CONFIG_FIRST], &defaults[STORAGE_CONFIG_FIRST], STORAGE_CONFIG_WORDS * sizeof(uint16_t));
        config_decode(app.hr, &app.cfg);
        app.config_source = TRIMETER_CONFIG_SOURCE_DEFAULTS;
        return MB_OK;
    }
    default: return MB_EX_ILLEGAL_DATA_VALUE;
    }
}

static void run_map_command(uint16_t command)
{
    storage_t *st = &app.storage;
    int rc;
    switch (command) {
    case TRIMETER_MAP_COMMAND_BEGIN_WRITE:
        if (unlock_repeat(REG_HR_MAP_COMMAND, command)) return;
        /* Flash erase stalls the CPU on the MCU: never while the step timer must run. */
        if (motion_busy(&app.motion) || fit_busy(&app.fit)) {
            app.map_op_status = TRIMETER_MAP_OP_STATUS_ERROR_STATE;
            return;
        }
        if (!unlock_take(REG_HR_MAP_COMMAND, command)) {
            app.map_op_status = TRIMETER_MAP_OP_STATUS_ERROR_LOCKED;
            return;
        }
        rc = storage_map_begin(st, &app.upload, regmap_get_u32(&app.hr[REG_HR_MAP_EXPECTED_LENGTH]),
                               regmap_get_u32(&app.hr[REG_HR_MAP_EXPECTED_CRC32]), app.hr[REG_HR_MAP_VERSION]);
        if (rc != STORAGE_OK) unlock_close();
        app.map_op_status = rc == STORAGE_OK         ? TRIMETER_MAP_OP_STATUS_WRITING
                            : rc == STORAGE_ERR_BUSY ? TRIMETER_MAP_OP_STATUS_ERROR_BUSY
                                                     : TRIMETER_MAP_OP_STATUS_ERROR_STORAGE;
        return;
    case TRIMETER_MAP_COMMAND_VERIFY:
        if (!app.upload.open) {
            app.map_op_status = TRIMETER_MAP_OP_STATUS_ERROR_STATE;
            return;
        }
        rc = storage_map_verify(st, &app.upload);
        app.map_op_status = rc == STORAGE_OK             ? TRIMETER_MAP_OP_STATUS_VERIFY_OK
                            : rc == STORAGE_ERR_MISMATCH ? TRIMETER_MAP_OP_STATUS_VERIFY_FAILED
                            : rc == STORAGE_ERR_FORMAT   ? TRIMETER_MAP_OP_STATUS_ERROR_TABLE
                                                         : TRIMETER_MAP_OP_STATUS_ERROR_STORAGE;
        return;
    case TRIMETER_MAP_COMMAND_ACTIVATE:
        if (unlock_repeat(REG_HR_MAP_COMMAND, command)) return;
        if (!app.upload.open || !app.upload.verified || motion_busy(&app.motion) || fit_busy(&app.fit)) {
            app.map_op_status = TRIMETER_MAP_OP_STATUS_ERROR_STATE;
            return;
        }
        if (!unlock_take(REG_HR_MAP_COMMAND, command)) {
            app.map_op_status = TRIMETER_MAP_OP_STATUS_ERROR_LOCKED;
            return;
        }
        rc = storage_map_activate(st, &app.upload);
        if (rc != STORAGE_OK) unlock_close();
        app.map_op_status = rc == STORAGE_OK         ? TRIMETER_MAP_OP_STATUS_ACTIVATED
                            : rc == STORAGE_ERR_BUSY ? TRIMETER_MAP_OP_STATUS_ERROR_BUSY
                                                     : TRIMETER_MAP_OP_STATUS_ERROR_STORAGE;
        return;
    case TRIMETER_MAP_COMMAND_ABORT:
        storage_map_abort(&app.upload);
        app.map_op_status = TRIMETER_MAP_OP_STATUS_IDLE;
        return;
    default: return;
    }
}

static uint8_t run_fit_command(uint16_t command)
{
    switch (command) {
    case TRIMETER_FIT_COMMAND_RUN:
        /* a fit's bins and results belong to one master's exchange: a broadcast has no reply to wait on */
        if (mb_request_is_broadcast(&app.mb)) return MB_EX_ILLEGAL_FUNCTION;
        return fit_start(&app.fit, &app.storage, app.hr[REG_HR_FIT_BIN_COUNT],
                         regmap_get_f32(&app.hr[REG_HR_FIT_THICKNESS_MM]));
    case TRIMETER_FIT_COMMAND_ABORT: fit_abort(&app.fit); return MB_OK;
    default: return MB_OK;
    }
}

static uint8_t run_spectro_command(uint16_t command)
{
    const hal_t *h = app.hal;
    uint32_t integration_us = regmap_get_u32(&app.hr[REG_HR_SPECTRO_INTEGRATION_US]);
    uint16_t frames = app.hr[REG_HR_SPECTRO_FRAMES], gain = app.hr[REG_HR_SPECTRO_GAIN];
    switch (command) {
    case TRIMETER_SPECTRO_COMMAND_CAPTURE:
    case TRIMETER_SPECTRO_COMMAND_CAPTURE_DARK: {
        if (mb_request_is_broadcast(&app.mb)) return MB_EX_ILLEGAL_FUNCTION;
        bool dark = command == TRIMETER_SPECTRO_COMMAND_CAPTURE_DARK;
        uint8_t ex = c12880_start(&app.spectro, h, dark, frames, integration_us, gain, now());
        if (!ex && dark)
            for (int s = 0; s < HAL_SHUTTER_COUNT; s++) set_shutter((enum hal_shutter)s, false);
        return ex;
    }
    case TRIMETER_SPECTRO_COMMAND_ABORT: c12880_abort(&app.spectro); return MB_OK;
    default: return MB_OK;
    }
}

/* ---------------------------------------------------------------- Modbus data callbacks */

static bool get_bit(const uint8_t *bits, unsigned i) { return (bits[i / 8] >> (i % 8)) & 1u; }

uint8_t app_read_bits(void *ctx, mb_table_t table, uint16_t addr, uint16_t n, uint8_t *out)
{
    (void)ctx;
    uint8_t ex = regmap_check_read((regmap_table_t)table, addr, n);
    if (ex) return ex;
    memset(out, 0, (n + 7u) / 8u);
    for (unsigned i = 0; i < n; i++) {
        unsigned a = addr + i;
        bool v = false;
        if (table == MB_TABLE_COILS) {
            if (a <= REG_COIL_SHUTTER_COLLIMATED_OPEN) v = app.act.shutter_open[a - REG_COIL_SHUTTER_PANEL_LEFT_OPEN];
            else if (a <= REG_COIL_LED_COLLIMATED_ON) v = app.act.led_on[a - REG_COIL_LED_PANEL_LEFT_ON];
        } else {
            switch (a) {
            case REG_DI_ENDSTOP: v = app.hal->endstop_active(app.hal->ctx); break;
            case REG_DI_BUTTON_PRESSED: v = app.act.button_stable; break;
            case REG_DI_BUSY: v = app_busy(); break;
            case REG_DI_FAULT: v = app_fault() != TRIMETER_FAULT_NONE; break;
            case REG_DI_HOMED: v = app.motion.homed; break;
            default: break;
            }
        }
        if (v) out[i / 8] |= (uint8_t)(1u << (i % 8));
    }
    return MB_OK;
}

uint8_t app_write_bits(void *ctx, uint16_t addr, uint16_t n, const uint8_t *bits)
{
    (void)ctx;
    uint8_t ex = regmap_check_write_bits(addr, n);
    if (ex) return ex;
    write_arrives();
    bool want[HAL_LED_COUNT];
    for (int l = 0; l < HAL_LED_COUNT; l++) want[l] = app.act.led_on[l];
    for (unsigned i = 0; i < n; i++) {
        unsigned a = addr + i;
        bool v = get_bit(bits, i);
        if (a <= REG_COIL_SHUTTER_COLLIMATED_OPEN)
            set_shutter((enum hal_shutter)(a - REG_COIL_SHUTTER_PANEL_LEFT_OPEN), v);
        else
            want[a - REG_COIL_LED_PANEL_LEFT_ON] = v;
    }
    /* All LEDs of one write switch together; an unchanged LED doesn't restart the settle. */
    for (int l = 0; l < HAL_LED_COUNT; l++)
        actuators_set_led(&app.act, (enum hal_led)l, want[l], led_level((enum hal_led)l), app.cfg.led_settle_ms,
                          now());
    return MB_OK;
}

static void fill_input_registers(uint16_t *ir)
{
    const mb_counters_t *c = mb_counters(&app.mb);
    memset(ir, 0, REG_IR_SPAN * sizeof *ir);
    ir[REG_IR_VENDOR_ID] = TRIMETER_VENDOR_ID;
    ir[REG_IR_MODEL_ID] = TRIMETER_MODEL_ID;
    ir[REG_IR_FIRMWARE_VERSION_MAJOR] = TRIMETER_FIRMWARE_VERSION_MAJOR;
    ir[REG_IR_FIRMWARE_VERSION_MINOR] = TRIMETER_FIRMWARE_VERSION_MINOR;
    ir[REG_IR_FIRMWARE_VERSION_PATCH] = TRIMETER_FIRMWARE_VERSION_PATCH;
    regmap_put_u32(&ir[REG_IR_REGMAP_HASH], TRIMETER_REGMAP_HASH);
    ir[REG_IR_STATE] = (uint16_t)app_state();
    ir[REG_IR_FAULT_CODE] = (uint16_t)app_fault();
    regmap_put_u32(&ir[REG_IR_POSITION_STEPS], (uint32_t)app.motion.position);
    ir[REG_IR_POSITION_SLOT] = (uint16_t)believed_slot();
    ir[REG_IR_BUTTON_EVENTS] = app.act.button_events;
    regmap_put_u32(&ir[REG_IR_UPTIME_S], app.uptime_s);
    ir[REG_IR_MODBUS_FRAMES_OK] = (uint16_t)c->frames_ok;
    ir[REG_IR_MODBUS_CRC_ERRORS] = (uint16_t)(c->crc_errors + c->overruns);
    ir[REG_IR_MODBUS_EXCEPTIONS] = (uint16_t)c->exceptions;
    ir[REG_IR_CONFIG_SOURCE] = (uint16_t)app.config_source;
    int active = storage_map_active(&app.storage);
    ir[REG_IR_MAP_ACTIVE_SLOT] = (uint16_t)(active < 0 ? TRIMETER_MAP_SLOT_NONE : TRIMETER_MAP_SLOT_A + active);
    static const uint16_t base[STORAGE_MAP_SLOTS] = {REG_IR_MAP_SLOT_A_VALID, REG_IR_MAP_SLOT_B_VALID};
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++) {
        /* same layout for both slots: valid, length (u32), crc32 (u32), version */
        const storage_map_slot_t *m = &app.storage.map[s];
        bool valid = app.storage.map_valid[s];
        ir[base[s]] = valid;
        regmap_put_u32(&ir[base[s] + (REG_IR_MAP_SLOT_A_LENGTH - REG_IR_MAP_SLOT_A_VALID)], valid ? m->length : 0);
        regmap_put_u32(&ir[base[s] + (REG_IR_MAP_SLOT_A_CRC32 - REG_IR_MAP_SLOT_A_VALID)], valid ? m->crc32 : 0);
        ir[base[s] + (REG_IR_MAP_SLOT_A_VERSION - REG_IR_MAP_SLOT_A_VALID)] = valid ? m->version : 0;
    }
    ir[REG_IR_MAP_OP_STATUS] = app.map_op_status;
    static const uint16_t wear[HAL_REGION_COUNT] = {REG_IR_ERASE_COUNT_CONFIG_A, REG_IR_ERASE_COUNT_CONFIG_B,
                                                    REG_IR_ERASE_COUNT_MAP_A, REG_IR_ERASE_COUNT_MAP_B};
    for (int r = 0; r < HAL_REGION_COUNT; r++) regmap_put_u32(&ir[wear[r]], app.storage.erase_count[r]);
    ir[REG_IR_ERASE_REFUSALS] = app.storage.erase_refusals;
    regmap_put_u32(&ir[REG_IR_MAP_OP_BYTES_WRITTEN], app.upload.open ? app.upload.bytes_written : 0);
    ir[REG_IR_LAMP_MONITOR_PANEL_LEFT] = lamp_monitor_counts(&app.lamp_monitor, HAL_LED_PANEL_LEFT);
    ir[REG_IR_LAMP_MONITOR_PANEL_RIGHT] = lamp_monitor_counts(&app.lamp_monitor, HAL_LED_PANEL_RIGHT);
    ir[REG_IR_LAMP_MONITOR_COLLIMATED] = lamp_monitor_counts(&app.lamp_monitor, HAL_LED_COLLIMATED);
    ir[REG_IR_FIT_STATUS] = (uint16_t)app.fit.status;
    ir[REG_IR_FIT_BINS_DONE] = app.fit.done;
    ir[REG_IR_FIT_AVAILABLE] = fit_available();
    regmap_put_u32(&ir[REG_IR_FIT_TABLE_CRC32], app.fit.table ? app.fit.table_crc32 : 0);
    const c12880_t *sp = &app.spectro;
    uint32_t clock_hz = app.hal->spectro_clock_hz ? app.hal->spectro_clock_hz(app.hal->ctx) : 0u;
    ir[REG_IR_SPECTRO_STATUS] = (uint16_t)sp->status;
    ir[REG_IR_SPECTRO_FRAMES_DONE] = sp->frames_done;
    ir[REG_IR_SPECTRO_PEAK_COUNTS] = sp->peak;
    ir[REG_IR_SPECTRO_DARK_VALID] = sp->dark_valid;
    regmap_put_u32(&ir[REG_IR_SPECTRO_CAPTURE_US], sp->capture_us);
    ir[REG_IR_SPECTRO_SEQUENCE] = sp->sequence;
    ir[REG_IR_SPECTRO_PIXELS] = clock_hz ? C12880_PIXELS : 0u;
    regmap_put_u32(&ir[REG_IR_SPECTRO_CLOCK_HZ], clock_hz);
    const standalone_t *st = &app.standalone;
    ir[REG_IR_STANDALONE_STATUS] = (uint16_t)st->status;
    ir[REG_IR_STANDALONE_BINS] = st->bins;
    ir[REG_IR_STANDALONE_SEQUENCE] = st->sequence;
    ir[REG_IR_STANDALONE_CALIBRATED] = st->calibrated;
    regmap_put_f32(&ir[REG_IR_STANDALONE_THICKNESS_MM], st->thickness_mm);
    regmap_put_u32(&ir[REG_IR_STANDALONE_TABLE_CRC32], st->table_crc32);
    ir[REG_IR_STANDALONE_FLAGGED_BINS] = st->flagged_bins;
    static const uint16_t integration[STANDALONE_SETUPS] = {
        REG_IR_STANDALONE_INTEGRATION_BLACK_US, REG_IR_STANDALONE_INTEGRATION_WHITE_US,
        REG_IR_STANDALONE_INTEGRATION_OPEN_US};
    for (int k = 0; k < STANDALONE_SETUPS; k++) regmap_put_u32(&ir[integration[k]], st->integration_us[k]);
    static const uint16_t lamp_level[HAL_LED_COUNT] = {REG_IR_STANDALONE_LAMP_PANEL_LEFT, REG_IR_STANDALONE_LAMP_PANEL_RIGHT,
                                                       REG_IR_STANDALONE_LAMP_COLLIMATED};
    for (int l = 0; l < HAL_LED_COUNT; l++) regmap_put_f32(&ir[lamp_level[l]], st->lamp_level[l]);
    ir[REG_IR_STANDALONE_CHECK] = (uint16_t)st->check;
    regmap_put_f32(&ir[REG_IR_STANDALONE_CHECK_VALUE], st->check_value);
    ir[REG_IR_STANDALONE_WARMUP_REMAINING_S] = lamps_lit() ? warmup_remaining_s() : app.hr[REG_HR_STANDALONE_WARMUP_S];
}

uint8_t app_read_regs(void *ctx, mb_table_t table, uint16_t addr, uint16_t n, uint16_t *out)
{
    (void)ctx;
    uint8_t ex = regmap_check_read((regmap_table_t)table, addr, n);
    if (ex) return ex;
    if (table == MB_TABLE_HOLDING_REGISTERS) {
        memcpy(out, &app.hr[addr], n * sizeof *out);
    } else {
        static uint16_t ir[REG_IR_SPAN];
        fill_input_registers(ir);
        memcpy(out, &ir[addr], n * sizeof *out);
    }
    return MB_OK;
}

static bool covers(uint16_t addr, uint16_t n, uint16_t reg) { return reg >= addr && reg < addr + n; }

/* What a broadcast may never do (storage, unlocking); vals is the request's words from addr. */
static bool broadcast_forbidden(uint16_t addr, uint16_t n, const uint16_t *vals)
{
    if (covers(addr, n, REG_HR_UNLOCK)) return true;
    if (covers(addr, n, REG_HR_COMMAND) && destructive_command(vals[REG_HR_COMMAND - addr])) return true;
    return covers(addr, n, REG_HR_MAP_COMMAND) && vals[REG_HR_MAP_COMMAND - addr] != TRIMETER_MAP_COMMAND_NONE;
}

uint8_t app_write_regs(void *ctx, uint16_t addr, uint16_t n, const uint16_t *vals)
{
    (void)ctx;
    static uint16_t before[REG_HR_SPAN];
    uint8_t ex = regmap_check_write_regs(addr, n, vals);
    if (ex) return ex;
    if (mb_request_is_broadcast(&app.mb) && broadcast_forbidden(addr, n, vals)) return MB_EX_ILLEGAL_FUNCTION;
    write_arrives();
    memcpy(before, app.hr, sizeof before);
    memcpy(&app.hr[addr], vals, n * sizeof *vals);
    config_t candidate;
    config_decode(app.hr, &candidate);
    if (!config_check(&candidate, NULL)) {
        memcpy(app.hr, before, sizeof before);
        return MB_EX_ILLEGAL_DATA_VALUE;
    }
    config_t previous = app.cfg;
    app.cfg = candidate;
    if (covers(addr, n, REG_HR_COMMAND)) ex = run_command(app.hr[REG_HR_COMMAND]);
    if (!ex && covers(addr, n, REG_HR_FIT_COMMAND)) ex = run_fit_command(app.hr[REG_HR_FIT_COMMAND]);
    if (!ex && covers(addr, n, REG_HR_SPECTRO_COMMAND)) ex = run_spectro_command(app.hr[REG_HR_SPECTRO_COMMAND]);
    if (ex) {
        memcpy(app.hr, before, sizeof before);
        app.cfg = previous;
        return ex;
    }
    if (covers(addr, n, REG_HR_MAP_COMMAND)) run_map_command(app.hr[REG_HR_MAP_COMMAND]);
    /* standalone presses: the lamps come on now and stay on, so they are warm by the first press */
    if (covers(addr, n, REG_HR_STANDALONE_MODE) && app.hr[REG_HR_STANDALONE_MODE] != TRIMETER_STANDALONE_MODE_OFF)
        lamps_on();
    if (covers(addr, n, REG_HR_UNLOCK)) {
        /* after this write's commands: an unlock serves the requests that follow it */
        unlock_close();
        if (app.hr[REG_HR_UNLOCK] == TRIMETER_UNLOCK_KEY) {
            app.unlock_open = true;
            app.unlock_us = now();
        }
        app.hr[REG_HR_UNLOCK] = TRIMETER_UNLOCK_LOCKED; /* the key is not left readable */
    }
    if (covers(addr, n, REG_HR_LED_PANELS_LEVEL) || covers(addr, n, REG_HR_LED_COLLIMATED_LEVEL) ||
        app.cfg.led_settle_ms != previous.led_settle_ms)
        refresh_leds();
    return MB_OK;
}

/* File records → bytes of a map slot: record k holds bytes 2k (high) and 2k+1 (low). */
static bool record_span(uint16_t file, uint16_t record, uint16_t n, uint32_t length, uint32_t *offset)
{
    uint32_t k = (uint32_t)(file - 1u) * TRIMETER_MAP_RECORDS_PER_FILE + record;
    uint32_t records = (length + 1u) / 2u;
    if (file == 0 || k >= records || n > records - k) return false;
    *offset = 2u * k;
    return true;
}

uint8_t app_read_file(void *ctx, uint16_t file, uint16_t record, uint16_t n, uint16_t *out)
{
    (void)ctx;
    static uint8_t bytes[2 * 125];
    if (fit_is_file(file)) return fit_read_records(&app.fit, file, record, n, out);
    if (c12880_is_file(file)) return c12880_read_records(&app.spectro, file, record, n, out);
    if (standalone_is_file(file)) return standalone_read_records(&app.standalone, file, record, n, out);
    uint16_t which = app.hr[REG_HR_MAP_READ_SLOT];
    int slot = which == TRIMETER_MAP_SLOT_NONE ? storage_map_active(&app.storage) : (int)which - TRIMETER_MAP_SLOT_A;
    uint32_t offset;
    if (slot < 0 || !app.storage.map_valid[slot] || n > 125) return MB_EX_ILLEGAL_DATA_ADDRESS;
    uint32_t length = app.storage.map[slot].length;
    if (!record_span(file, record, n, length, &offset)) return MB_EX_ILLEGAL_DATA_ADDRESS;
    uint32_t count = 2u * n;
    if (offset + count > length) count = length - offset; /* the odd tail's pad byte */
    memset(bytes, 0, sizeof bytes);
    if (storage_map_read(&app.storage, slot, offset, bytes, count) != STORAGE_OK) return MB_EX_SERVER_DEVICE_FAILURE;
    for (unsigned i = 0; i < n; i++) out[i] = (uint16_t)((bytes[2 * i] << 8) | bytes[2 * i + 1]);
    return MB_OK;
}

uint8_t app_write_file(void *ctx, uint16_t file, uint16_t record, uint16_t n, const uint16_t *vals)
{
    (void)ctx;
    static uint8_t bytes[2 * 125];
    uint32_t offset;
    if (c12880_is_file(file) || standalone_is_file(file)) return MB_EX_ILLEGAL_DATA_ADDRESS; /* read-only */
    if (fit_is_file(file)) {
        if (mb_request_is_broadcast(&app.mb)) return MB_EX_ILLEGAL_FUNCTION;
        write_arrives();
        return fit_write_records(&app.fit, file, record, n, vals);
    }
    if (!app.upload.open || mb_request_is_broadcast(&app.mb)) return MB_EX_ILLEGAL_FUNCTION; /* no begin_write */
    write_arrives();
    if (n > 125 || !record_span(file, record, n, app.upload.expected_length, &offset))
        return MB_EX_ILLEGAL_DATA_ADDRESS;
    for (unsigned i = 0; i < n; i++) {
        bytes[2 * i] = (uint8_t)(vals[i] >> 8);
        bytes[2 * i + 1] = (uint8_t)vals[i];
    }
    uint32_t count = 2u * n;
    if (offset + count > app.upload.expected_length) count = app.upload.expected_length - offset;
    if (storage_map_session_write(&app.storage, &app.upload, offset, bytes, count) != STORAGE_OK) {
        app.map_op_status = TRIMETER_MAP_OP_STATUS_ERROR_STORAGE;
        return MB_EX_SERVER_DEVICE_FAILURE;
    }
    app.map_op_status = TRIMETER_MAP_OP_STATUS_WRITING;
    return MB_OK;
}

/* ---------------------------------------------------------------- standalone presses */

enum press_step { PRESS_NONE, PRESS_WARMING, PRESS_HOMING, PRESS_MOVING, PRESS_LIGHTS, PRESS_CAPTURE, PRESS_DARK, PRESS_FIT };

/* Auto-exposure: a saturated capture is taken again at half the time, one whose brightest pixel is below
 * PRESS_DIM_FRACTION of full scale at twice the time (while that stays within the register's range and
 * below saturation by linearity), at most PRESS_EXPOSURE_TRIES captures per set-up. */
#define PRESS_DIM_FRACTION 0.4f
#define PRESS_EXPOSURE_TRIES 6

/* The shutters of one set-up: the panels' (black, white) or the collimated beam's (open); both false: dark.
 * The lamps stay on throughout, as the host's sequences keep them: a lamp switched per set-up would be
 * captured cold, and its photodiode could not be compared with the calibration's. */
static void press_lights(bool panels, bool collimated)
{
    bool open[HAL_SHUTTER_COUNT] = {[HAL_SHUTTER_PANEL_LEFT] = panels, [HAL_SHUTTER_PANEL_RIGHT] = panels,
                                    [HAL_SHUTTER_COLLIMATED] = collimated};
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) set_shutter((enum hal_shutter)s, open[s]); /* shutter l covers LED l */
    lamps_on();
}

/* The lamp-monitor photodiodes at the end of a capture: behind the set-up's open shutters (lit) or every one
 * closed (dark). */
static void press_read_lamps(bool dark)
{
    standalone_t *st = &app.standalone;
    for (int l = 0; l < HAL_LED_COUNT; l++) {
        uint16_t counts = lamp_monitor_counts(&app.lamp_monitor, (enum hal_led)l);
        if (dark) st->lamp_dark[l] = counts;
        else if (app.act.shutter_open[l]) st->lamp_lit[l] = counts;
    }
}

static void press_end(trimeter_standalone_status_t status)
{
    press_lights(false, false);
    if (app.spectro.running) c12880_abort(&app.spectro);
    app.press_step = PRESS_NONE;
    app.standalone.status = status;
    app.standalone.sequence++;
}

static bool motion_idle(void)
{
    return !motion_busy(&app.motion) && !actuators_busy(&app.act) && !app.pending_command;
}

static void press_move(void)
{
    uint8_t ex = start_motion(TRIMETER_COMMAND_GOTO_BLACK + app.press_setup);
    if (ex) press_end(TRIMETER_STANDALONE_STATUS_ERROR_MOTION);
    else app.press_step = PRESS_MOVING;
}

static uint8_t press_capture(bool dark)
{
    app.press_tries++;
    return c12880_start(&app.spectro, app.hal, dark, app.hr[REG_HR_SPECTRO_FRAMES],
                        app.standalone.integration_us[app.press_setup], app.hr[REG_HR_SPECTRO_GAIN], now());
}

/* After a light capture: a new integration time to capture again with, or 0 to keep this one. */
static uint32_t press_exposure_change(void)
{
    uint32_t t = app.standalone.integration_us[app.press_setup];
    if (app.press_tries >= PRESS_EXPOSURE_TRIES) return 0;
    if (app.spectro.status == TRIMETER_SPECTRO_STATUS_SATURATED) return t / 2u >= REG_HR_SPECTRO_INTEGRATION_US_MIN ? t / 2u : 0;
    bool dim = (float)app.spectro.peak < PRESS_DIM_FRACTION * (float)C12880_ADC_FULL_SCALE;
    return dim && t <= REG_HR_SPECTRO_INTEGRATION_US_MAX / 2u ? 2u * t : 0;
}

static bool capture_ok(void)
{
    return app.spectro.status == TRIMETER_SPECTRO_STATUS_DONE || app.spectro.status == TRIMETER_SPECTRO_STATUS_SATURATED;
}

/* A press of the button: starts a standalone press when the mode asks for one and nothing stops it. */
static void press_begin(void)
{
    uint16_t mode = app.hr[REG_HR_STANDALONE_MODE];
    standalone_t *st = &app.standalone;
    if (mode == TRIMETER_STANDALONE_MODE_OFF || app.press_step) return;
    uint32_t length = 0;
    const uint8_t *table = storage_map_active_bytes(&app.storage, &length);
    uint32_t clock_hz = app.hal->spectro_clock_hz ? app.hal->spectro_clock_hz(app.hal->ctx) : 0u;
    trimeter_standalone_status_t refusal = TRIMETER_STANDALONE_STATUS_NONE;
    if (app_fault() != TRIMETER_FAULT_NONE) refusal = TRIMETER_STANDALONE_STATUS_ERROR_MOTION;
    else if (!table || !fit_available()) refusal = TRIMETER_STANDALONE_STATUS_ERROR_NO_TABLE;
    else if (mode == TRIMETER_STANDALONE_MODE_MEASURE && !st->calibrated)
        refusal = TRIMETER_STANDALONE_STATUS_ERROR_NO_CALIBRATION;
    else if (!clock_hz) refusal = TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO;
    if (refusal) {
        st->status = refusal;
        return;
    }
    app.press_calibrating = mode == TRIMETER_STANDALONE_MODE_CALIBRATE || mode == TRIMETER_STANDALONE_MODE_CALIBRATE_FORCE;
    app.press_setup = STANDALONE_BLACK;
    st->status = TRIMETER_STANDALONE_STATUS_BUSY;
    for (int k = 0; k < STANDALONE_SETUPS; k++) st->integration_us[k] = regmap_get_u32(&app.hr[REG_HR_SPECTRO_INTEGRATION_US]);
    press_lights(false, false);
    /* A real instrument waits rather than flags: the operator pressed once and gets a trustworthy result a
     * few minutes later (the LED says busy) instead of a flagged one and a second press; and a calibration
     * taken cold would bias every measurement after it without any later check seeing it. */
    app.press_step = PRESS_WARMING;
}

/* The press's first move, once the lamps are warm. */
static void press_home(void)
{
    if (app.motion.homed) {
        app.press_step = PRESS_HOMING; /* waits for any motion a host started, then moves */
    } else if (!motion_busy(&app.motion) && start_motion(TRIMETER_COMMAND_HOME) != MB_OK) {
        press_end(TRIMETER_STANDALONE_STATUS_ERROR_MOTION);
    } else {
        app.press_step = PRESS_HOMING;
    }
}

/* The fit of a measurement press, once its captures are reduced. */
static void press_fit(void)
{
    standalone_t *st = &app.standalone;
    uint32_t length = 0;
    const uint8_t *table = storage_map_active_bytes(&app.storage, &length);
    if (!table) {
        press_end(TRIMETER_STANDALONE_STATUS_ERROR_NO_TABLE);
        return;
    }
    uint16_t n = standalone_fit_input(st, app.fit.in);
    st->thickness_mm = map_table_thickness_mm(table);
    if (fit_start(&app.fit, &app.storage, n, st->thickness_mm) != MB_OK) {
        st->table_crc32 = 0;
        press_end(TRIMETER_STANDALONE_STATUS_ERROR_FIT);
        return;
    }
    st->table_crc32 = app.fit.table_crc32;
    app.press_step = PRESS_FIT;
}

static void press_poll(void)
{
    standalone_t *st = &app.standalone;
    if (app.press_step == PRESS_NONE) return;
    if (app_fault() != TRIMETER_FAULT_NONE) {
        if (app.press_step == PRESS_FIT) fit_abort(&app.fit);
        press_end(TRIMETER_STANDALONE_STATUS_ERROR_MOTION);
        return;
    }
    switch (app.press_step) {
    case PRESS_WARMING:
        if (!lamps_lit()) lamps_on(); /* a host switched one off: its warm-up starts again */
        else if (warmup_remaining_s() == 0) press_home();
        return;
    case PRESS_HOMING:
        if (!motion_idle()) return;
        if (!app.motion.homed) {
            press_end(TRIMETER_STANDALONE_STATUS_ERROR_MOTION);
            return;
        }
        press_move();
        return;
    case PRESS_MOVING:
        if (!motion_idle()) return;
        press_lights(app.press_setup != STANDALONE_OPEN, app.press_setup == STANDALONE_OPEN);
        app.press_tries = 0;
        app.press_step = PRESS_LIGHTS;
        return;
    case PRESS_LIGHTS:
        if (actuators_busy(&app.act)) return;
        if (press_capture(false) != MB_OK) {
            press_end(TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO);
            return;
        }
        app.press_step = PRESS_CAPTURE;
        return;
    case PRESS_CAPTURE: {
        if (c12880_busy(&app.spectro)) return;
        if (!capture_ok()) {
            press_end(TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO);
            return;
        }
        uint32_t again = press_exposure_change();
        if (again) {
            st->integration_us[app.press_setup] = again;
            if (press_capture(false) != MB_OK) press_end(TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO);
            return;
        }
        memcpy(st->light[app.press_setup], app.spectro.light, sizeof st->light[0]);
        press_read_lamps(false);
        press_lights(false, false); /* every shutter closed: the dark capture waits for them to settle */
        if (press_capture(true) != MB_OK) {
            press_end(TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO);
            return;
        }
        app.press_step = PRESS_DARK;
        return;
    }
    case PRESS_DARK: {
        if (c12880_busy(&app.spectro)) return;
        if (!capture_ok()) {
            press_end(TRIMETER_STANDALONE_STATUS_ERROR_SPECTRO);
            return;
        }
        memcpy(st->dark[app.press_setup], app.spectro.dark, sizeof st->dark[0]);
        press_read_lamps(true);
        if (++app.press_setup < STANDALONE_SETUPS) {
            press_move();
            return;
        }
        standalone_reduce(st, app.cfg.spectro_wl);
        if (!app.press_calibrating) {
            press_fit();
            return;
        }
        /* a refused calibration leaves the mode as it was: the operator empties the holder and presses again */
        if (standalone_calibrate(st, regmap_get_f32(&app.hr[REG_HR_WHITE_REFERENCE_REFLECTANCE]),
                                 app.hr[REG_HR_STANDALONE_MODE] != TRIMETER_STANDALONE_MODE_CALIBRATE_FORCE))
            app.hr[REG_HR_STANDALONE_MODE] = TRIMETER_STANDALONE_MODE_MEASURE;
        press_end(st->status);
        return;
    }
    case PRESS_FIT:
        if (fit_busy(&app.fit)) return;
        if (app.fit.status != TRIMETER_FIT_STATUS_DONE) {
            press_end(TRIMETER_STANDALONE_STATUS_ERROR_FIT);
            return;
        }
        standalone_take_fit(st, app.fit.out, app.fit.done);
        press_end(st->status);
        return;
    default: return;
    }
}

/* ---------------------------------------------------------------- lifecycle */

void app_init(const hal_t *hal)
{
    memset(&app, 0, sizeof app);
    app.hal = hal;
    app.boot_us = app.uptime_mark_us = hal->now_us(hal->ctx);
    hal->step_timer_stop(hal->ctx);

    storage_load(&app.storage, hal);
    app.config_source = config_load(app.hr, &app.storage);
    config_decode(app.hr, &app.cfg);

    motion_config_t mc;
    config_motion(&app.cfg, &mc);
    motion_init(&app.motion, hal, &mc);
    actuators_init(&app.act, hal, app.boot_us);
    lamp_monitor_init(&app.lamp_monitor);
    fit_init(&app.fit);
    c12880_init(&app.spectro);
    standalone_init(&app.standalone);
    for (int s = 0; s < HAL_SHUTTER_COUNT; s++) set_shutter((enum hal_shutter)s, false);

    app.mb_io = (mb_io_t){.read = io_read, .write = io_write, .now_us = io_now, .ctx = (void *)hal};
    app.mb_app = (mb_app_t){
        .read_bits = app_read_bits,
        .write_bits = app_write_bits,
        .read_regs = app_read_regs,
        .write_regs = app_write_regs,
        .read_file = app_read_file,
        .write_file = app_write_file,
        .vendor = TRIMETER_VENDOR_NAME,
        .product = TRIMETER_PRODUCT_CODE,
        .revision = TRIMETER_FIRMWARE_VERSION,
        .vendor_url = TRIMETER_VENDOR_URL,
        .product_name = TRIMETER_PRODUCT_NAME,
        .ctx = &app,
    };
    mb_init(&app.mb, app.cfg.modbus_address, app.cfg.modbus_baud, &app.mb_io, &app.mb_app);
}

void app_override_modbus_address(uint8_t address)
{
    if (address >= 1 && address <= MB_ADDRESS_MAX) mb_set_address(&app.mb, address);
}

void app_poll(void)
{
    uint32_t t = now();
    mb_poll(&app.mb);
    motion_poll(&app.motion, t);
    storage_poll(&app.storage, t);
    fit_poll(&app.fit);
    c12880_poll(&app.spectro, app.hal, !actuators_busy(&app.act), t);
    if (app.unlock_open && t - app.unlock_us >= APP_UNLOCK_WINDOW_US) unlock_close(); /* before the clock wraps */

    bool moving = motion_busy(&app.motion);
    if (app.was_moving && !moving && app.motion.state != MOTION_FAULT)
        actuators_settle(&app.act, app.cfg.motion_settle_ms, t);
    if (!moving && app.pending_command) {
        int command = app.pending_command;
        app.pending_command = 0;
        /* refused (fault, not homed): dropped; the fault / homed registers say why */
        if (app_fault() == TRIMETER_FAULT_NONE &&
            (command == TRIMETER_COMMAND_HOME || app.motion.homed))
            (void)start_motion(command);
        moving = motion_busy(&app.motion);
    }
    app.was_moving = moving;

    if (app.act.button_events != app.press_events_seen) {
        app.press_events_seen = app.act.button_events;
        press_begin();
    }
    press_poll();

    enum status_pattern pattern = (enum status_pattern)app.hr[REG_HR_STATUS_PATTERN];
    if (app.hr[REG_HR_STANDALONE_MODE] != TRIMETER_STANDALONE_MODE_OFF || app.press_step)
        pattern = (enum status_pattern)standalone_pattern(app.standalone.status);
    actuators_set_pattern(&app.act, app_fault() != TRIMETER_FAULT_NONE ? STATUS_FAST_BLINK : pattern);
    actuators_poll(&app.act, t);
    lamp_monitor_poll(&app.lamp_monitor, app.hal, t);

    /* the lamps' warm-up clock: whole seconds with every lamp on, from 0 whenever one is off */
    bool lit = lamps_lit();
    if (!lit) app.lamps_lit_s = 0;
    while (t - app.uptime_mark_us >= 1000000u) {
        app.uptime_mark_us += 1000000u;
        app.uptime_s++;
        if (lit && app.lamps_lit_s < UINT16_MAX) app.lamps_lit_s++;
    }
}

uint32_t app_step_isr(void) { return motion_isr(&app.motion); }
