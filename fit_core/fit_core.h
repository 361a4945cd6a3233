/* The one seam between the firmware and the inverse core it shares with the host (this directory:
 * table_fit.c and compact.c, compiled for both ports by firmware/Makefile's FIT_CORE_SRC; the host's
 * kernel builds the same sources in double precision and calls them as tm_table_fit, table_fit.h).
 *
 * tr_fit_bins fits n bins with the map table `table` (len bytes, read in place: flash on the MCU; a
 * format-2 device table, 4-byte aligned; its CRC-32 is the storage's to check, map_table.h):
 *   in[TR_FIT_IN_PER_BIN * i + TR_FIT_IN_*]   I_b, I_w, I_c (relative to the calibration), rho_b, rho_w
 *   out[TR_FIT_OUT_PER_BIN * i + TR_FIT_OUT_*] alpha, sigma_t (1/mm), g; NaN where the bin is unusable
 *   flags[i]                                   trimeter.inversion.flags.FitFlag bits, 0 = a clean fit
 * Any float input (NaN, inf, negative, above one, a background outside [0, 1]) is a flagged bin, never a
 * fault. n = 0 only checks that the core fits with this table (its format and sizes): the firmware calls
 * that before a run, so a table the core cannot use is refused up front. Single precision; no malloc; the
 * core keeps no state between calls, so the firmware may fit a run a few bins per call.
 *
 * Returns TR_FIT_OK, or TR_FIT_ERR_TABLE (not a table this core fits with; outputs untouched), or
 * TR_FIT_ERR_ARGS (a NULL pointer with n > 0). */
#ifndef TRIMETER_FIT_CORE_H
#define TRIMETER_FIT_CORE_H

#include <stddef.h>
#include <stdint.h>

enum { TR_FIT_IN_I_B, TR_FIT_IN_I_W, TR_FIT_IN_I_C, TR_FIT_IN_RHO_B, TR_FIT_IN_RHO_W, TR_FIT_IN_PER_BIN };
enum { TR_FIT_OUT_ALPHA, TR_FIT_OUT_SIGMA_T, TR_FIT_OUT_G, TR_FIT_OUT_PER_BIN };
enum { TR_FIT_OK = 0, TR_FIT_ERR_TABLE = -1, TR_FIT_ERR_ARGS = -2 };

int tr_fit_bins(const uint8_t *table, size_t len, const float *in, size_t n, float *out, uint16_t *flags);

#endif
