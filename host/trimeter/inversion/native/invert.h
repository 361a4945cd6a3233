/* The inversion kernel's boundary: everything a caller of the compiled kernel (Python through ctypes,
 * the firmware linking the same sources) sees. tools/gen_native.py reads this file and generates the
 * Python side (invert_h.py: ctypes structures, prototypes, flag bits, constants) and the ABI hash
 * (invert_abi.h, a hash of this file without its comments), so the two sides cannot drift apart:
 * `make check-gen` fails when a generated file is stale, and Python refuses a library whose
 * tm_abi_hash() is another header's.
 *
 * Kept to a small C subset the generator parses: `#define TM_NAME number`, enums of `NAME = 1 << k`
 * or plain counters, `typedef struct { … } tm_name;` with fields of int32_t / int64_t / double and
 * pointers to them, and one-line prototypes of tm_ functions.
 *
 * Data layouts (C order, float64):
 *   poly  [(na-1)(ns-1)(ng-1)][8 terms][3 coefs]  trilinear polynomial per forward cell, terms
 *         1, wa, ws, wg, wa·ws, wa·wg, ws·wg, wa·ws·wg; coefs A, B, C
 *   cells [ns][ny-1][nx-1][4 terms][2]            bilinear inverse cell, terms 1, fu, fv, fu·fv; (α, g)
 *   frame [ns][6]                                 (x0, y0, m00·(nx-1), m01·(nx-1), m10·(ny-1), m11·(ny-1))
 */
#ifndef TRIMETER_INVERT_H
#define TRIMETER_INVERT_H

#include <stddef.h>
#include <stdint.h>

/* A polish step at most this fraction of the one before it also ends a bin's polish when the next
 * step, extrapolated at that rate, would be below κ of the noise std (ForwardGrid.step_is_small). */
#define TM_STEP_RATIO 0.25
/* The in-scattering correction takes L = ln(1 + r) a second time, at the moved σt, only where the
 * first is above this (ForwardGrid.correct_inscatter). */
#define TM_INSCATTER_ONCE 1e-3

/* FitFlag bits (trimeter.inversion.flags; a test checks that both agree) */
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

/* The rows of a fit's output block (tm_fit, tm_fit_solve): TM_ROW_COUNT rows of n values, float64
 * except flags (int64), so that the caller hands over one address. conditioning_*: α's and g's std
 * at no less than the noise model, which UNDERDETERMINED is judged on. */
enum tm_row {
    TM_ROW_ALPHA,
    TM_ROW_SIGMA_T,
    TM_ROW_G,
    TM_ROW_ALPHA_STD,
    TM_ROW_SIGMA_T_STD,
    TM_ROW_G_STD,
    TM_ROW_SIGMA_T_BEER,
    TM_ROW_FLAGS,
    TM_ROW_CONDITIONING_ALPHA_STD,
    TM_ROW_CONDITIONING_G_STD,
    TM_ROW_COUNT
};

typedef struct {
    int32_t na, ns, ng;
    const double *alpha, *log_sigma_t, *g; /* axes */
    const double *inv_da, *inv_ds, *inv_dg; /* 1 / axis spacing, per interval */
    const double *poly;
    double alpha_lo, alpha_hi, g_lo, g_hi;
    /* I_c = a·x / (1 − b·x²), x = exp(−σt ℓ) (trimeter.forward.collimated.stack_constants) */
    double thickness_mm, stack_a, stack_b;
    double uniform_ds; /* 1 / the ln σt step when that axis is evenly spaced (as generated), else 0 */
    /* In-scattering into I_c (ForwardGrid.inscatter_log1p), or inscatter_L = NULL: L = ln(1 + r) on
     * this grid's α and g nodes and in_nt evenly spaced optical depths τ = σt·ℓ from 0 to in_tau_max,
     * [na][in_nt][ng]. */
    int32_t in_nt;
    const double *inscatter_L;
    double in_inv_dt, in_tau_max;
    /* The map's own error (ForwardGrid.model_var): variances of I_b, I_w on this grid's nodes,
     * [na][ns][ng][2], or NULL (then the scalar mc_stderr of the options stands in for it). */
    const double *model_var;
} tm_forward_grid;

typedef struct {
    int32_t ns, ny, nx;
    const double *cells;
    const double *frame;
    /* the table's own σt nodes (its slices); the forward grid may be finer (refined in σt at load) */
    const double *log_sigma_t, *inv_ds;
    double uniform_ds; /* as in tm_forward_grid */
} tm_inverse_table;

typedef struct {
    double noise_rel, noise_abs; /* intensity noise σ_I = noise_rel·I + noise_abs */
    double mc_stderr;            /* the map's MC std-error, added to σ_I of I_b and I_w in quadrature */
    double ic_floor, alpha_min_g;
    double input_tolerance;      /* intensities this far outside [0, 1] are still taken as noise */
    double ref_rho_b, ref_rho_w; /* stand-in backgrounds for unusable bins */
    double t_max;                /* I_c at σt = 0 */
    double t_valid;              /* the Beer-Lambert inverse is defined for 0 < I_c ≤ t_valid */
    double step_tol;
    double step_tol_std;         /* κ: a polish step below κ of the bin's noise std also counts as converged */
    double underdetermined_alpha_std, underdetermined_g_std; /* FLAG_UNDERDETERMINED above these stds */
    double thickness_rel_std;    /* the sample thickness's relative std: σt's (α and g do not depend on it) */
    double inscatter_rel_std;    /* the in-scattering correction's relative std */
    /* FLAG_STD_APPROXIMATE: checked where α's or g's std is above these, over ±sigmas σ, to tol of it */
    double std_check_alpha, std_check_g, std_check_sigmas, std_check_tol;
    int32_t iterations;
} tm_fit_options;

/* The fit from a self-sufficient device table (.tlut v2, trimeter.formats.device_table) alone, one bin at
 * a time with no allocation (table_fit.c, the source the firmware links as tr_fit_bins,
 * firmware/core/fit_core.h): fit()'s lut fit with these settings, fixed (a test checks them against
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
/* tm_table_fit's returns besides 0 (tr_fit_bins's, checked against fit_core.h at compile time) */
#define TM_TABLE_FIT_ERR_TABLE -1
#define TM_TABLE_FIT_ERR_ARGS -2

/* The hash of this header (invert_abi.h) the library was compiled with. */
uint64_t tm_abi_hash(void);
/* Host library only: a hash of the sources it was built from (`make native` passes it; 0 when built
 * otherwise), so that Python can tell a library older than its sources. */
uint64_t tm_source_hash(void);

/* 0: the scalar polish only, 1: four bins per Newton step with AVX2 where the CPU has it (bit for bit
 * the same results). Returns whether the four-lane step is in use now. */
int tm_set_simd(int enabled);

/* The whole single-thickness fit in one call, with scratch from malloc (host library only): -1 on a
 * malformed grid or a missing guess, -2 when out of memory, else the number of Newton steps taken. */
long long tm_fit(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w, const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, const double *alpha0, const double *g0, double *outputs);

/* Several thicknesses' fits of the same bins combined (trimeter.inversion.finish.combine, operation for
 * operation): fits holds k output blocks one after the other (k × TM_ROW_COUNT × n, each as tm_fit
 * writes it; its conditioning rows the α and g stds where that fit has none), outputs one more. The
 * inverse-variance mean and std, flags merged, STD_APPROXIMATE where a flagged thickness carries a
 * quarter of the weight, THICKNESS_DISAGREE beyond disagree_sigmas combined stds, UNDERDETERMINED on
 * the combined conditioning stds. */
void tm_combine(size_t k, size_t n, const double *fits, double underdetermined_alpha_std, double underdetermined_g_std, double disagree_sigmas, double *outputs);

/* The fit in two halves around a caller-owned scratch block of tm_fit_scratch_size(n) bytes (no
 * allocation: what the firmware calls), with a guess (e.g. an MLP's) from the features in between. */
size_t tm_fit_scratch_size(size_t n);
void tm_fit_prepare(const tm_forward_grid *f, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w, const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, void *scratch, double *outputs, double log_lo, double log_hi, float *features);
long long tm_fit_solve(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n, const double *alpha0, const double *g0, void *scratch, double *outputs);

/* The fit from a device table of len bytes (read in place; its CRC-32 is the caller's to check):
 * in[5 i …] = I_b, I_w, I_c, rho_b, rho_w of bin i, out[3 i …] = α, σt, g (NaN where unusable),
 * flags[i] = FitFlag bits. n = 0 only checks the table. Double precision on the host; the -DTR_SINGLE
 * build fits in single precision inside (as the MCU does). Returns 0 or TM_TABLE_FIT_ERR_*. */
int tm_table_fit(const uint8_t *table, size_t len, const double *in, size_t n, double *out, int64_t *flags);

/* The device table's compact model at n points, as the table fit evaluates it (tr_compact_eval;
 * trimeter.model.compact.CompactForward.evaluate, clamped to the map's box): out[12 i …] = A, B, C, then
 * their derivatives in α, in ln σt and in g. The host's stds of the table fit take its Jacobian from here
 * (trimeter.inversion.table_std). Returns 0 or TM_TABLE_FIT_ERR_*. */
int tm_table_eval(const uint8_t *table, size_t len, size_t n, const double *alpha, const double *log_sigma_t,
                  const double *g, double *out);

/* The parts for the numpy-side callers: the guess and polish at a given ln σt (J: n × 3 × 3; with
 * scratch from malloc, host library only) and the first-order stds from given Jacobians. */
int tm_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b, const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w, int iterations, double step_tol, const double *step_var, double *alpha, double *g, double *residual, double *J);
void tm_propagate(size_t n, const double *J, const double *sigma_I, const double *sigma_t_var, double *std_a, double *std_s, double *std_g);

#endif
