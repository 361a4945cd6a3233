/* The register-map rules (regmap.c over the generated table): wide values written whole,
 * ranges/allowed values, read-only and unmapped addresses, defaults, word order. */
#include <math.h>

#include "../core/modbus.h"
#include "../core/regmap.h"
#include "check.h"

static void test_word_order_is_big_endian(void) {
    uint16_t w[2];
    regmap_put_u32(w, 0x12345678u);
    CHECK_EQ_INT(w[0], 0x1234);
    CHECK_EQ_INT(w[1], 0x5678);
    regmap_put_f32(w, 80.0f); /* 0x42A00000 */
    CHECK_EQ_INT(w[0], 0x42A0);
    CHECK_EQ_INT(w[1], 0x0000);
    CHECK(regmap_get_f32(w) == 80.0f);
}

static void test_find_covers_both_words(void) {
    const regmap_entry_t *e = regmap_find(REGMAP_HOLDING_REGISTER, REG_HR_STEPS_PER_MM + 1);
    CHECK(e && e->address == REG_HR_STEPS_PER_MM && e->words == 2);
    CHECK(regmap_find(REGMAP_INPUT_REGISTER, REG_IR_REGMAP_HASH + 1) != NULL);
    CHECK(regmap_find(REGMAP_HOLDING_REGISTER, REG_HR_STATUS_PATTERN + 1) == NULL); /* a gap */
    CHECK(regmap_find(REGMAP_COIL, REG_COIL_SPAN) == NULL);
}

static void test_half_wide_write_refused_with_02(void) {
    uint16_t w[4];
    regmap_put_f32(w, 100.0f);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM, 2, w), MB_OK);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM, 1, w), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM + 1, 1, w), MB_EX_ILLEGAL_DATA_ADDRESS);
    /* Second word of one value + first of the next: both halves cut. */
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM + 1, 2, w), MB_EX_ILLEGAL_DATA_ADDRESS);
    /* Two whole values in one write. */
    regmap_put_f32(w + 2, 20.0f);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM, 4, w), MB_OK);
}

static void test_ranges_and_allowed_values(void) {
    uint16_t w[2];
    regmap_put_f32(w, 0.5f); /* steps_per_mm min is 1 */
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM, 2, w), MB_EX_ILLEGAL_DATA_VALUE);
    regmap_put_f32(w, NAN);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM, 2, w), MB_EX_ILLEGAL_DATA_VALUE);
    regmap_put_f32(w, INFINITY);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STEPS_PER_MM, 2, w), MB_EX_ILLEGAL_DATA_VALUE);
    w[0] = 1001;
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_LED_PANELS_LEVEL, 1, w), MB_EX_ILLEGAL_DATA_VALUE);
    w[0] = 1000;
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_LED_PANELS_LEVEL, 1, w), MB_OK);
    w[0] = (uint16_t)-1; /* homing_direction is i16 -1..1 */
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_HOMING_DIRECTION, 1, w), MB_OK);
    w[0] = (uint16_t)-2;
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_HOMING_DIRECTION, 1, w), MB_EX_ILLEGAL_DATA_VALUE);
    w[0] = TRIMETER_COMMAND_LOAD_DEFAULTS + 1; /* not a command */
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_COMMAND, 1, w), MB_EX_ILLEGAL_DATA_VALUE);
    regmap_put_u32(w, 115200u);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_MODBUS_BAUD, 2, w), MB_OK);
    regmap_put_u32(w, 100000u); /* inside min..max but not an allowed rate */
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_MODBUS_BAUD, 2, w), MB_EX_ILLEGAL_DATA_VALUE);
    regmap_put_u32(w, TRIMETER_MAP_SLOT_CAPACITY_BYTES + 1u);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_MAP_EXPECTED_LENGTH, 2, w), MB_EX_ILLEGAL_DATA_VALUE);
    regmap_put_u32(w, 0xFFFFFFFFu); /* full u32 range for a CRC */
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_MAP_EXPECTED_CRC32, 2, w), MB_OK);
}

static void test_addresses_before_values(void) {
    /* A write spanning a gap is 02 even if a value is also bad (02 is checked first). */
    uint16_t w[2] = {0xFFFF, 0};
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_STATUS_PATTERN, 2, w), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(regmap_check_write_regs(REG_HR_SPAN, 1, w), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(regmap_check_write_regs(0xFFFF, 1, w), MB_EX_ILLEGAL_DATA_ADDRESS);
}

static void test_bits_and_reads(void) {
    CHECK_EQ_INT(regmap_check_write_bits(REG_COIL_SHUTTER_PANEL_LEFT_OPEN, REG_COIL_SPAN), MB_OK);
    CHECK_EQ_INT(regmap_check_write_bits(REG_COIL_SPAN - 1, 2), MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(regmap_check_read(REGMAP_INPUT_REGISTER, 0, REG_IR_SPAN), MB_OK);
    CHECK_EQ_INT(regmap_check_read(REGMAP_INPUT_REGISTER, 5, 1), MB_OK); /* gap reads 0 */
    CHECK_EQ_INT(regmap_check_read(REGMAP_INPUT_REGISTER, 0, REG_IR_SPAN + 1),
                 MB_EX_ILLEGAL_DATA_ADDRESS);
    CHECK_EQ_INT(regmap_check_read(REGMAP_DISCRETE_INPUT, REG_DI_SPAN, 1), MB_EX_ILLEGAL_DATA_ADDRESS);
}

static void test_defaults(void) {
    static uint16_t hr[REG_HR_SPAN];
    regmap_fill_defaults(REGMAP_HOLDING_REGISTER, hr, REG_HR_SPAN);
    CHECK(regmap_get_f32(&hr[REG_HR_STEPS_PER_MM]) == REG_HR_STEPS_PER_MM_DEFAULT);
    CHECK_EQ_INT(regmap_get_u32(&hr[REG_HR_MODBUS_BAUD]), REG_HR_MODBUS_BAUD_DEFAULT);
    CHECK_EQ_INT((int16_t)hr[REG_HR_HOMING_DIRECTION], REG_HR_HOMING_DIRECTION_DEFAULT);
    CHECK_EQ_INT(hr[REG_HR_STATUS_PATTERN], TRIMETER_STATUS_PATTERN_SLOW_BLINK);
    /* Every default passes the map's own write check, one item at a time. */
    for (uint32_t i = 0; i < REGMAP_ENTRY_COUNT; i++) {
        const regmap_entry_t *e = &regmap_entries[i];
        if (e->table == REGMAP_HOLDING_REGISTER && e->writable)
            CHECK_EQ_INT(regmap_check_write_regs(e->address, e->words, &hr[e->address]), MB_OK);
    }
}

int main(void) {
    RUN_TEST(test_word_order_is_big_endian);
    RUN_TEST(test_find_covers_both_words);
    RUN_TEST(test_half_wide_write_refused_with_02);
    RUN_TEST(test_ranges_and_allowed_values);
    RUN_TEST(test_addresses_before_values);
    RUN_TEST(test_bits_and_reads);
    RUN_TEST(test_defaults);
    return CHECK_SUMMARY();
}
