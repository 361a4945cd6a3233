/* Register-map rules over the generated descriptor table (registers_gen.{h,c}), so the app does
 * not restate them: which addresses exist, which are writable, min/max/allowed values, and that a
 * write must cover wide (two-register) values whole. Also the wide-value word helpers.
 * Return values are Modbus exception codes (modbus.h), MB_OK when allowed. */
#ifndef TRIMETER_REGMAP_H
#define TRIMETER_REGMAP_H

#include <stdint.h>

#include "registers_gen.h"

/* The item covering `address` in `table` (its first or second word), or NULL for a gap. */
const regmap_entry_t *regmap_find(regmap_table_t table, uint16_t address);

/* Reads: inside the table's span (REG_*_SPAN) -> MB_OK (gaps read 0), else exception 02. */
uint8_t regmap_check_read(regmap_table_t table, uint16_t addr, uint16_t n);

/* Coil writes: every address mapped and writable -> MB_OK, else 02. */
uint8_t regmap_check_write_bits(uint16_t addr, uint16_t n);

/* Holding-register writes: every word mapped and writable, no wide value cut in half (02), every
 * value within min..max / allowed and finite for f32 (03). Checks everything before the app
 * changes anything, so a refused write changes nothing. */
uint8_t regmap_check_write_regs(uint16_t addr, uint16_t n, const uint16_t *vals);

/* Fill a bank indexed by address (`span` words; for coils one word per coil, 0/1)
 * with the declared defaults of `table`. */
void regmap_fill_defaults(regmap_table_t table, uint16_t *bank, uint16_t span);

/* Wide values: words[0] is the high word (big-endian word order). */
uint32_t regmap_get_u32(const uint16_t *words);
void regmap_put_u32(uint16_t *words, uint32_t v);
float regmap_get_f32(const uint16_t *words);
void regmap_put_f32(uint16_t *words, float v);

#endif
