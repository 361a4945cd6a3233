/* See table_fixture.h. */
#include "table_fixture.h"

#include <string.h>

#include "../core/crc.h"
#include "../core/map_table.h"

static void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v) { put16(p, (uint16_t)v); put16(p + 2, (uint16_t)(v >> 16)); }
static void putf(uint8_t *p, float f)
{
    uint32_t bits;
    memcpy(&bits, &f, sizeof bits);
    put32(p, bits);
}

void fixture_table_fix_crc(uint8_t *table, uint32_t length)
{
    put32(table + length - 4, crc32_update(0, table, length - 4));
}

uint32_t fixture_table(uint8_t *out, uint32_t cap, uint16_t grid, uint8_t seed)
{
    uint32_t length = map_table_size(grid, grid, grid, grid, grid);
    if (length == 0 || length > cap) return 0;
    memset(out, 0, MAP_TABLE_HEADER_BYTES);
    memcpy(out, "\x89TRLUT\r\n", 8);
    put16(out + 8, MAP_TABLE_FORMAT_VERSION);
    put16(out + 10, MAP_TABLE_HEADER_BYTES);
    put32(out + 12, length);
    for (int i = 0; i < 32; i++) out[16 + i] = (uint8_t)(seed + i); /* source map digest */
    putf(out + 48, 1.5f);   /* n */
    putf(out + 52, 0.4f);   /* thickness, mm */
    putf(out + 56, 0.0f);   /* no cover slides */
    putf(out + 60, 0.02f);  /* rho_b_ref */
    putf(out + 64, 0.95f);  /* rho_w_ref */
    putf(out + 68, 1e-3f);  /* MC std-error */
    for (int i = 0; i < 5; i++) put16(out + 72 + 2 * i, grid);
    memcpy(out + 84, "fixture", 7);
    for (uint32_t i = MAP_TABLE_HEADER_BYTES; i < length - 4; i++) out[i] = (uint8_t)(i * 31u + seed);
    fixture_table_fix_crc(out, length);
    return length;
}
