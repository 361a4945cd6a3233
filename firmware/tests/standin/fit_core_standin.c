/* A stand-in for the inverse core, for testing the fit's plumbing end to end before the real core is
 * linked (tests/device/test_fit_on_device.py builds the sim with it: make sim FIT_CORE_SRC=this file;
 * tests/test_standalone.c links it).
 * A transparent function of each bin, so a test can predict every output exactly in float32:
 *   alpha = I_b, sigma_t = 10 * I_w, g = I_c - rho_b - rho_w; a bin with a non-finite input has
 *   FitFlag NONFINITE_INPUT and NaN outputs. It accepts a table only if it starts with the map-table magic.
 * Never in a product build: it fits nothing. */
#include <math.h>
#include <string.h>

#include "fit_core.h"
#include "table_fit.h"

int tr_fit_bins(const uint8_t *table, size_t len, const float *in, size_t n, float *out, uint16_t *flags)
{
    if (!table || len < 8 || memcmp(table, "\x89TRLUT\r\n", 8) != 0) return TR_FIT_ERR_TABLE;
    if (n > 0 && (!in || !out || !flags)) return TR_FIT_ERR_ARGS;
    for (size_t i = 0; i < n; i++) {
        const float *b = &in[i * TR_FIT_IN_PER_BIN];
        float *o = &out[i * TR_FIT_OUT_PER_BIN];
        int finite = 1;
        for (int k = 0; k < TR_FIT_IN_PER_BIN; k++) finite = finite && isfinite(b[k]);
        flags[i] = finite ? 0u : TM_FLAG_NONFINITE_INPUT;
        o[TR_FIT_OUT_ALPHA] = finite ? b[TR_FIT_IN_I_B] : NAN;
        o[TR_FIT_OUT_SIGMA_T] = finite ? 10.0f * b[TR_FIT_IN_I_W] : NAN;
        o[TR_FIT_OUT_G] = finite ? b[TR_FIT_IN_I_C] - b[TR_FIT_IN_RHO_B] - b[TR_FIT_IN_RHO_W] : NAN;
    }
    return TR_FIT_OK;
}
