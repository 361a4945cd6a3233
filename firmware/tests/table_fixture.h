/* A map table as host/trimeter/inversion/table.py writes it (header, payload, trailing CRC-32), small
 * and deterministic, for the tests of what the firmware accepts in a map slot. Tests only. */
#ifndef TRIMETER_TABLE_FIXTURE_H
#define TRIMETER_TABLE_FIXTURE_H

#include <stdint.h>

/* Writes a table with every grid count = `grid` (>= 2) and a payload picked by `seed` into out
 * (capacity cap); returns its length, 0 if it does not fit. */
uint32_t fixture_table(uint8_t *out, uint32_t cap, uint16_t grid, uint8_t seed);
/* Recomputes the trailing CRC-32 after a test edited the bytes. */
void fixture_table_fix_crc(uint8_t *table, uint32_t length);

#endif
