/* What the firmware accepts as a map table (map_table.h): the host's layout passes, and every
 * header defect is named, with the table's own CRC fixed so only the defect under test remains. */
#include <string.h>

#include "../core/crc.h"
#include "../core/map_table.h"
#include "check.h"
#include "table_fixture.h"

static uint8_t table[4096];
static uint32_t length;

static enum map_table_verdict check(const uint8_t *t, uint32_t len)
{
    uint32_t stored = len >= 4 ? (uint32_t)(t[len - 4] | t[len - 3] << 8 | t[len - 2] << 16 | (uint32_t)t[len - 1] << 24) : 0;
    return map_table_check(t, len, crc32_update(0, t, len >= 4 ? len - 4 : 0), stored);
}

/* One edit of the fixture, its CRC fixed; returns the verdict. */
static enum map_table_verdict edited(unsigned offset, const void *bytes, unsigned n)
{
    static uint8_t copy[sizeof table];
    memcpy(copy, table, length);
    memcpy(copy + offset, bytes, n);
    fixture_table_fix_crc(copy, length);
    return check(copy, length);
}

static void test_the_hosts_layout_is_accepted(void)
{
    length = fixture_table(table, sizeof table, 4, 7);
    CHECK_EQ_INT(length, 940); /* 128 + 4·(4+4+4+6) + 2·3·64 + 24·4 + 2·2·64 + 4 */
    CHECK_EQ_INT(check(table, length), MAP_TABLE_OK);
    CHECK_EQ_INT(map_table_size(2, 2, 2, 2, 2), 308);
    CHECK_EQ_INT(map_table_size(65535, 65535, 65535, 65535, 65535), 0); /* no 32-bit wrap to a small size */
}

static void test_each_header_defect_is_refused(void)
{
    length = fixture_table(table, sizeof table, 4, 7);
    float one = 1.0f, nan = 0.0f / 0.0f, zero = 0.0f, half = 0.5f, thick = 150.0f, below_one = 0.99f;
    uint16_t v2 = 2, h64 = 64, g1 = 1, g5 = 5;
    uint32_t other_len = 942;
    CHECK_EQ_INT(edited(0, "\x89TRLUX", 6), MAP_TABLE_BAD_MAGIC);
    CHECK_EQ_INT(edited(8, &v2, 2), MAP_TABLE_BAD_VERSION);
    CHECK_EQ_INT(edited(10, &h64, 2), MAP_TABLE_BAD_VERSION);
    CHECK_EQ_INT(edited(12, &other_len, 4), MAP_TABLE_BAD_SIZE);
    CHECK_EQ_INT(edited(72, &g1, 2), MAP_TABLE_BAD_GRID);  /* n_alpha 1 */
    CHECK_EQ_INT(edited(80, &g5, 2), MAP_TABLE_BAD_GRID);  /* n_y 5: the sizes no longer add up */
    CHECK_EQ_INT(edited(48, &below_one, 4), MAP_TABLE_BAD_SETUP); /* n < 1 */
    CHECK_EQ_INT(edited(48, &nan, 4), MAP_TABLE_BAD_SETUP);
    CHECK_EQ_INT(edited(52, &zero, 4), MAP_TABLE_BAD_SETUP);      /* thickness 0 */
    CHECK_EQ_INT(edited(52, &thick, 4), MAP_TABLE_BAD_SETUP);     /* 150 mm */
    CHECK_EQ_INT(edited(60, &one, 4), MAP_TABLE_BAD_SETUP);       /* rho_b >= rho_w */
    CHECK_EQ_INT(edited(64, &nan, 4), MAP_TABLE_BAD_SETUP);
    CHECK_EQ_INT(edited(60, &half, 4), MAP_TABLE_OK);             /* a legal edit passes */
    table[500] ^= 1; /* payload changed, the table's own CRC not updated */
    CHECK_EQ_INT(check(table, length), MAP_TABLE_BAD_CRC);
}

static void test_the_device_table_format_2_is_accepted_and_its_defects_refused(void)
{
    length = fixture_table_v2(table, sizeof table, 3);
    CHECK(length > 0);
    CHECK_EQ_INT(check(table, length), MAP_TABLE_OK);
    CHECK(map_table_thickness_mm(table) == 0.4f);
    CHECK_EQ_INT(map_table_v2_size(65535, 65535, 65535, 65535, 65535, 65535, 65535, 0), 0);
    uint16_t h128 = 128, three = 3, one = 1;
    uint32_t geometry_longer = 9;
    float nan = 0.0f / 0.0f, one_f = 1.0f;
    CHECK_EQ_INT(edited(10, &h128, 2), MAP_TABLE_BAD_VERSION);   /* format 2 with format 1's header size */
    CHECK_EQ_INT(edited(116, &three, 2), MAP_TABLE_BAD_GRID);    /* n_alpha 3: a cubic spline needs 4 */
    CHECK_EQ_INT(edited(124, &one, 2), MAP_TABLE_BAD_GRID);      /* n_u 1 */
    CHECK_EQ_INT(edited(240, &geometry_longer, 4), MAP_TABLE_BAD_GRID); /* sections no longer add up */
    CHECK_EQ_INT(edited(84, &nan, 4), MAP_TABLE_BAD_SETUP);      /* thickness */
    CHECK_EQ_INT(edited(92, &one_f, 4), MAP_TABLE_BAD_SETUP);    /* rho_b >= rho_w */
    CHECK_EQ_INT(check(table, length - 8), MAP_TABLE_BAD_SIZE);
}

static void test_junk_with_a_right_length_is_not_a_table(void)
{
    uint8_t junk[64];
    for (int i = 0; i < 64; i++) junk[i] = (uint8_t)(i * 37 + 1);
    CHECK_EQ_INT(check(junk, sizeof junk), MAP_TABLE_TOO_SHORT);
    static uint8_t big[940];
    memset(big, 0xA5, sizeof big);
    fixture_table_fix_crc(big, sizeof big); /* even a self-consistent CRC does not make it a table */
    CHECK_EQ_INT(check(big, sizeof big), MAP_TABLE_BAD_MAGIC);
}

int main(void)
{
    RUN_TEST(test_the_hosts_layout_is_accepted);
    RUN_TEST(test_each_header_defect_is_refused);
    RUN_TEST(test_the_device_table_format_2_is_accepted_and_its_defects_refused);
    RUN_TEST(test_junk_with_a_right_length_is_not_a_table);
    return CHECK_SUMMARY();
}
