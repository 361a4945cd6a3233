/* Map table header checks; see map_table.h. */
#include "map_table.h"

#include <math.h>
#include <string.h>

static const uint8_t magic[8] = {0x89, 'T', 'R', 'L', 'U', 'T', '\r', '\n'};

static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static uint32_t get32(const uint8_t *p) { return get16(p) | ((uint32_t)get16(p + 2) << 16); }

static float getf(const uint8_t *p)
{
    uint32_t bits = get32(p);
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}

float map_table_thickness_mm(const uint8_t *header) { return getf(header + 52); }

uint32_t map_table_size(uint32_t na, uint32_t ns, uint32_t ng, uint32_t nx, uint32_t ny)
{
    /* header, axes + (offset, step) of A, B, C, the u16 coefficients, the inverse frames, the two
     * u16 inverse grids, the CRC — in 64 bits: 16-bit counts can overflow 32 */
    uint64_t forward = (uint64_t)na * ns * ng, inverse = (uint64_t)ns * nx * ny;
    uint64_t total = MAP_TABLE_HEADER_BYTES + 4u * ((uint64_t)na + ns + ng + 6u) + 6u * forward + 24u * (uint64_t)ns +
                     4u * inverse + 4u;
    return total > 0xFFFFFFFFu ? 0u : (uint32_t)total;
}

enum map_table_verdict map_table_check(const uint8_t *h, uint32_t length, uint32_t body_crc32, uint32_t stored_crc32)
{
    if (length < MAP_TABLE_HEADER_BYTES + 4u) return MAP_TABLE_TOO_SHORT;
    if (memcmp(h, magic, sizeof magic) != 0) return MAP_TABLE_BAD_MAGIC;
    if (get16(h + 8) != MAP_TABLE_FORMAT_VERSION || get16(h + 10) != MAP_TABLE_HEADER_BYTES) return MAP_TABLE_BAD_VERSION;
    if (get32(h + 12) != length) return MAP_TABLE_BAD_SIZE;
    uint16_t na = get16(h + 72), ns = get16(h + 74), ng = get16(h + 76), nx = get16(h + 78), ny = get16(h + 80);
    if (na < 2 || ns < 2 || ng < 2 || nx < 2 || ny < 2 || map_table_size(na, ns, ng, nx, ny) != length)
        return MAP_TABLE_BAD_GRID;
    float n = getf(h + 48), thickness = map_table_thickness_mm(h), rho_b = getf(h + 60), rho_w = getf(h + 64);
    /* the comparisons are false for NaN, so a NaN anywhere fails them */
    if (!(n >= 1.0f && isfinite(n)) || !(thickness > 0.0f && thickness <= MAP_TABLE_MAX_THICKNESS_MM) ||
        !(rho_b >= 0.0f && rho_b < rho_w && rho_w <= 1.0f))
        return MAP_TABLE_BAD_SETUP;
    if (body_crc32 != stored_crc32) return MAP_TABLE_BAD_CRC;
    return MAP_TABLE_OK;
}
