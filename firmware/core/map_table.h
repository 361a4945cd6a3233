/* The map table's header, checked before a slot may become (or stay) the active map.
 *
 * Two formats, both little-endian, both starting with the magic "\x89TRLUT\r\n", u16 version, u16
 * header size, u32 total size (trailing CRC-32 included), and ending with a CRC-32 of every byte before it:
 *   1  host/trimeter/maps/table.py: header 128 bytes, the source map's SHA-256, six f32 (n, thickness_mm,
 *      cover_slide_n, rho_b_ref, rho_w_ref, mc_stderr), u16 grid counts n_alpha, n_sigma, n_g, n_x, n_y,
 *      then the payload.
 *   2  the self-sufficient device table, host/trimeter/maps/device_table.py: header 256 bytes, two
 *      SHA-256s, six f32 as above at offset 80, u16 counts n_alpha, n_sigma, n_g, n_inverse, n_u, n_tau,
 *      n_v at 116, a directory of (offset, length) per section at 156, then the sections, each padded to
 *      8 bytes. The inverse core fits with this one (fit_core.h).
 *
 * What the firmware accepts ("geometry" = the table's grid and the sample set-up it was built for):
 * the magic, a known version with its header size, the total size equal to the uploaded length, every
 * grid count at least its format's minimum with the sizes adding up to exactly that length, n >= 1 and
 * 0 < thickness <= 100 mm (finite), 0 <= rho_b_ref < rho_w_ref <= 1, and the table's own trailing CRC-32.
 * The payload is the host's (and the inverse core's) to interpret; a table passing all this is what the
 * host wrote, not bytes that happen to carry the expected CRC. */
#ifndef TRIMETER_MAP_TABLE_H
#define TRIMETER_MAP_TABLE_H

#include <stdint.h>

/* The bytes map_table_check reads: the longer of the two headers */
#define MAP_TABLE_HEADER_BYTES 256u
#define MAP_TABLE_V1_HEADER_BYTES 128u
#define MAP_TABLE_V2_HEADER_BYTES 256u
#define MAP_TABLE_MAX_THICKNESS_MM 100.0f

enum map_table_verdict {
    MAP_TABLE_OK = 0,
    MAP_TABLE_TOO_SHORT,   /* shorter than a header + CRC */
    MAP_TABLE_BAD_MAGIC,
    MAP_TABLE_BAD_VERSION, /* format version or header size */
    MAP_TABLE_BAD_SIZE,    /* total size field != length */
    MAP_TABLE_BAD_GRID,    /* a count < 2, or the counts don't add up to the length */
    MAP_TABLE_BAD_SETUP,   /* n, thickness, reference reflectances impossible */
    MAP_TABLE_BAD_CRC,     /* the table's own CRC-32 */
};

/* header: the first MAP_TABLE_HEADER_BYTES bytes (only read when length allows); length: the
 * whole table; body_crc32: CRC-32 of its first length - 4 bytes; stored_crc32: its last 4 bytes
 * as a little-endian u32. */
enum map_table_verdict map_table_check(const uint8_t *header, uint32_t length, uint32_t body_crc32,
                                       uint32_t stored_crc32);

/* The sample thickness ℓ in mm the table was built for (header of a table map_table_check accepted, either format). */
float map_table_thickness_mm(const uint8_t *header);

/* The total size of a format-1 table with these grid counts (0 if it would not fit in 32 bits). */
uint32_t map_table_size(uint32_t n_alpha, uint32_t n_sigma, uint32_t n_g, uint32_t n_x, uint32_t n_y);

/* The total size of a format-2 table with these counts and a geometry section of geometry_bytes (0 if it
 * would not fit in 32 bits). */
uint32_t map_table_v2_size(uint32_t n_alpha, uint32_t n_sigma, uint32_t n_g, uint32_t n_inverse, uint32_t n_u,
                           uint32_t n_tau, uint32_t n_v, uint32_t geometry_bytes);

#endif
