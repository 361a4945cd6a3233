/* Fitting on the device; see fit.h. */
#include "fit.h"

#include <stddef.h>
#include <string.h>

#include "fit_core.h"
#include "map_table.h"
#include "modbus.h"
#include "regmap.h"

#define IN_STRIDE TRIMETER_FIT_INPUT_WORD_STRIDE
#define OUT_STRIDE TRIMETER_FIT_OUTPUT_WORD_STRIDE

#ifdef TRIMETER_FIT_CORE
bool fit_available(void) { return true; }
#else
/* Until the Makefile links the core, the reference stays unresolved (NULL) instead of failing the link,
 * and the device says so (fit_available, error_unavailable). With TRIMETER_FIT_CORE set the reference
 * is strong: a core that does not provide the seam fails the build. */
#pragma weak tr_fit_bins
bool fit_available(void) { return tr_fit_bins != NULL; }
#endif

void fit_init(fit_t *f) { memset(f, 0, sizeof *f); }

bool fit_busy(const fit_t *f) { return f->status == TRIMETER_FIT_STATUS_BUSY; }

static uint8_t refuse(fit_t *f, trimeter_fit_status_t why, uint8_t exception)
{
    f->status = why;
    return exception;
}

uint8_t fit_start(fit_t *f, const storage_t *st, uint16_t count, float thickness_mm)
{
    if (fit_busy(f)) return MB_EX_SERVER_DEVICE_BUSY;
    if (count == 0 || count > FIT_MAX_BINS) return MB_EX_ILLEGAL_DATA_VALUE;
    f->done = 0; /* a refused run leaves no earlier results readable as if they were its own */
    f->table = NULL;
    if (!fit_available()) return refuse(f, TRIMETER_FIT_STATUS_ERROR_UNAVAILABLE, MB_EX_ILLEGAL_FUNCTION);
    uint32_t length = 0;
    const uint8_t *table = storage_map_active_bytes(st, &length);
    if (!table) return refuse(f, TRIMETER_FIT_STATUS_ERROR_NO_TABLE, MB_EX_ILLEGAL_FUNCTION);
    /* a valid slot passed map_table_check, so its header is there and ℓ is finite and positive */
    float thickness = map_table_thickness_mm(table), off = thickness_mm - thickness;
    float tolerance = 1e-6f * (thickness > 1.0f ? thickness : 1.0f);
    if (!(off <= tolerance && -off <= tolerance))
        return refuse(f, TRIMETER_FIT_STATUS_ERROR_GEOMETRY, MB_EX_ILLEGAL_DATA_VALUE);
    if (tr_fit_bins(table, length, NULL, 0, NULL, NULL) != TR_FIT_OK)
        return refuse(f, TRIMETER_FIT_STATUS_ERROR_TABLE, MB_EX_ILLEGAL_FUNCTION);
    f->table = table;
    f->table_length = length;
    /* its own CRC (the last 4 bytes) names it: a CRC-32 over a whole table is the same for every table */
    const uint8_t *tail = table + length - 4;
    f->table_crc32 = (uint32_t)tail[0] | (uint32_t)tail[1] << 8 | (uint32_t)tail[2] << 16 | (uint32_t)tail[3] << 24;
    f->count = count;
    f->status = TRIMETER_FIT_STATUS_BUSY;
    return MB_OK;
}

void fit_abort(fit_t *f)
{
    if (fit_busy(f)) f->status = TRIMETER_FIT_STATUS_ABORTED;
}

void fit_poll(fit_t *f)
{
    if (!fit_busy(f)) return;
    float in[FIT_BINS_PER_POLL * TR_FIT_IN_PER_BIN] = {0}, out[FIT_BINS_PER_POLL * TR_FIT_OUT_PER_BIN];
    uint16_t flags[FIT_BINS_PER_POLL];
    static const uint8_t in_word[TR_FIT_IN_PER_BIN] = {
        [TR_FIT_IN_I_B] = TRIMETER_FIT_INPUT_WORD_I_B,     [TR_FIT_IN_I_W] = TRIMETER_FIT_INPUT_WORD_I_W,
        [TR_FIT_IN_I_C] = TRIMETER_FIT_INPUT_WORD_I_C,     [TR_FIT_IN_RHO_B] = TRIMETER_FIT_INPUT_WORD_RHO_B,
        [TR_FIT_IN_RHO_W] = TRIMETER_FIT_INPUT_WORD_RHO_W,
    };
    static const uint8_t out_word[TR_FIT_OUT_PER_BIN] = {
        [TR_FIT_OUT_ALPHA] = TRIMETER_FIT_OUTPUT_WORD_ALPHA,
        [TR_FIT_OUT_SIGMA_T] = TRIMETER_FIT_OUTPUT_WORD_SIGMA_T,
        [TR_FIT_OUT_G] = TRIMETER_FIT_OUTPUT_WORD_G,
    };
    size_t n = f->count - f->done;
    if (n > FIT_BINS_PER_POLL) n = FIT_BINS_PER_POLL;
    for (size_t i = 0; i < n; i++)
        for (size_t k = 0; k < TR_FIT_IN_PER_BIN; k++)
            in[i * TR_FIT_IN_PER_BIN + k] = regmap_get_f32(&f->in[(f->done + i) * IN_STRIDE + in_word[k]]);
    if (tr_fit_bins(f->table, f->table_length, in, n, out, flags) != TR_FIT_OK) {
        f->status = TRIMETER_FIT_STATUS_ERROR_CORE;
        return;
    }
    for (size_t i = 0; i < n; i++) {
        uint16_t *w = &f->out[(f->done + i) * OUT_STRIDE];
        for (size_t k = 0; k < TR_FIT_OUT_PER_BIN; k++) regmap_put_f32(&w[out_word[k]], out[i * TR_FIT_OUT_PER_BIN + k]);
        w[TRIMETER_FIT_OUTPUT_WORD_FLAGS] = flags[i];
    }
    f->done = (uint16_t)(f->done + n);
    if (f->done == f->count) f->status = TRIMETER_FIT_STATUS_DONE;
}

bool fit_is_file(uint16_t file) { return file == TRIMETER_FIT_FILE_INPUT || file == TRIMETER_FIT_FILE_OUTPUT; }

/* Records record..record+n-1 inside the first `limit` of a file? */
static bool within(uint16_t record, uint16_t n, uint32_t limit) { return n > 0 && record <= limit && n <= limit - record; }

uint8_t fit_write_records(fit_t *f, uint16_t file, uint16_t record, uint16_t n, const uint16_t *vals)
{
    if (file != TRIMETER_FIT_FILE_INPUT) return MB_EX_ILLEGAL_DATA_ADDRESS; /* the results are read-only */
    if (!within(record, n, FIT_MAX_BINS * IN_STRIDE)) return MB_EX_ILLEGAL_DATA_ADDRESS;
    if (fit_busy(f)) return MB_EX_SERVER_DEVICE_BUSY; /* the run reads these */
    memcpy(&f->in[record], vals, n * sizeof *vals);
    return MB_OK;
}

uint8_t fit_read_records(const fit_t *f, uint16_t file, uint16_t record, uint16_t n, uint16_t *out)
{
    if (file == TRIMETER_FIT_FILE_INPUT) {
        if (!within(record, n, FIT_MAX_BINS * IN_STRIDE)) return MB_EX_ILLEGAL_DATA_ADDRESS;
        memcpy(out, &f->in[record], n * sizeof *out);
        return MB_OK;
    }
    if (file != TRIMETER_FIT_FILE_OUTPUT || !within(record, n, (uint32_t)f->done * OUT_STRIDE))
        return MB_EX_ILLEGAL_DATA_ADDRESS;
    memcpy(out, &f->out[record], n * sizeof *out);
    return MB_OK;
}
