/* What the table fit (table_fit.c) shares with the host's compiled kernel: the FitFlag bits it sets, the
 * polish's constants, its fixed settings and tm_table_fit, the host's entry to it. The host's boundary
 * header (host/trimeter/inversion/native/invert.h) includes this one, and tools/gen_native.py generates the
 * Python side from the two together, so it is kept to the C subset that generator parses (see invert.h).
 * The firmware sees the table fit through fit_core.h alone. */
#ifndef TRIMETER_TABLE_FIT_H
#define TRIMETER_TABLE_FIT_H

#include <stddef.h>
#include <stdint.h>

/* A polish step at most this fraction of the one before it also ends a bin's polish (the table fit's and
 * the host kernel's) when the next step, extrapolated at that rate, would be below κ of the noise std
 * (ForwardGrid.step_is_small). */
#define TM_STEP_RATIO 0.25
/* The in-scattering correction takes L = ln(1 + r) a second time, at the moved σt, only where the
 * first is above this (ForwardGrid.correct_inscatter). */
#define TM_INSCATTER_ONCE 1e-3

/* FitFlag bits (trimeter.inversion.flags; a test checks that both agree): the table fit's, and the host
 * kernel's besides (THICKNESS_DISAGREE, STD_APPROXIMATE and the band flags are never the table fit's) */
enum tm_flag {
    TM_FLAG_NONFINITE_INPUT = 1 << 0,
    TM_FLAG_NEGATIVE_INPUT = 1 << 1,
    TM_FLAG_ABOVE_ONE = 1 << 2,
    TM_FLAG_BLACK_NOT_BELOW_WHITE = 1 << 3,
    TM_FLAG_IC_BELOW_FLOOR = 1 << 4,
    TM_FLAG_G_UNDEFINED = 1 << 5,
    TM_FLAG_OUTSIDE_MAP = 1 << 6,
    TM_FLAG_NOT_CONVERGED = 1 << 7,
    TM_FLAG_THICKNESS_DISAGREE = 1 << 8,
    TM_FLAG_BAD_BACKGROUND = 1 << 9,
    TM_FLAG_UNDERDETERMINED = 1 << 10,
    TM_FLAG_STD_APPROXIMATE = 1 << 11,
    TM_FLAG_BAND_UNRESOLVED = 1 << 12,
    TM_FLAG_PER_CHANNEL_BANDS = 1 << 13
};

/* The table fit is fit()'s lut fit with these settings, fixed (a test checks them against
 * trimeter.inversion.api's defaults). */
#define TM_TABLE_FIT_NOISE_REL 0.005
#define TM_TABLE_FIT_NOISE_ABS 2e-4
#define TM_TABLE_FIT_IC_FLOOR 1e-4
#define TM_TABLE_FIT_ALPHA_MIN_G 0.02
#define TM_TABLE_FIT_POLISH 8
#define TM_TABLE_FIT_POLISH_TOL 1e-6
#define TM_TABLE_FIT_POLISH_TOL_STD 3e-3
#define TM_TABLE_FIT_INPUT_TOLERANCE 1e-3
#define TM_TABLE_FIT_UNDERDETERMINED_ALPHA_STD 0.1
#define TM_TABLE_FIT_UNDERDETERMINED_G_STD 0.2
#define TM_TABLE_FIT_INSCATTER_REL_STD 0.05
/* tm_table_fit's returns besides 0 (tr_fit_bins's, checked in table_fit.c at compile time) */
#define TM_TABLE_FIT_ERR_TABLE -1
#define TM_TABLE_FIT_ERR_ARGS -2

/* The host's entry (its compiled kernel; the firmware calls tr_fit_bins): the same fit with double
 * inputs and outputs, in[5 i …] = I_b, I_w, I_c, rho_b, rho_w of bin i, out[3 i …] = α, σt, g (NaN where
 * unusable), flags[i] = FitFlag bits. n = 0 only checks the table. Double precision inside; the
 * -DTR_SINGLE build fits in single precision inside (as the MCU does). Returns 0 or TM_TABLE_FIT_ERR_*. */
int tm_table_fit(const uint8_t *table, size_t len, const double *in, size_t n, double *out, int64_t *flags);

#endif
