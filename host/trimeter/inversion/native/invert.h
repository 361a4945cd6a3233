/* The inversion kernel's boundary: everything Python (through ctypes) sees of the compiled kernel. The
 * part shared with the firmware (the FitFlag bits, the polish's constants, the table fit's settings and
 * tm_table_fit) is declared once in fit_core/table_fit.h, included below. tools/gen_native.py reads this
 * file, with that include in place, and generates the Python side (invert_h.py: ctypes structures,
 * prototypes, flag bits, constants) and the ABI hash (invert_abi.h, a hash of both without their
 * comments), so the two sides cannot drift apart: `make check-gen` fails when a generated file is stale,
 * and Python refuses a library whose tm_abi_hash() is another header's.
 *
 * Kept to a small C subset the generator parses: `#include "table_fit.h"`, `#define TM_NAME number`,
 * enums of `NAME = 1 << k` or plain counters, `typedef struct { … } tm_name;` with fields of uint16_t /
 * int32_t / int64_t / double and pointers to them, and one-line prototypes of tm_ functions.
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

#include "table_fit.h"

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
    /* Where the search for α's (g's) cell starts, or NULL (a binary search): alpha_index[b] is the cell
     * of α = alpha[0] + b / alpha_index_scale, b < alpha_index_n; the cell of any α is then the walk from
     * alpha_index[(α − alpha[0])·scale], a step or two on an axis refined unevenly, where a binary
     * search is ~7 dependent loads. Any index in [0, na−2] gives the same cell, only more slowly. */
    int32_t alpha_index_n, g_index_n;
    const uint16_t *alpha_index, *g_index;
    double alpha_index_scale, g_index_scale;
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

/* The hash of this header (invert_abi.h) the library was compiled with. */
uint64_t tm_abi_hash(void);
/* Host library only: a hash of the sources it was built from (`make native` passes it; 0 when built
 * otherwise), so that Python can tell a library older than its sources. */
uint64_t tm_source_hash(void);

/* 0: the scalar loops only, 1: four bins per step with AVX2 where the CPU has it (the polish, the σ
 * check, two thicknesses' combination; bit for bit the same results). Returns whether the four-lane
 * steps are in use now. */
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

/* Several thicknesses of the same n bins fitted and combined in one call (host library only): thickness j
 * (grids[j], tables[j], options[j]: k of each, side by side) fitted as tm_fit fits it, from row j of the
 * k × n inputs (sd_in: k × n × 3, or NULL), into block j of fits (k × TM_ROW_COUNT × n); then tm_combine
 * of those blocks into outputs (NULL: none, e.g. for one thickness, whose fit is then tm_fit's with the
 * table's guess). Up to `threads` threads share the bins out in parts of a thickness each
 * (the caller's included, the others kept for the next call; ≤ 1: all in the caller's): the same
 * results for any count. -1 on a malformed grid or table, -2 when out of memory, else the Newton steps
 * taken over all thicknesses. */
long long tm_fit_thicknesses(size_t k, const tm_forward_grid *grids, const tm_inverse_table *tables, const tm_fit_options *options, size_t n, const double *I_b, const double *I_w, const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, double underdetermined_alpha_std, double underdetermined_g_std, double disagree_sigmas, double *fits, double *outputs, int threads);

/* A tm_fit_thicknesses(k, …, n, …, threads) to come (host library only): the helpers it will hand parts to
 * are woken now and wait for it awake for a millisecond, so that the call does not wait for their CPUs to
 * wake from idle. Changes no result; without it, or past the wait, the call wakes them itself. */
void tm_expect_fit(size_t k, size_t n, int threads);

/* The fit in two halves around a caller-owned scratch block of tm_fit_scratch_size(n) bytes (no
 * allocation: what the firmware calls), with a guess (e.g. an MLP's) from the features in between. */
size_t tm_fit_scratch_size(size_t n);
void tm_fit_prepare(const tm_forward_grid *f, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w, const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, void *scratch, double *outputs, double log_lo, double log_hi, float *features);
long long tm_fit_solve(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n, const double *alpha0, const double *g0, void *scratch, double *outputs);

/* The device table's compact model at n points, as the table fit evaluates it (tr_compact_eval;
 * trimeter.model.compact.CompactForward.evaluate, clamped to the map's box): out[12 i …] = A, B, C, then
 * their derivatives in α, in ln σt and in g. The host's stds of the table fit take its Jacobian from here
 * (trimeter.inversion.table_std). Host library only (library.c). Returns 0 or TM_TABLE_FIT_ERR_*. */
int tm_table_eval(const uint8_t *table, size_t len, size_t n, const double *alpha, const double *log_sigma_t,
                  const double *g, double *out);

/* The parts for the numpy-side callers: the guess and polish at a given ln σt (J: n × 3 × 3; with
 * scratch from malloc, host library only) and the first-order stds from given Jacobians. */
int tm_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b, const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w, int iterations, double step_tol, const double *step_var, double *alpha, double *g, double *residual, double *J);
void tm_propagate(size_t n, const double *J, const double *sigma_I, const double *sigma_t_var, double *std_a, double *std_s, double *std_g);

#endif
