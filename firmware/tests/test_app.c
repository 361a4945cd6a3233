/* The application through its Modbus data callbacks: busy flag, queued motion, fault latch and
 * clear, config validation and persistence, shutters/LEDs/button, map upload via file records. */
#include <string.h>

#include "../core/app.h"
#include "../core/crc.h"
#include "../core/regmap.h"
#include "app_fixture.h"
#include "check.h"
#include "fake_hal.h"
#include "table_fixture.h"

static fake_hal_t *f;

/* Runs until busy clears (or the limit); returns true if it did. */
static bool run_until_idle(uint32_t limit_ms)
{
    for (uint32_t i = 0; i < limit_ms; i += 10) {
        if (!app_busy()) return true;
        run_ms(10);
    }
    return !app_busy();
}

static uint8_t command(uint16_t c) { return write_reg(REG_HR_COMMAND, c); }
static void unlock(void) { CHECK_EQ_INT(write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY), MB_OK); }
/* A destructive command, unlocked right before as the host does. */
static uint8_t unlocked_command(uint16_t c)
{
    unlock();
    return command(c);
}

static uint8_t write_f32(uint16_t addr, float v)
{
    uint16_t w[2];
    regmap_put_f32(w, v);
    return app_write_regs(NULL, addr, 2, w);
}

static float read_f32_hr(uint16_t addr)
{
    uint16_t w[2];
    app_read_regs(NULL, MB_TABLE_HOLDING_REGISTERS, addr, 2, w);
    return regmap_get_f32(w);
}

static bool di(uint16_t addr)
{
    uint8_t b = 0;
    CHECK_EQ_INT(app_read_bits(NULL, MB_TABLE_DISCRETE_INPUTS, addr, 1, &b), MB_OK);
    return b & 1;
}

static uint8_t write_coil(uint16_t addr, bool v)
{
    uint8_t b = v;
    return app_write_bits(NULL, addr, 1, &b);
}

static void fresh_device(void)
{
    f = fixture_fresh_hal();
    f->carriage_steps = 3000; /* somewhere mid-travel at power-on */
    f->endstop_steps = 0;
    f->hard_stop_steps = -40;
    fixture_boot();
}

static void home_device(void)
{
    CHECK_EQ_INT(command(TRIMETER_COMMAND_HOME), MB_OK);
    CHECK(run_until_idle(30000));
    CHECK(di(REG_DI_HOMED));
}

static void test_identity_and_boot_state(void)
{
    fresh_device();
    CHECK_EQ_INT(ir(REG_IR_VENDOR_ID), TRIMETER_VENDOR_ID);
    CHECK_EQ_INT(ir32(REG_IR_REGMAP_HASH), TRIMETER_REGMAP_HASH);
    /* shutters are closed at boot and that takes the settle time */
    CHECK(di(REG_DI_BUSY));
    CHECK_EQ_INT(ir(REG_IR_STATE), TRIMETER_STATE_SETTLING);
    CHECK_EQ_INT(f->servo_us[HAL_SHUTTER_COLLIMATED], REG_HR_SERVO_COLLIMATED_CLOSED_US_DEFAULT);
    run_ms(REG_HR_SHUTTER_SETTLE_MS_DEFAULT + 2);
    CHECK(!di(REG_DI_BUSY));
    CHECK_EQ_INT(ir(REG_IR_STATE), TRIMETER_STATE_IDLE);
    CHECK(!di(REG_DI_HOMED));
    CHECK_EQ_INT(ir(REG_IR_POSITION_SLOT), TRIMETER_SLOT_UNKNOWN);
    CHECK(f->watchdog_kicks > 0);
}

static void test_motion_commands_return_at_once_with_busy(void)
{
    fresh_device();
    run_ms(500);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_BLACK), MB_EX_ILLEGAL_FUNCTION); /* not homed */
    uint64_t t0 = f->now_us;
    CHECK_EQ_INT(command(TRIMETER_COMMAND_HOME), MB_OK);
    CHECK_EQ_INT(f->now_us, t0); /* no simulated time passed inside the callback */
    CHECK(di(REG_DI_BUSY));
    CHECK_EQ_INT(ir(REG_IR_STATE), TRIMETER_STATE_HOMING);
    CHECK(run_until_idle(30000));
    CHECK(di(REG_DI_HOMED));
    CHECK_EQ_INT(f->carriage_steps, 160); /* back-off 2 mm at 80 steps/mm */

    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_WHITE), MB_OK);
    CHECK(di(REG_DI_BUSY));
    CHECK_EQ_INT(ir(REG_IR_STATE), TRIMETER_STATE_MOVING);
    CHECK_EQ_INT(ir(REG_IR_POSITION_SLOT), TRIMETER_SLOT_UNKNOWN);
    run_ms(100);
    CHECK(ir32(REG_IR_POSITION_STEPS) > 160 && ir32(REG_IR_POSITION_STEPS) < 4800);
    CHECK(run_until_idle(30000));
    CHECK_EQ_INT((int32_t)ir32(REG_IR_POSITION_STEPS), 4800); /* 60 mm */
    CHECK_EQ_INT(f->carriage_steps, 4800);
    CHECK_EQ_INT(ir(REG_IR_POSITION_SLOT), TRIMETER_SLOT_WHITE);
    CHECK_EQ_INT(app_read_regs(NULL, MB_TABLE_HOLDING_REGISTERS, REG_HR_COMMAND, 1, &(uint16_t){0}), MB_OK);
}

static void test_settle_after_arrival(void)
{
    fresh_device();
    home_device();
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_BLACK), MB_OK);
    /* wait for the motion itself to end, then busy must hold motion_settle_ms longer */
    while (motion_busy(&app_get()->motion)) run_ms(1);
    CHECK(di(REG_DI_BUSY));
    CHECK_EQ_INT(ir(REG_IR_STATE), TRIMETER_STATE_SETTLING);
    run_ms(REG_HR_MOTION_SETTLE_MS_DEFAULT - 5);
    CHECK(di(REG_DI_BUSY));
    run_ms(10);
    CHECK(!di(REG_DI_BUSY));
}

static void test_command_during_motion_is_queued(void)
{
    fresh_device();
    home_device();
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_OPEN), MB_OK);
    run_ms(200);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_BLACK), MB_OK); /* accepted while moving */
    CHECK(run_until_idle(30000));
    CHECK_EQ_INT(f->carriage_steps, (int)(REG_HR_SLOT_BLACK_MM_DEFAULT * REG_HR_STEPS_PER_MM_DEFAULT + 0.5f)); /* the last command wins */
    CHECK_EQ_INT(ir(REG_IR_POSITION_SLOT), TRIMETER_SLOT_BLACK);
    /* stop drops a queued command */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_OPEN), MB_OK);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_WHITE), MB_OK);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_STOP), MB_OK);
    CHECK(run_until_idle(2000));
    CHECK(f->carriage_steps < 4800);
}

static void test_fault_latches_until_cleared(void)
{
    fresh_device();
    f->endstop_broken = true;
    CHECK_EQ_INT(command(TRIMETER_COMMAND_HOME), MB_OK);
    CHECK(run_until_idle(60000));
    CHECK(di(REG_DI_FAULT));
    CHECK_EQ_INT(ir(REG_IR_FAULT_CODE), TRIMETER_FAULT_HOMING_TIMEOUT);
    CHECK_EQ_INT(ir(REG_IR_STATE), TRIMETER_STATE_FAULT);
    run_ms(5000); /* latched: still there later */
    CHECK_EQ_INT(ir(REG_IR_FAULT_CODE), TRIMETER_FAULT_HOMING_TIMEOUT);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_HOME), MB_EX_ILLEGAL_FUNCTION);
    uint16_t cmd;
    app_read_regs(NULL, MB_TABLE_HOLDING_REGISTERS, REG_HR_COMMAND, 1, &cmd);
    CHECK_EQ_INT(cmd, TRIMETER_COMMAND_HOME); /* the refused write changed nothing */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_CLEAR_FAULT), MB_OK);
    CHECK(!di(REG_DI_FAULT));
    CHECK_EQ_INT(ir(REG_IR_FAULT_CODE), TRIMETER_FAULT_NONE);
    f->endstop_broken = false;
    home_device();
    CHECK(!di(REG_DI_FAULT));
}

static void test_stuck_slider_is_a_stall(void)
{
    fresh_device();
    home_device();
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_WHITE), MB_OK);
    CHECK(run_until_idle(30000));
    f->stuck = true;
    f->carriage_steps = 0; /* jammed at the home end without the firmware knowing */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_OPEN), MB_OK);
    CHECK(run_until_idle(30000));
    CHECK_EQ_INT(ir(REG_IR_FAULT_CODE), TRIMETER_FAULT_STALL);
    /* jammed between slots: only the driver's stall output can tell */
    fresh_device();
    f->has_stall_output = true;
    home_device();
    f->stuck = true;
    CHECK_EQ_INT(command(TRIMETER_COMMAND_GOTO_WHITE), MB_OK);
    CHECK(run_until_idle(30000));
    CHECK_EQ_INT(ir(REG_IR_FAULT_CODE), TRIMETER_FAULT_STALL);
    CHECK(di(REG_DI_FAULT));
}

static void test_config_validation(void)
{
    fresh_device();
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_BLACK_MM, 30.0f), MB_OK);
    CHECK(read_f32_hr(REG_HR_SLOT_BLACK_MM) == 30.0f);
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_BLACK_MM, 121.0f), MB_EX_ILLEGAL_DATA_VALUE); /* map max */
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_BLACK_MM, 1.0f), MB_EX_ILLEGAL_DATA_VALUE);   /* in the back-off */
    CHECK(read_f32_hr(REG_HR_SLOT_BLACK_MM) == 30.0f);
    /* 10000 steps/mm at 40 mm/s is 400 kHz of steps: no */
    CHECK_EQ_INT(write_f32(REG_HR_STEPS_PER_MM, 10000.0f), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK(read_f32_hr(REG_HR_STEPS_PER_MM) == 80.0f);
    CHECK_EQ_INT(write_reg(REG_HR_HOMING_DIRECTION, 0), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(write_reg(REG_HR_MODBUS_ADDRESS, 0), MB_EX_ILLEGAL_DATA_VALUE);
    /* a block write with one bad value changes nothing, not even the good ones before it */
    uint16_t block[6];
    regmap_put_f32(&block[0], 25.0f);  /* slot_black_mm */
    regmap_put_f32(&block[2], 65.0f);  /* slot_white_mm */
    regmap_put_f32(&block[4], 0.5f);   /* slot_open_mm: inside the back-off */
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_SLOT_BLACK_MM, 6, block), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK(read_f32_hr(REG_HR_SLOT_BLACK_MM) == 30.0f);
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 60.0f);
    /* half a wide value: address error */
    CHECK_EQ_INT(write_reg(REG_HR_SLOT_BLACK_MM, 0x4200), MB_EX_ILLEGAL_DATA_ADDRESS);
    /* the back-off is the soft lower limit: a slot inside a longer one is refused */
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_BLACK_MM, 4.0f), MB_OK);
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_BACKOFF_MM, 5.0f), MB_EX_ILLEGAL_DATA_VALUE);
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_BACKOFF_MM, 3.5f), MB_OK);
    /* a seek over the whole travel (130 mm) must end within homing_timeout_ms (10 s) */
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_SPEED_MM_S, 14.0f), MB_OK);  /* 9.3 s */
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_SPEED_MM_S, 12.0f), MB_EX_ILLEGAL_DATA_VALUE); /* 10.8 s */
    CHECK_EQ_INT(write_f32(REG_HR_SPEED_MM_S, 12.0f), MB_EX_ILLEGAL_DATA_VALUE); /* caps the seek speed too */
    CHECK_EQ_INT(write_reg(REG_HR_HOMING_TIMEOUT_MS, 30000), MB_OK);
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_SPEED_MM_S, 5.0f), MB_OK);
    CHECK(read_f32_hr(REG_HR_HOMING_SPEED_MM_S) == 5.0f);
}

static void test_homing_uses_the_configured_speed_and_back_off(void)
{
    fresh_device();
    run_ms(REG_HR_SHUTTER_SETTLE_MS_DEFAULT + 2);
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_BACKOFF_MM, 4.0f), MB_OK);
    CHECK_EQ_INT(write_f32(REG_HR_HOMING_SPEED_MM_S, 25.0f), MB_OK);
    /* seeking from 3000 steps at 25 mm/s = 2000 steps/s: 2000 steps nearer the endstop after 1 s */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_HOME), MB_OK);
    run_ms(1000);
    CHECK(f->carriage_steps > 3000 - 2000 - 60 && f->carriage_steps < 3000 - 2000 + 60);
    CHECK(run_until_idle(30000));
    CHECK(di(REG_DI_HOMED));
    /* then backed off 4 mm = 320 steps */
    CHECK_EQ_INT(ir32(REG_IR_POSITION_STEPS), 320);
    CHECK_EQ_INT(f->carriage_steps, 320);
}

static void test_config_persists_across_reboot(void)
{
    fresh_device();
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 70.0f), MB_OK);
    fixture_boot(); /* not saved: lost */
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 60.0f);
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 70.0f), MB_OK);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    fixture_boot();
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 70.0f);
    CHECK_EQ_INT(app_get()->config_source, TRIMETER_CONFIG_SOURCE_SAVED);
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_SAVED);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_LOAD_DEFAULTS), MB_OK);
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 60.0f);
    fixture_boot(); /* defaults were not saved: the saved 70 comes back */
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 70.0f);
    /* flash refuses the save: storage fault, exception 04, old copy still loads */
    f->power_budget = f->bytes_programmed + 10;
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 80.0f), MB_OK);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_SERVER_DEVICE_FAILURE);
    CHECK_EQ_INT(ir(REG_IR_FAULT_CODE), TRIMETER_FAULT_STORAGE);
    fake_hal_power_on(f);
    fixture_boot();
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 70.0f);
}

/* Edits every saved system record in the fake flash as another firmware could have left it: the
 * register-map hash (hash != 0) and/or one configuration word (word >= 0), the CRC-32 fixed so it
 * stays a valid record. Layout: storage.c (little-endian; format at 4, words at 6, hash at 12,
 * config after a 52-byte header in format 1, after the erase counts (68 bytes) in format 2). */
static void edit_saved_records(uint32_t hash, int word, uint16_t value)
{
    for (int r = 0; r < 2; r++) {
        uint8_t *b = f->config[r];
        if (!(b[0] == 0x4D && b[1] == 0x53 && b[2] == 0x54 && b[3] == 0x52)) continue; /* "MSTR" */
        uint32_t header = b[4] == 1 ? 52u : 52u + 4u * HAL_REGION_COUNT;
        uint32_t size = header + 2u * (uint32_t)(b[6] | b[7] << 8) + 4u;
        if (hash)
            for (int i = 0; i < 4; i++) b[12 + i] = (uint8_t)(hash >> (8 * i));
        if (word >= 0) {
            b[header + 2 * word] = (uint8_t)value;
            b[header + 1 + 2 * word] = (uint8_t)(value >> 8);
        }
        uint32_t crc = crc32_update(0, b, size - 4);
        for (int i = 0; i < 4; i++) b[size - 4 + i] = (uint8_t)(crc >> (8 * i));
    }
}

static void test_config_source_says_why_defaults_run(void)
{
    fresh_device();
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_DEFAULTS); /* nothing saved yet */
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 70.0f), MB_OK);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_SAVED);
    /* a firmware update that changed the register map: the saved words can't be read, defaults run */
    edit_saved_records(TRIMETER_REGMAP_HASH ^ 0x1u, -1, 0);
    fixture_boot();
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_OTHER_REGISTER_MAP);
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 60.0f);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK); /* saving anew makes it this map's */
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_SAVED);
    fixture_boot();
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_SAVED);
    /* a saved record of this map that fails the checks (homing_direction 0): refused, defaults run */
    edit_saved_records(0, REG_HR_HOMING_DIRECTION - STORAGE_CONFIG_FIRST, 0);
    fixture_boot();
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_REFUSED);
    CHECK_EQ_INT((int16_t)app_get()->hr[REG_HR_HOMING_DIRECTION], (int16_t)REG_HR_HOMING_DIRECTION_DEFAULT);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_LOAD_DEFAULTS), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_DEFAULTS);
}

static void test_shutters_leds_settle(void)
{
    fresh_device();
    run_ms(500);
    CHECK(!di(REG_DI_BUSY));
    CHECK_EQ_INT(write_coil(REG_COIL_SHUTTER_PANEL_LEFT_OPEN, true), MB_OK);
    CHECK_EQ_INT(f->servo_us[HAL_SHUTTER_PANEL_LEFT], REG_HR_SERVO_PANEL_LEFT_OPEN_US_DEFAULT);
    CHECK(di(REG_DI_BUSY));
    run_ms(REG_HR_SHUTTER_SETTLE_MS_DEFAULT + 2);
    CHECK(!di(REG_DI_BUSY));
    /* both panels in one write; level from led_panels_level */
    CHECK_EQ_INT(write_reg(REG_HR_LED_PANELS_LEVEL, 600), MB_OK);
    uint8_t both = 0x3;
    CHECK_EQ_INT(app_write_bits(NULL, REG_COIL_LED_PANEL_LEFT_ON, 2, &both), MB_OK);
    CHECK_EQ_INT(f->led_permille[HAL_LED_PANEL_LEFT], 600);
    CHECK_EQ_INT(f->led_permille[HAL_LED_PANEL_RIGHT], 600);
    CHECK_EQ_INT(f->led_permille[HAL_LED_COLLIMATED], 0);
    CHECK(di(REG_DI_BUSY));
    run_ms(REG_HR_LED_SETTLE_MS_DEFAULT + 2);
    CHECK(!di(REG_DI_BUSY));
    CHECK_EQ_INT(write_reg(REG_HR_LED_PANELS_LEVEL, 300), MB_OK); /* level change of a lit LED */
    CHECK_EQ_INT(f->led_permille[HAL_LED_PANEL_LEFT], 300);
    CHECK(di(REG_DI_BUSY));
    uint8_t coils = 0;
    CHECK_EQ_INT(app_read_bits(NULL, MB_TABLE_COILS, 0, 6, &coils), MB_OK);
    CHECK_EQ_INT(coils, 0x19); /* left shutter, both panels */
    CHECK_EQ_INT(app_write_bits(NULL, 6, 1, &both), MB_EX_ILLEGAL_DATA_ADDRESS);
}

static void test_button_debounce_and_events(void)
{
    fresh_device();
    CHECK_EQ_INT(ir(REG_IR_BUTTON_EVENTS), 0);
    /* contact bounce shorter than the debounce time: nothing */
    for (int i = 0; i < 5; i++) {
        f->button = true;
        run_ms(3);
        f->button = false;
        run_ms(3);
    }
    CHECK_EQ_INT(ir(REG_IR_BUTTON_EVENTS), 0);
    f->button = true;
    run_ms(50);
    CHECK(di(REG_DI_BUTTON_PRESSED));
    f->button = false;
    run_ms(50);
    f->button = true;
    run_ms(50);
    f->button = false;
    run_ms(50);
    CHECK_EQ_INT(ir(REG_IR_BUTTON_EVENTS), 2);
}

static void test_status_led_patterns(void)
{
    fresh_device();
    CHECK_EQ_INT(write_reg(REG_HR_STATUS_PATTERN, TRIMETER_STATUS_PATTERN_ON), MB_OK);
    run_ms(5);
    CHECK(f->status_led);
    CHECK_EQ_INT(write_reg(REG_HR_STATUS_PATTERN, TRIMETER_STATUS_PATTERN_SLOW_BLINK), MB_OK);
    int toggles = 0;
    bool last = f->status_led;
    for (int i = 0; i < 2000; i++) {
        run_ms(1);
        if (f->status_led != last) toggles++, last = f->status_led;
    }
    CHECK(toggles >= 3 && toggles <= 5); /* 1 Hz over 2 s */
    CHECK_EQ_INT(write_reg(REG_HR_STATUS_PATTERN, TRIMETER_STATUS_PATTERN_DOUBLE_BLINK), MB_OK);
    int flashes = 0, lit_ms = 0;
    last = f->status_led;
    for (int i = 0; i < 3000; i++) {
        run_ms(1);
        lit_ms += f->status_led;
        if (f->status_led && !last) flashes++;
        last = f->status_led;
    }
    CHECK(flashes >= 3 && flashes <= 5);      /* two per 1.5 s over 3 s */
    CHECK(lit_ms >= 500 && lit_ms <= 700);    /* short flashes: 600 ms lit in 3 s */
    CHECK_EQ_INT(write_reg(REG_HR_STATUS_PATTERN, TRIMETER_STATUS_PATTERN_TRIPLE_BLINK), MB_OK);
    flashes = 0, lit_ms = 0;
    last = f->status_led;
    for (int i = 0; i < 4200; i++) {
        run_ms(1);
        lit_ms += f->status_led;
        if (f->status_led && !last) flashes++;
        last = f->status_led;
    }
    CHECK(flashes >= 5 && flashes <= 7);      /* three per 2.1 s over 4.2 s */
    CHECK(lit_ms >= 800 && lit_ms <= 1000);   /* six 150 ms flashes: 900 ms lit */
    CHECK_EQ_INT(write_reg(REG_HR_STATUS_PATTERN, 9), MB_EX_ILLEGAL_DATA_VALUE);
}

#define MAP_GRID 4 /* a fixture table of 940 bytes */
#define MAP_BYTES 940
static uint8_t map_data[MAP_BYTES];

/* Writes `len` bytes of `data` into the open upload through file records, 100 records a request. */
static void upload_bytes(const uint8_t *data, uint32_t len)
{
    uint16_t regs[100];
    for (uint32_t rec = 0; rec < (len + 1) / 2; rec += 100) {
        uint32_t n = (len + 1) / 2 - rec < 100 ? (len + 1) / 2 - rec : 100;
        for (uint32_t i = 0; i < n; i++) {
            uint32_t b = 2 * (rec + i);
            regs[i] = (uint16_t)(data[b] << 8 | (b + 1 < len ? data[b + 1] : 0));
        }
        CHECK_EQ_INT(app_write_file(NULL, 1, (uint16_t)rec, (uint16_t)n, regs), MB_OK);
    }
}

/* begin_write (unlocked) of `len` bytes with their CRC; returns map_op_status. */
static uint16_t begin_upload(const uint8_t *data, uint32_t len, uint16_t version)
{
    uint16_t params[7];
    regmap_put_u32(&params[0], len);
    regmap_put_u32(&params[2], crc32_update(0, data, len));
    params[4] = version;
    params[5] = 0;
    params[6] = TRIMETER_MAP_COMMAND_BEGIN_WRITE;
    unlock();
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_MAP_EXPECTED_LENGTH, 7, params), MB_OK);
    return ir(REG_IR_MAP_OP_STATUS);
}

static void test_map_upload_over_file_records(void)
{
    fresh_device();
    CHECK_EQ_INT(fixture_table(map_data, MAP_BYTES, MAP_GRID, 9), MAP_BYTES);
    uint16_t regs[120];
    CHECK_EQ_INT(app_write_file(NULL, 1, 0, 1, regs), MB_EX_ILLEGAL_FUNCTION); /* no begin_write */
    uint16_t params[7];
    regmap_put_u32(&params[0], MAP_BYTES);
    regmap_put_u32(&params[2], crc32_update(0, map_data, MAP_BYTES));
    params[4] = 42;                               /* version */
    params[5] = 0;                                /* read slot: active */
    params[6] = TRIMETER_MAP_COMMAND_BEGIN_WRITE; /* acts after the parameters */
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_MAP_EXPECTED_LENGTH, 7, params), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_LOCKED); /* no unlock: nothing erased */
    CHECK_EQ_INT(ir32(REG_IR_ERASE_COUNT_MAP_A), 0);
    unlock();
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_MAP_EXPECTED_LENGTH, 7, params), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_WRITING);
    CHECK_EQ_INT(ir32(REG_IR_ERASE_COUNT_MAP_A), 1);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_STATE); /* not verified */
    upload_bytes(map_data, MAP_BYTES);
    CHECK_EQ_INT(app_write_file(NULL, 1, 470, 1, regs), MB_EX_ILLEGAL_DATA_ADDRESS); /* past the length */
    CHECK_EQ_INT(ir32(REG_IR_MAP_OP_BYTES_WRITTEN), MAP_BYTES);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_VERIFY_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_NONE);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_LOCKED); /* verified, but locked */
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_NONE);
    unlock();
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ACTIVATED);
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_A);
    CHECK_EQ_INT(ir(REG_IR_MAP_SLOT_A_VALID), 1);
    CHECK_EQ_INT(ir32(REG_IR_MAP_SLOT_A_LENGTH), MAP_BYTES);
    CHECK_EQ_INT(ir(REG_IR_MAP_SLOT_A_VERSION), 42);
    fixture_boot(); /* survives a reboot, and reads back record by record */
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_A);
    uint16_t back[1];
    CHECK_EQ_INT(app_read_file(NULL, 1, 469, 1, back), MB_OK); /* the last record */
    CHECK_EQ_INT(back[0], map_data[938] << 8 | map_data[939]);
    CHECK_EQ_INT(app_read_file(NULL, 1, 10, 1, back), MB_OK);
    CHECK_EQ_INT(back[0], map_data[20] << 8 | map_data[21]);
    CHECK_EQ_INT(app_read_file(NULL, 1, 470, 1, back), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_READ_SLOT, TRIMETER_MAP_SLOT_B), MB_OK);
    CHECK_EQ_INT(app_read_file(NULL, 1, 0, 1, back), MB_EX_ILLEGAL_DATA_ADDRESS); /* B is empty */
    /* a wrong CRC never activates */
    regmap_put_u32(&params[2], 0x12345678u);
    params[5] = 0;
    unlock();
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_MAP_EXPECTED_LENGTH, 7, params), MB_OK);
    regs[0] = 0x0102;
    CHECK_EQ_INT(app_write_file(NULL, 1, 0, 1, regs), MB_OK);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_VERIFY_FAILED);
    unlock();
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_STATE);
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_A);
}

/* A CRC-32 proves the bytes arrived, not that they are a table: 64 junk bytes with their right CRC-32,
 * uploaded and activated. */
static void test_junk_bytes_never_become_a_valid_map(void)
{
    fresh_device();
    static uint8_t junk[64];
    for (int i = 0; i < 64; i++) junk[i] = (uint8_t)(i * 37 + 1);
    CHECK_EQ_INT(begin_upload(junk, sizeof junk, 1), TRIMETER_MAP_OP_STATUS_WRITING);
    upload_bytes(junk, sizeof junk);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_TABLE);
    unlock();
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_STATE);
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_NONE);
    CHECK_EQ_INT(ir(REG_IR_MAP_SLOT_A_VALID), 0);
    /* a real table whose header claims another geometry (n_g 5 with the size of 4): refused too */
    CHECK_EQ_INT(fixture_table(map_data, MAP_BYTES, MAP_GRID, 3), MAP_BYTES);
    map_data[76] = 5;
    fixture_table_fix_crc(map_data, MAP_BYTES);
    CHECK_EQ_INT(begin_upload(map_data, MAP_BYTES, 2), TRIMETER_MAP_OP_STATUS_WRITING);
    upload_bytes(map_data, MAP_BYTES);
    CHECK_EQ_INT(write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY), MB_OK);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_ERROR_TABLE);
    CHECK_EQ_INT(ir(REG_IR_MAP_ACTIVE_SLOT), TRIMETER_MAP_SLOT_NONE);
}

static uint32_t erases(void)
{
    return ir32(REG_IR_ERASE_COUNT_CONFIG_A) + ir32(REG_IR_ERASE_COUNT_CONFIG_B) + ir32(REG_IR_ERASE_COUNT_MAP_A) +
           ir32(REG_IR_ERASE_COUNT_MAP_B);
}

static void test_destructive_commands_need_an_unlock_right_before(void)
{
    fresh_device();
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 70.0f), MB_OK);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_LOAD_DEFAULTS), MB_EX_ILLEGAL_FUNCTION);
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 70.0f);
    CHECK_EQ_INT(erases(), 0);
    CHECK_EQ_INT(write_reg(REG_HR_UNLOCK, 0x1234), MB_EX_ILLEGAL_DATA_VALUE); /* a wrong key */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_ILLEGAL_FUNCTION);
    /* unlock and command in one request: the unlock serves only later requests */
    uint16_t both[2] = {TRIMETER_COMMAND_SAVE_CONFIG, TRIMETER_UNLOCK_KEY};
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_COMMAND, 2, both), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(erases(), 0);
    /* the window: one command, within APP_UNLOCK_WINDOW_US */
    unlock();
    uint16_t key_read = 0xFFFF;
    app_read_regs(NULL, MB_TABLE_HOLDING_REGISTERS, REG_HR_UNLOCK, 1, &key_read);
    CHECK_EQ_INT(key_read, TRIMETER_UNLOCK_LOCKED); /* the key is not left readable */
    run_ms(APP_UNLOCK_WINDOW_US / 1000 - 10);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    CHECK_EQ_INT(erases(), 1);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK); /* a retry at once: acknowledged, not run */
    CHECK_EQ_INT(erases(), 1);
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 75.0f), MB_OK);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_ILLEGAL_FUNCTION); /* not a retry: spent */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_LOAD_DEFAULTS), MB_EX_ILLEGAL_FUNCTION);
    unlock();
    run_ms(APP_UNLOCK_WINDOW_US / 1000 + 1);
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_ILLEGAL_FUNCTION); /* the window closed */
    unlock();
    CHECK_EQ_INT(write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_LOCKED), MB_OK);    /* closed by hand */
    CHECK_EQ_INT(command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    CHECK_EQ_INT(erases(), 2);
    fixture_boot();
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 75.0f);
    /* save_config with nothing changed: acknowledged, no erase, no byte programmed */
    long programmed = f->bytes_programmed;
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    CHECK_EQ_INT(erases(), 2);
    CHECK_EQ_INT(f->bytes_programmed, programmed);
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_SAVED);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_LOAD_DEFAULTS), MB_OK); /* changed words: saved */
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    CHECK_EQ_INT(erases(), 3);
    /* the saved copy refused at boot: the defaults run, and saving them is no no-op */
    edit_saved_records(0, REG_HR_HOMING_DIRECTION - STORAGE_CONFIG_FIRST, 0);
    fixture_boot();
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_REFUSED);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    CHECK_EQ_INT(erases(), 4);
    fixture_boot();
    CHECK_EQ_INT(ir(REG_IR_CONFIG_SOURCE), TRIMETER_CONFIG_SOURCE_SAVED);
}

/* A frame through the UART from `address` (0 = broadcast): FC 0x06 write single register. */
static void send_write_reg(uint8_t address, uint16_t reg, uint16_t value)
{
    uint8_t adu[6] = {address, 0x06, (uint8_t)(reg >> 8), (uint8_t)reg, (uint8_t)(value >> 8), (uint8_t)value};
    send_frame(adu, sizeof adu);
}

static void test_a_broadcast_never_unlocks_nor_runs_a_destructive_command(void)
{
    fresh_device();
    CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 70.0f), MB_OK);
    send_write_reg(0, REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY);
    send_write_reg(1, REG_HR_COMMAND, TRIMETER_COMMAND_SAVE_CONFIG);
    CHECK_EQ_INT(f->tx_len, 5); /* exception reply */
    CHECK_EQ_INT(f->tx[2], MB_EX_ILLEGAL_FUNCTION);
    send_write_reg(1, REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY);
    CHECK_EQ_INT(f->tx_len, 8); /* echo */
    send_write_reg(0, REG_HR_COMMAND, TRIMETER_COMMAND_LOAD_DEFAULTS);
    send_write_reg(0, REG_HR_COMMAND, TRIMETER_COMMAND_SAVE_CONFIG);
    CHECK_EQ_INT(f->tx_len, 0); /* never answered */
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 70.0f);
    CHECK_EQ_INT(erases(), 0);
    send_write_reg(0, REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_BEGIN_WRITE);
    CHECK_EQ_INT(ir(REG_IR_MAP_OP_STATUS), TRIMETER_MAP_OP_STATUS_IDLE);
    CHECK_EQ_INT(erases(), 0);
    /* the unicast window is still there for the master that opened it */
    send_write_reg(1, REG_HR_COMMAND, TRIMETER_COMMAND_SAVE_CONFIG);
    CHECK_EQ_INT(f->tx_len, 8);
    CHECK_EQ_INT(erases(), 1);
    /* harmless broadcasts still work */
    send_write_reg(0, REG_HR_LED_PANELS_LEVEL, 300);
    CHECK_EQ_INT(app_get()->hr[REG_HR_LED_PANELS_LEVEL], 300);
    /* and file records of an open upload can't be written by broadcast */
    CHECK_EQ_INT(fixture_table(map_data, MAP_BYTES, MAP_GRID, 4), MAP_BYTES);
    CHECK_EQ_INT(begin_upload(map_data, MAP_BYTES, 1), TRIMETER_MAP_OP_STATUS_WRITING);
    uint8_t fc15[] = {0, 0x15, 9, 6, 0, 1, 0, 0, 0, 1, 0xAB, 0xCD};
    send_frame(fc15, sizeof fc15);
    CHECK_EQ_INT(ir32(REG_IR_MAP_OP_BYTES_WRITTEN), 0);
}

static void test_erases_are_rate_limited_and_counted(void)
{
    fresh_device();
    run_ms(500);
    /* a flood of changed, unlocked saves: a burst goes through, then one per refill interval */
    unsigned ok = 0, busy = 0;
    for (int i = 0; i < 12; i++) {
        CHECK_EQ_INT(write_f32(REG_HR_SLOT_WHITE_MM, 61.0f + (float)i), MB_OK);
        uint8_t rc = unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG);
        ok += rc == MB_OK;
        busy += rc == MB_EX_SERVER_DEVICE_BUSY;
    }
    CHECK_EQ_INT(ok, STORAGE_ERASE_BURST);
    CHECK_EQ_INT(busy, 12 - STORAGE_ERASE_BURST);
    CHECK_EQ_INT(ir(REG_IR_ERASE_REFUSALS), 12 - STORAGE_ERASE_BURST);
    CHECK_EQ_INT(erases(), STORAGE_ERASE_BURST);
    CHECK(!di(REG_DI_FAULT)); /* a refused erase is no storage fault */
    CHECK_EQ_INT(app_get()->config_source, TRIMETER_CONFIG_SOURCE_SAVED);
    /* a refused save changes nothing: the refused value is back to the last one written */
    CHECK(read_f32_hr(REG_HR_SLOT_WHITE_MM) == 72.0f);
    /* begin_write is refused the same way, with its own status */
    CHECK_EQ_INT(fixture_table(map_data, MAP_BYTES, MAP_GRID, 5), MAP_BYTES);
    CHECK_EQ_INT(begin_upload(map_data, MAP_BYTES, 1), TRIMETER_MAP_OP_STATUS_ERROR_BUSY);
    run_ms(STORAGE_ERASE_REFILL_US / 1000 + 10);
    CHECK_EQ_INT(begin_upload(map_data, MAP_BYTES, 1), TRIMETER_MAP_OP_STATUS_WRITING);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_EX_SERVER_DEVICE_BUSY);
    /* the counts are in flash: the next save carries them, and a reboot reads them back */
    run_ms(STORAGE_ERASE_REFILL_US / 1000 + 10);
    CHECK_EQ_INT(unlocked_command(TRIMETER_COMMAND_SAVE_CONFIG), MB_OK);
    uint32_t before = erases();
    CHECK_EQ_INT(before, STORAGE_ERASE_BURST + 2);
    fixture_boot();
    CHECK_EQ_INT(erases(), before);
    CHECK_EQ_INT(ir32(REG_IR_ERASE_COUNT_MAP_A), 1);
    CHECK_EQ_INT(ir(REG_IR_ERASE_REFUSALS), 0); /* since boot */
}

/* Random requests through the real UART path (framer + dispatcher + these callbacks), under the
 * sanitizers: no crash, no out-of-range state, and the device still answers afterwards. */
static uint32_t rng_state = 12345;
static uint32_t rnd(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

/* This binary links no inverse core: the device says so and refuses every run, never making results up. */
static void test_without_the_inverse_core_a_fit_is_refused_as_unavailable(void)
{
    fresh_device();
    CHECK_EQ_INT(ir(REG_IR_FIT_AVAILABLE), 0);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_IDLE);
    uint16_t w[REG_HR_FIT_COMMAND - REG_HR_FIT_BIN_COUNT + 1] = {0};
    w[0] = 1;
    regmap_put_f32(&w[REG_HR_FIT_THICKNESS_MM - REG_HR_FIT_BIN_COUNT], 0.4f);
    w[REG_HR_FIT_COMMAND - REG_HR_FIT_BIN_COUNT] = TRIMETER_FIT_COMMAND_RUN;
    CHECK_EQ_INT(app_write_regs(NULL, REG_HR_FIT_BIN_COUNT, (uint16_t)(sizeof w / sizeof *w), w), MB_EX_ILLEGAL_FUNCTION);
    CHECK_EQ_INT(ir(REG_IR_FIT_STATUS), TRIMETER_FIT_STATUS_ERROR_UNAVAILABLE);
    CHECK_EQ_INT(ir(REG_IR_FIT_BINS_DONE), 0);
    uint16_t out[1];
    CHECK_EQ_INT(app_read_file(NULL, TRIMETER_FIT_FILE_OUTPUT, 0, 1, out), MB_EX_ILLEGAL_DATA_ADDRESS);
    /* the refused write changed nothing, the command included */
    CHECK_EQ_INT(app_read_regs(NULL, MB_TABLE_HOLDING_REGISTERS, REG_HR_FIT_COMMAND, 1, out), MB_OK);
    CHECK_EQ_INT(out[0], TRIMETER_FIT_COMMAND_NONE);
}

static void test_random_requests_never_break_the_app(void)
{
    static const uint8_t codes[] = {1, 2, 3, 4, 5, 6, 15, 16, 20, 21, 23, 43, 7, 0x80, 0xFF};
    fresh_device();
    f->has_stall_output = true;
    int replies = 0;
    for (int i = 0; i < 20000; i++) {
        uint8_t adu[64];
        size_t len = 2 + rnd() % 40;
        for (size_t k = 0; k < len; k++) adu[k] = (uint8_t)rnd();
        adu[0] = 1;
        adu[1] = codes[rnd() % sizeof codes];
        if (rnd() % 2) { /* aim at the mapped addresses half of the time */
            adu[2] = 0;
            adu[3] = (uint8_t)(rnd() % 96);
            adu[4] = 0;
            adu[5] = (uint8_t)(1 + rnd() % 8);
        }
        send_frame(adu, len);
        replies += f->tx_len > 0;
        CHECK((unsigned)app_state() <= TRIMETER_STATE_FAULT);
        CHECK((unsigned)app_fault() <= TRIMETER_FAULT_STORAGE);
    }
    CHECK(replies > 1000); /* the frames did reach the app */
    uint8_t read_vendor[] = {1, 4, 0, 0, 0, 1};
    send_frame(read_vendor, sizeof read_vendor);
    CHECK_EQ_INT(f->tx_len, 7);
    CHECK_EQ_INT(f->tx[3] << 8 | f->tx[4], TRIMETER_VENDOR_ID);
}

int main(void)
{
    RUN_TEST(test_identity_and_boot_state);
    RUN_TEST(test_motion_commands_return_at_once_with_busy);
    RUN_TEST(test_settle_after_arrival);
    RUN_TEST(test_command_during_motion_is_queued);
    RUN_TEST(test_fault_latches_until_cleared);
    RUN_TEST(test_stuck_slider_is_a_stall);
    RUN_TEST(test_config_validation);
    RUN_TEST(test_homing_uses_the_configured_speed_and_back_off);
    RUN_TEST(test_config_persists_across_reboot);
    RUN_TEST(test_config_source_says_why_defaults_run);
    RUN_TEST(test_shutters_leds_settle);
    RUN_TEST(test_button_debounce_and_events);
    RUN_TEST(test_status_led_patterns);
    RUN_TEST(test_map_upload_over_file_records);
    RUN_TEST(test_junk_bytes_never_become_a_valid_map);
    RUN_TEST(test_destructive_commands_need_an_unlock_right_before);
    RUN_TEST(test_a_broadcast_never_unlocks_nor_runs_a_destructive_command);
    RUN_TEST(test_erases_are_rate_limited_and_counted);
    RUN_TEST(test_without_the_inverse_core_a_fit_is_refused_as_unavailable);
    RUN_TEST(test_random_requests_never_break_the_app);
    fixture_free_hal();
    return CHECK_SUMMARY();
}
