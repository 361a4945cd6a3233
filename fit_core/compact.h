/* The self-sufficient device table (.tlut v2, trimeter.formats.device_table) as the fit from it reads it
 * in place: a checked view of its header and sections, the compact forward model evaluated on the
 * fly (trimeter.model.compact.CompactForward), the inverse table's guess, the in-scattering table and
 * the map's error at its nodes. Shared by compact.c and table_fit.c; callers see fit_core.h and
 * table_fit.h only.
 *
 * tr_real is double on the host and float on the MCU (-DTR_SINGLE, the Cortex-M4's FPU is single
 * precision): every literal and math call below goes through R() and the R_ functions, so that a
 * single-precision build never promotes to double. */
#ifndef TRIMETER_COMPACT_H
#define TRIMETER_COMPACT_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>

#ifdef TR_SINGLE
typedef float tr_real;
#define R(x) ((float)(x))
/* the builtins: a freestanding build (the firmware's) otherwise calls a library function for what the
 * FPU does in one instruction (VSQRT.F32, VABS.F32) */
#define R_SQRT __builtin_sqrtf
#define R_LOG logf
#define R_LOG1P log1pf
#define R_EXP expf
#define R_FABS __builtin_fabsf
#else
typedef double tr_real;
#define R(x) ((double)(x))
#define R_SQRT sqrt
#define R_LOG log
#define R_LOG1P log1p
#define R_EXP exp
#define R_FABS fabs
#endif

/* Section order of the format (trimeter.formats.device_table.SECTIONS) */
enum {
    TR_SEC_ALPHA,
    TR_SEC_LOG_SIGMA_T,
    TR_SEC_G,
    TR_SEC_SCALES,
    TR_SEC_SPLINE,
    TR_SEC_MODEL_STD,
    TR_SEC_INSCATTER,
    TR_SEC_INV_FRAME,
    TR_SEC_INV_ALPHA_Q,
    TR_SEC_INV_G_Q,
    TR_SEC_GEOMETRY,
    TR_SEC_COUNT
};
/* Rows of the scales section: (offset, step) of each quantized quantity */
enum { TR_SCALE_A, TR_SCALE_B, TR_SCALE_C, TR_SCALE_STD_B, TR_SCALE_STD_W, TR_SCALE_L, TR_SCALE_COUNT };

/* A checked table: pointers into the caller's bytes (nothing copied) and the numbers derived from the
 * header. The float sections are read as float, the codes as uint16_t: the reader has checked that
 * every section starts 4-byte aligned in memory and that both byte orders agree (little-endian). */
typedef struct {
    int na, ns, ng, n_inv, nu, nt, nv;
    const float *alpha, *log_sigma_t, *g, *scales, *inv_frame;
    const uint16_t *spline, *model_std, *inscatter, *inv_alpha_q, *inv_g_q;
    tr_real n, thickness_mm, rho_b_ref, rho_w_ref, mc_stderr;
    tr_real u_max, tau_max, v_max;
    /* I_c = a·x / (1 − b·x²), x = exp(−σt ℓ), and T(σt = 0) (trimeter.model.collimated.stack_constants) */
    tr_real stack_a, stack_b, t_max, t_valid;
} tr_table;

/* A, B, C at a point and their derivatives in α, ln σt and g */
typedef struct { tr_real v[3], da[3], ds[3], dg[3]; } tr_abc;

/* 0 and *t filled, or -1: not a v2 table this reader can use (any defect in the header, the section
 * directory, the axes or the scales; the CRC-32 is not checked here, see compact.c). */
int tr_table_open(const uint8_t *data, size_t len, tr_table *t);

/* The compact model on one ln σt, which stays fixed while a bin's (α, g) are solved: the cubic B-spline
 * basis along ln σt (the first of its 4 non-zero functions, their values and derivatives), and the
 * coefficients of the last (α, g) window contracted with it, kept for the next evaluation in the same
 * window (a Newton step rarely leaves it; the sums are the ones it would compute, so the results do
 * not depend on the reuse). */
typedef struct {
    int first;
    tr_real N[4], dN[4];
    int window_alpha, window_g; /* the window the sums belong to; -1: none yet */
    tr_real sum[4][4][3], sum_d[4][4][3]; /* [g node][α row][A, B, C]: Σ code·N and Σ code·dN along ln σt */
} tr_sigma_slice;
void tr_sigma_slice_init(const tr_table *t, tr_real log_sigma_t, tr_sigma_slice *slice);

/* CompactForward.evaluate at one point on the slice's ln σt, clamped to the map's box */
void tr_compact_eval(const tr_table *t, tr_real alpha, tr_sigma_slice *sigma, tr_real g, tr_abc *out);

/* TableInverter.initial_guess: the inverse table's (α, g) at ln σt (clamped to the axis) */
void tr_inverse_guess(const tr_table *t, tr_real log_sigma_t, tr_real I_b, tr_real I_w, tr_real *alpha, tr_real *g);

/* L = ln(1 + r) of the in-scattered light at (α, σt, g), as the host's lut fit takes it
 * (ForwardGrid.inscatter_log1p on the table's grid refined at load), in two halves: the (α, g) cells
 * once, then L at each σt (the fit takes it at two) */
typedef struct {
    tr_real wa, wg, wu[2], wv[2];
    int iu[2], iv[2];
} tr_inscatter_cells;
void tr_inscatter_cells_init(const tr_table *t, tr_real alpha, tr_real g, tr_inscatter_cells *cells);
tr_real tr_inscatter_log1p_at(const tr_table *t, const tr_inscatter_cells *cells, tr_real sigma_t);

/* The map's error variances of I_b, I_w at (α, ln σt, g), trilinear on the nodes (ForwardGrid.model_variance) */
void tr_model_variance(const tr_table *t, tr_real alpha, tr_real log_sigma_t, tr_real g, tr_real *var_b,
                       tr_real *var_w);

static inline tr_real tr_clamp(tr_real x, tr_real lo, tr_real hi) { return x < lo ? lo : (x > hi ? hi : x); }

#endif
