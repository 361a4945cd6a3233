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
    memset(out, 0, MAP_TABLE_V1_HEADER_BYTES);
    memcpy(out, "\x89TRLUT\r\n", 8);
    put16(out + 8, 1);
    put16(out + 10, MAP_TABLE_V1_HEADER_BYTES);
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
    for (uint32_t i = MAP_TABLE_V1_HEADER_BYTES; i < length - 4; i++) out[i] = (uint8_t)(i * 31u + seed);
    fixture_table_fix_crc(out, length);
    return length;
}

uint32_t fixture_table_v2(uint8_t *out, uint32_t cap, uint8_t seed)
{
    enum { NA = 4, NS = 4, NG = 3, NI = 2, NU = 2, NT = 2, NV = 2 };
    static const char geometry[] = "{}";
    uint32_t length = map_table_v2_size(NA, NS, NG, NI, NU, NT, NV, sizeof geometry - 1);
    if (length == 0 || length > cap) return 0;
    memset(out, 0, length);
    memcpy(out, "\x89TRLUT\r\n", 8);
    put16(out + 8, 2);
    put16(out + 10, MAP_TABLE_V2_HEADER_BYTES);
    put32(out + 12, length);
    for (int i = 0; i < 64; i++) out[16 + i] = (uint8_t)(seed + i); /* the two SHA-256s */
    static const float setup[9] = {1.5f, 0.4f, 0.0f, 0.02f, 0.95f, 1e-3f, 6.9f, 10.0f, 2.3f};
    for (int i = 0; i < 9; i++) putf(out + 80 + 4 * i, setup[i]);
    static const uint16_t counts[7] = {NA, NS, NG, NI, NU, NT, NV};
    for (int i = 0; i < 7; i++) put16(out + 116 + 2 * i, counts[i]);
    memcpy(out + 132, "fixture-v2", 10);
    const uint32_t sizes[11] = {4 * NA, 4 * NS, 4 * NG, 48, 6 * NG * NA * NS, 4 * NA * NS * NG, 2 * NU * NT * NV,
                                24 * NS, 2 * NS * NI * NI, 2 * NS * NI * NI, sizeof geometry - 1};
    uint32_t at[11], offset = MAP_TABLE_V2_HEADER_BYTES;
    for (int i = 0; i < 11; i++) {
        at[i] = offset;
        put32(out + 156 + 8 * i, offset);
        put32(out + 160 + 8 * i, sizes[i]);
        offset += (sizes[i] + 7u) / 8u * 8u;
    }
    static const float alpha[NA] = {0.0f, 0.3f, 0.6f, 0.99f}, log_sigma[NS] = {-1.0f, 0.0f, 1.0f, 2.0f},
                       g[NG] = {-0.3f, 0.3f, 0.8f};
    for (int i = 0; i < NA; i++) putf(out + at[0] + 4 * i, alpha[i]);
    for (int i = 0; i < NS; i++) putf(out + at[1] + 4 * i, log_sigma[i]);
    for (int i = 0; i < NG; i++) putf(out + at[2] + 4 * i, g[i]);
    for (int i = 0; i < 6; i++) putf(out + at[3] + 8 * i + 4, i < 3 ? 1e-5f : 1e-7f); /* offsets 0, steps */
    for (int s = 4; s <= 9; s++) /* the codes (the frames as codes too: finite floats) */
        for (uint32_t i = 0; i < sizes[s]; i += 2) put16(out + at[s] + i, (uint16_t)(i * 2654435761u + seed * 40503u));
    for (int k = 0; k < NS; k++) { /* the inverse frame: (x0, y0) = 0, an identity map */
        static const float frame[6] = {0.0f, 0.0f, 1.0f, 0.0f, 0.0f, 1.0f};
        for (int i = 0; i < 6; i++) putf(out + at[7] + 24 * k + 4 * i, frame[i]);
    }
    memcpy(out + at[10], geometry, sizeof geometry - 1);
    fixture_table_fix_crc(out, length);
    return length;
}
