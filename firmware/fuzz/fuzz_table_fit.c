/* libFuzzer target over the inverse core the firmware links (tr_fit_bins, fit_core/fit_core.h), in single
 * precision as on the MCU: a format-2 device table (tests/table_fixture.c's) with bytes changed anywhere,
 * the length cut or not, and up to 8 bins of arbitrary floats.
 *
 * An input: one byte of edit count (low 4 bits; bit 4: cut the length by the next byte), then per edit
 * a u16 offset (little-endian, modulo the table's length) and the byte written there, then the bins,
 * 5 floats (I_b, I_w, I_c, rho_b, rho_w) of 4 bytes each.
 *
 * Invariants (abort = a finding), besides the sanitizers': the core returns TR_FIT_OK or
 * TR_FIT_ERR_TABLE (never ERR_ARGS for these arguments); with OK, every bin's flags are known FitFlag
 * bits, its outputs NaN exactly where an unusable-input flag is set, α in [0, 1], g in [-1, 1] and
 * σt >= 0 where they are numbers; and the unedited table is always taken. */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "fit_core.h"
#include "../tests/table_fixture.h"

#define FLAGS_UNUSABLE 0x207u /* NONFINITE_INPUT | NEGATIVE_INPUT | ABOVE_ONE | BAD_BACKGROUND */
#define FLAGS_KNOWN 0x6FFu    /* up to UNDERDETERMINED, without THICKNESS_DISAGREE */
#define MAX_BINS 8

static _Alignas(8) uint8_t base[4096];
static _Alignas(8) uint8_t table[sizeof base];
static uint32_t base_length;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (!base_length) {
        base_length = fixture_table_v2(base, sizeof base, 5);
        if (!base_length || tr_fit_bins(base, base_length, NULL, 0, NULL, NULL) != TR_FIT_OK) abort();
    }
    memcpy(table, base, base_length);
    size_t i = 0;
    uint32_t length = base_length;
    unsigned head = size ? data[i++] : 0, edits = head & 0x0Fu;
    if ((head & 0x10u) && i < size) length -= data[i++] % length;
    for (unsigned e = 0; e < edits && i + 3 <= size; e++, i += 3)
        table[(uint32_t)(data[i] | data[i + 1] << 8) % base_length] = data[i + 2];
    float in[MAX_BINS * TR_FIT_IN_PER_BIN], out[MAX_BINS * TR_FIT_OUT_PER_BIN];
    uint16_t flags[MAX_BINS];
    size_t n = (size - i) / sizeof(float[TR_FIT_IN_PER_BIN]);
    if (n > MAX_BINS) n = MAX_BINS;
    memcpy(in, data + i, n * sizeof(float[TR_FIT_IN_PER_BIN]));
    int rc = tr_fit_bins(table, length, in, n, out, flags);
    if (rc != TR_FIT_OK && rc != TR_FIT_ERR_TABLE) abort();
    if (rc == TR_FIT_ERR_TABLE && !edits && length == base_length) abort();
    if (rc != TR_FIT_OK) return 0;
    for (size_t b = 0; b < n; b++) {
        const float *o = &out[b * TR_FIT_OUT_PER_BIN];
        float alpha = o[TR_FIT_OUT_ALPHA], sigma_t = o[TR_FIT_OUT_SIGMA_T], g = o[TR_FIT_OUT_G];
        if (flags[b] & ~FLAGS_KNOWN) abort();
        if ((flags[b] & FLAGS_UNUSABLE) && !(isnan(alpha) && isnan(sigma_t) && isnan(g))) abort();
        if (!isnan(alpha) && !(alpha >= 0.0f && alpha <= 1.0f)) abort();
        if (!isnan(g) && !(g >= -1.0f && g <= 1.0f)) abort();
        if (!isnan(sigma_t) && !(sigma_t >= 0.0f)) abort();
    }
    return 0;
}
