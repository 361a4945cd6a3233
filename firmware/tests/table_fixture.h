/* Map tables as the host writes them (header, payload, trailing CRC-32), small and deterministic, for the
 * tests of what the firmware accepts in a map slot and what the inverse core makes of it. Tests only. */
#ifndef TRIMETER_TABLE_FIXTURE_H
#define TRIMETER_TABLE_FIXTURE_H

#include <stdint.h>

/* Writes a table with every grid count = `grid` (>= 2) and a payload picked by `seed` into out
 * (capacity cap); returns its length, 0 if it does not fit. */
uint32_t fixture_table(uint8_t *out, uint32_t cap, uint16_t grid, uint8_t seed);
/* Writes a format-2 table (formats/device_table.py's layout: the smallest counts, axes and a set-up the
 * inverse core accepts, codes picked by `seed`: a valid table of a made-up material model) into out
 * (capacity cap, 8-byte aligned for the core); returns its length, 0 if it does not fit. */
uint32_t fixture_table_v2(uint8_t *out, uint32_t cap, uint8_t seed);
/* Recomputes the trailing CRC-32 after a test edited the bytes. */
void fixture_table_fix_crc(uint8_t *table, uint32_t length);

#endif
