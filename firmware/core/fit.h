/* Fitting on the device: the bins a master writes over Modbus file records, a run against the active map
 * table (read in place), and the results read back; the register map's fit_* items (registers.toml).
 *
 * A run fits FIT_BINS_PER_POLL bins per fit_poll(), so the main loop keeps answering Modbus and the motion
 * keeps its timing while a fit works. The fit itself is fit_core.h's tr_fit_bins (the inverse core shared
 * with the host, fit_core/ at the repository's root), linked when the Makefile compiles it in
 * (FIT_CORE_SRC); without it fit_available() is false and every run is refused as error_unavailable — the
 * firmware never makes results up. */
#ifndef TRIMETER_FIT_H
#define TRIMETER_FIT_H

#include <stdbool.h>
#include <stdint.h>

#include "registers_gen.h"
#include "storage.h"

#define FIT_MAX_BINS REG_HR_FIT_BIN_COUNT_MAX
#define FIT_BINS_PER_POLL 4u

typedef struct fit {
    uint16_t in[FIT_MAX_BINS * TRIMETER_FIT_INPUT_WORD_STRIDE];   /* file fit_input, as the master wrote it */
    uint16_t out[FIT_MAX_BINS * TRIMETER_FIT_OUTPUT_WORD_STRIDE]; /* file fit_output */
    const uint8_t *table;                                         /* the run's table, in place */
    uint32_t table_length;
    uint32_t table_crc32;                                         /* the table's own (trailing) CRC-32 */
    uint16_t count;  /* bins in the run */
    uint16_t done;   /* bins in `out` */
    trimeter_fit_status_t status;
} fit_t;

/* Whether the inverse core is linked into this build. */
bool fit_available(void);

void fit_init(fit_t *f);

/* fit_command = run: checks everything before any bin is fitted (the core, an active table, the stated
 * thickness against the table's, the core's acceptance of the table) and starts the run. Returns MB_OK or
 * the Modbus exception; f->status says which refusal (registers.toml, enums.fit_status). */
uint8_t fit_start(fit_t *f, const storage_t *st, uint16_t count, float thickness_mm);
void fit_abort(fit_t *f);
bool fit_busy(const fit_t *f);
/* Fits the next few bins of a run; nothing to do otherwise. */
void fit_poll(fit_t *f);

/* File records of enums.fit_file (FC 0x14 / 0x15): Modbus exception or MB_OK. */
uint8_t fit_write_records(fit_t *f, uint16_t file, uint16_t record, uint16_t n, const uint16_t *vals);
uint8_t fit_read_records(const fit_t *f, uint16_t file, uint16_t record, uint16_t n, uint16_t *out);
bool fit_is_file(uint16_t file);

#endif
