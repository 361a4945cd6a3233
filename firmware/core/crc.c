/* Table-driven CRCs (a byte per step instead of a bit: the Modbus reply path and the 128 KiB map
 * verify are the hot users). The tables are filled on first use rather than written out as
 * literals; first use is mb_init / storage init, before any interrupt uses them. */
#include "crc.h"

static uint16_t crc16_table[256];
static uint32_t crc32_table[256];
static uint8_t tables_ready;

static void crc_tables_init(void) {
    for (uint32_t i = 0; i < 256; i++) {
        uint16_t c16 = (uint16_t)i;
        uint32_t c32 = i;
        for (int bit = 0; bit < 8; bit++) {
            c16 = (uint16_t)((c16 & 1u) ? (c16 >> 1) ^ 0xA001u : c16 >> 1);
            c32 = (c32 & 1u) ? (c32 >> 1) ^ 0xEDB88320u : c32 >> 1;
        }
        crc16_table[i] = c16;
        crc32_table[i] = c32;
    }
    tables_ready = 1;
}

uint16_t crc16_modbus_update(uint16_t crc, const void *data, size_t n) {
    const uint8_t *p = data;
    if (!tables_ready) crc_tables_init();
    while (n--) crc = (uint16_t)((crc >> 8) ^ crc16_table[(crc ^ *p++) & 0xFFu]);
    return crc;
}

uint16_t crc16_modbus(const void *data, size_t n) { return crc16_modbus_update(0xFFFFu, data, n); }

uint32_t crc32_update(uint32_t crc, const void *data, size_t n) {
    const uint8_t *p = data;
    if (!tables_ready) crc_tables_init();
    crc = ~crc;
    while (n--) crc = (crc >> 8) ^ crc32_table[(crc ^ *p++) & 0xFFu];
    return ~crc;
}
