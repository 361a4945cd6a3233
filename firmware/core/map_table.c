/* Map table header checks; see map_table.h. */
#include "map_table.h"

#include <math.h>
#include <stdbool.h>
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

/* where the six set-up floats (n, thickness_mm, cover_slide_n, rho_b_ref, rho_w_ref, mc_stderr) start */
static uint32_t setup_offset(const uint8_t *header) { return get16(header + 8) == 2 ? 80u : 48u; }

float map_table_thickness_mm(const uint8_t *header) { return getf(header + setup_offset(header) + 4); }

uint32_t map_table_size(uint32_t na, uint32_t ns, uint32_t ng, uint32_t nx, uint32_t ny)
{
    /* header, axes + (offset, step) of A, B, C, the u16 coefficients, the inverse frames, the two
     * u16 inverse grids, the CRC — in 64 bits: 16-bit counts can overflow 32 */
    uint64_t forward = (uint64_t)na * ns * ng, inverse = (uint64_t)ns * nx * ny;
    uint64_t total = MAP_TABLE_V1_HEADER_BYTES + 4u * ((uint64_t)na + ns + ng + 6u) + 6u * forward + 24u * (uint64_t)ns +
                     4u * inverse + 4u;
    return total > 0xFFFFFFFFu ? 0u : (uint32_t)total;
}

static uint64_t padded8(uint64_t n) { return (n + 7u) / 8u * 8u; }

uint32_t map_table_v2_size(uint32_t na, uint32_t ns, uint32_t ng, uint32_t ni, uint32_t nu, uint32_t nt, uint32_t nv,
                           uint32_t geometry_bytes)
{
    /* the sections in order (maps/device_table.py SECTIONS), each padded to 8 bytes; 64 bits as above */
    uint64_t forward = (uint64_t)na * ns * ng, inverse = (uint64_t)ns * ni * ni;
    uint64_t sections[] = {4u * (uint64_t)na, 4u * (uint64_t)ns, 4u * (uint64_t)ng, 48u, 6u * forward, 4u * forward,
                           2u * (uint64_t)nu * nt * nv, 24u * (uint64_t)ns, 2u * inverse, 2u * inverse, geometry_bytes};
    uint64_t total = MAP_TABLE_V2_HEADER_BYTES + 4u;
    for (unsigned i = 0; i < sizeof sections / sizeof sections[0]; i++) total += padded8(sections[i]);
    return total > 0xFFFFFFFFu ? 0u : (uint32_t)total;
}

/* the grid counts add up to `length` in the header's format */
static bool grid_fits(const uint8_t *h, uint16_t version, uint32_t length)
{
    if (version == 1) {
        uint16_t na = get16(h + 72), ns = get16(h + 74), ng = get16(h + 76), nx = get16(h + 78), ny = get16(h + 80);
        return na >= 2 && ns >= 2 && ng >= 2 && nx >= 2 && ny >= 2 && map_table_size(na, ns, ng, nx, ny) == length;
    }
    uint16_t c[7];
    static const uint16_t least[7] = {4, 4, 3, 2, 2, 2, 2}; /* cubic splines in α and ln σt, PCHIP in g */
    for (int i = 0; i < 7; i++) {
        c[i] = get16(h + 116 + 2 * i);
        if (c[i] < least[i]) return false;
    }
    uint32_t geometry_bytes = get32(h + 156 + 8 * 10 + 4); /* the last section's length in the directory */
    return map_table_v2_size(c[0], c[1], c[2], c[3], c[4], c[5], c[6], geometry_bytes) == length;
}

enum map_table_verdict map_table_check(const uint8_t *h, uint32_t length, uint32_t body_crc32, uint32_t stored_crc32)
{
    if (length < MAP_TABLE_V1_HEADER_BYTES + 4u) return MAP_TABLE_TOO_SHORT;
    if (memcmp(h, magic, sizeof magic) != 0) return MAP_TABLE_BAD_MAGIC;
    uint16_t version = get16(h + 8), header_bytes = get16(h + 10);
    if (!(version == 1 && header_bytes == MAP_TABLE_V1_HEADER_BYTES) &&
        !(version == 2 && header_bytes == MAP_TABLE_V2_HEADER_BYTES))
        return MAP_TABLE_BAD_VERSION;
    if (length < header_bytes + 4u) return MAP_TABLE_TOO_SHORT;
    if (get32(h + 12) != length) return MAP_TABLE_BAD_SIZE;
    if (!grid_fits(h, version, length)) return MAP_TABLE_BAD_GRID;
    const uint8_t *setup = h + setup_offset(h);
    float n = getf(setup), thickness = getf(setup + 4), rho_b = getf(setup + 12), rho_w = getf(setup + 16);
    /* the comparisons are false for NaN, so a NaN anywhere fails them */
    if (!(n >= 1.0f && isfinite(n)) || !(thickness > 0.0f && thickness <= MAP_TABLE_MAX_THICKNESS_MM) ||
        !(rho_b >= 0.0f && rho_b < rho_w && rho_w <= 1.0f))
        return MAP_TABLE_BAD_SETUP;
    if (body_crc32 != stored_crc32) return MAP_TABLE_BAD_CRC;
    return MAP_TABLE_OK;
}
