/* What the kernel's translation units share and callers do not see: the per-bin working types, the
 * small inline pieces every stage evaluates (cell lookups, the trilinear coefficients, the background
 * response, the damped step), and the stages' entry points. Each stage is the numpy kernel's
 * (trimeter.inversion.kernel / lut / api) operation for operation, so that both agree bit for bit
 * up to rounding order (tests/inversion/test_native_kernel.py).
 *   lookups.c   the table's initial guess, in-scattering and model-error tables, cell prefetch
 *   newton.c    the damped Gauss-Newton polish (scalar), the Jacobian at the solution
 *   simd.c      four bins per step with AVX2: the polish, the σ check, two thicknesses' combination
 *               (x86-64 only; empty elsewhere)
 *   pipeline.c  the whole fit: input flags, σt from I_c, polish, in-scattering, stds, their check
 *   library.c   the host library's extras: malloc'd scratch, threads sharing out a fit's bins, the source hash
 * `make native-portable` builds the first four for the Cortex-M4 too (the stand-in for a host without
 * AVX2); only library.c allocates or starts threads. */
#ifndef TRIMETER_INVERT_INTERNAL_H
#define TRIMETER_INVERT_INTERNAL_H

#include <math.h>

#include "invert.h"

enum {
    TM_FLAGS_UNUSABLE = TM_FLAG_NONFINITE_INPUT | TM_FLAG_NEGATIVE_INPUT | TM_FLAG_ABOVE_ONE | TM_FLAG_BAD_BACKGROUND,
    /* bins whose stds already come with a caveat are not checked for TM_FLAG_STD_APPROXIMATE */
    TM_FLAGS_STD_CHECK_SKIP = TM_FLAGS_UNUSABLE | TM_FLAG_UNDERDETERMINED | TM_FLAG_G_UNDEFINED | TM_FLAG_OUTSIDE_MAP |
                              TM_FLAG_NOT_CONVERGED,
};

/* The four-lane polish exists where the compiler can target AVX2 (chosen at run time by CPU) */
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define TM_SIMD 1
#endif

static inline double clampd(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* numpy: i = clip(searchsorted(axis, x, side="right") - 1, 0, n-2); w = clip((x - axis[i]) inv_d[i], 0, 1) */
static inline int find_cell(const double *axis, const double *inv_d, int n, double x, double *w) {
    /* Branchless binary search for the last node <= x (a conditional move per halving: the
     * branchy version mispredicts on every other step at random bins). */
    const double *base = axis;
    int len = n;
    while (len > 1) {
        int half = len >> 1;
        base = (base[half] <= x) ? base + half : base;
        len -= half;
    }
    int i = (int)(base - axis);
    if (i > n - 2) i = n - 2;
    *w = clampd((x - axis[i]) * inv_d[i], 0.0, 1.0);
    return i;
}

/* find_cell from a starting cell i in [0, n-2]: walk down while x is below the cell, up while the
 * next node is ≤ x. Same result as find_cell for every non-NaN x; cheap when i is near the answer. */
static inline int walk_from(const double *axis, const double *inv_d, int n, double x, int i, double *w) {
    while (i > 0 && x < axis[i]) i--;
    while (i < n - 2 && axis[i + 1] <= x) i++;
    *w = clampd((x - axis[i]) * inv_d[i], 0.0, 1.0);
    return i;
}

/* Whether walk_from(…, x, i, …) stays at i: x in cell i (the end cells reaching past their ends). */
static inline int in_cell(const double *axis, int n, int i, double x) {
    return (i == 0 || axis[i] <= x) && (i == n - 2 || x < axis[i + 1]);
}

/* find_cell on an evenly spaced axis (inv_step = 1 / its step; 0: not evenly spaced, binary search):
 * the index straight from x, then a step either way for rounding at a node. */
static inline int find_cell_on(const double *axis, const double *inv_d, int n, double inv_step, double x, double *w) {
    if (!(inv_step > 0.0) || !isfinite(x)) return find_cell(axis, inv_d, n, x, w);
    double t = (x - axis[0]) * inv_step;
    return walk_from(axis, inv_d, n, x, t <= 0.0 ? 0 : (t >= n - 2 ? n - 2 : (int)t), w);
}

/* find_cell through an axis's index (tm_forward_grid's alpha_index; NULL: the binary search): the walk
 * from the cell the index gives for x's bucket. A NaN x takes bucket 0, whose cell is 0, as find_cell's. */
static inline int find_cell_indexed(const double *axis, const double *inv_d, int n, const uint16_t *index,
                                    int index_n, double scale, double x, double *w) {
    if (!index) return find_cell(axis, inv_d, n, x, w);
    double t = (x - axis[0]) * scale;
    int b = t >= 1.0 ? (t < index_n - 1 ? (int)t : index_n - 1) : 0;
    return walk_from(axis, inv_d, n, x, index[b], w);
}

/* find_cell_indexed near the cell found last time (hint; < 0: none): that cell while x is still in
 * it (Newton iterates converge, so mostly), else found afresh (a walk from the hint would mispredict a
 * branch per cell it crosses). */
static inline int cell_near(const double *axis, const double *inv_d, int n, const uint16_t *index, int index_n,
                            double scale, double x, int hint, double *w) {
    if (hint >= 0 && in_cell(axis, n, hint, x)) {
        *w = clampd((x - axis[hint]) * inv_d[hint], 0.0, 1.0);
        return hint;
    }
    return find_cell_indexed(axis, inv_d, n, index, index_n, scale, x, w);
}

/* The two on a forward grid's α and g axes */
#define TM_ALPHA_AXIS(f) (f)->alpha, (f)->inv_da, (f)->na, (f)->alpha_index, (f)->alpha_index_n, (f)->alpha_index_scale
#define TM_G_AXIS(f) (f)->g, (f)->inv_dg, (f)->ng, (f)->g_index, (f)->g_index_n, (f)->g_index_scale

static inline int alpha_cell(const tm_forward_grid *f, double alpha, double *w) {
    return find_cell_indexed(TM_ALPHA_AXIS(f), alpha, w);
}

static inline int g_cell(const tm_forward_grid *f, double g, double *w) { return find_cell_indexed(TM_G_AXIS(f), g, w); }

/* cell_near on the α and g axes from the cell found last time (hint; < 0: none) */
static inline int alpha_near(const tm_forward_grid *f, double alpha, int hint, double *w) {
    return cell_near(TM_ALPHA_AXIS(f), alpha, hint, w);
}

static inline int g_near(const tm_forward_grid *f, double g, int hint, double *w) {
    return cell_near(TM_G_AXIS(f), g, hint, w);
}

/* the same, keeping the cell found as the next hint */
static inline int walk_alpha(const tm_forward_grid *f, double alpha, int32_t *hint, double *w) {
    return *hint = alpha_near(f, alpha, *hint, w);
}

static inline int walk_g(const tm_forward_grid *f, double g, int32_t *hint, double *w) { return *hint = g_near(f, g, *hint, w); }

/* ln σt clamped to the grid the way ForwardGrid.sigma_cell does (NaN → lowest node, ±inf → ends). */
static inline double clamp_log_sigma(const tm_forward_grid *f, double log_sigma_t) {
    double lo = f->log_sigma_t[0], hi = f->log_sigma_t[f->ns - 1];
    return isnan(log_sigma_t) ? lo : clampd(log_sigma_t, lo, hi);
}

/* Where a bin's ln σt sits on the grid; fixed while its (α, g) are solved. */
typedef struct {
    int32_t is;
    int32_t ia, ig; /* the α and g cells of the last evaluation: walk_alpha's and walk_g's hints (-1: none yet) */
    int32_t evaluated; /* the polish stored its last evaluation (final_eval_t) for this bin */
    double ws;
    double sigma_t; /* σt clamped to the grid, as ForwardGrid.clamp_sigma_t (≈ exp of sigma_cell's ln σt) */
    double log_sigma_t; /* ln σt clamped to the grid */
    double last_step_a, last_step_g; /* |the polish's previous step| in α and g (0: none yet) */
} sigma_cell_t;

/* σt from ln σt, or directly when the caller has it (sigma_t > 0 and finite): one exp/log less per bin. */
static inline sigma_cell_t sigma_cell(const tm_forward_grid *f, double log_sigma_t, double sigma_t) {
    sigma_cell_t c;
    double ls = clamp_log_sigma(f, log_sigma_t);
    c.is = find_cell_on(f->log_sigma_t, f->inv_ds, f->ns, f->uniform_ds, ls, &c.ws);
    c.ia = c.ig = -1;
    c.evaluated = 0;
    c.last_step_a = c.last_step_g = 0.0;
    c.log_sigma_t = ls;
    c.sigma_t = ls != log_sigma_t || !(sigma_t > 0.0 && isfinite(sigma_t)) ? exp(ls) : sigma_t;
    return c;
}

/* The trilinear polynomial of forward cell (ia, is, ig): 8 terms × 3 coefficients. */
static inline const double *poly_row(const tm_forward_grid *f, int ia, int is, int ig) {
    return f->poly + (((size_t)ia * (size_t)(f->ns - 1) + (size_t)is) * (size_t)(f->ng - 1) + (size_t)ig) * 24u;
}

/* Find a bin's forward cell at (α, g) some cells away from its last one, through the axes' index (a
 * walk that far mispredicts at every cell), leave it as the bin's walk hints (coefficients() then finds
 * it at once; the cell, hence the result, is the same either way) and prefetch its polynomial,
 * 192 B, so that the evaluation does not wait for memory. */
static inline void prefetch_cell(const tm_forward_grid *f, sigma_cell_t *cell, double alpha, double g) {
    double w;
    int ia = cell->ia = alpha_cell(f, alpha, &w);
    int ig = cell->ig = g_cell(f, g, &w);
    const double *P = poly_row(f, ia, cell->is, ig);
    __builtin_prefetch(P);
    __builtin_prefetch(P + 8);
    __builtin_prefetch(P + 16);
}

typedef struct { double v[3], da[3], dg[3], ds[3]; } abc_t;

/* A bin's residual² |(I_b, I_w) − model|² and its ∂(I_b, I_w)/∂(α, σt, g) (rows I_b, I_w) at the
 * solution, for the uncertainty and the convergence flag. */
typedef struct { double residual2, J[6]; } final_eval_t;

/* A, B, C at (α, cell σ, g) and their derivatives (ForwardGrid.coefficients). */
static inline void coefficients(const tm_forward_grid *f, sigma_cell_t *cell, double alpha, double g, int with_ds,
                         abc_t *out) {
    double wa, wg, ws = cell->ws;
    int is = cell->is;
    int ia = walk_alpha(f, alpha, &cell->ia, &wa);
    int ig = walk_g(f, g, &cell->ig, &wg);
    const double *P = poly_row(f, ia, is, ig);
    for (int c = 0; c < 3; c++) {
        double p0 = P[0 * 3 + c] + P[2 * 3 + c] * ws;
        double p1 = P[1 * 3 + c] + P[4 * 3 + c] * ws;
        double p3 = P[3 * 3 + c] + P[6 * 3 + c] * ws;
        double p5 = P[5 * 3 + c] + P[7 * 3 + c] * ws;
        out->v[c] = p0 + p1 * wa + (p3 + p5 * wa) * wg;
        out->da[c] = (p1 + p5 * wg) * f->inv_da[ia];
        out->dg[c] = (p3 + p5 * wa) * f->inv_dg[ig];
        if (with_ds)
            out->ds[c] = (P[2 * 3 + c] + P[4 * 3 + c] * wa + (P[6 * 3 + c] + P[7 * 3 + c] * wa) * wg) * f->inv_ds[is];
    }
}

/* I(ρ) = A + Bρ/(1 − Cρ); grad_B = ρ/(1 − Cρ), grad_C = B·grad_B² (ForwardGrid.diffuse). */
static inline double diffuse(const double *abc, double rho, double *grad_b, double *grad_c) {
    double fr = rho / (1.0 - abc[2] * rho);
    *grad_b = fr;
    *grad_c = abc[1] * fr * fr;
    return abc[0] + abc[1] * fr;
}

static inline double directional(double grad_b, double grad_c, const double *d) {
    return d[0] + grad_b * d[1] + grad_c * d[2];
}

/* Whether a polish step δ in one parameter ends that parameter's polish (ForwardGrid.step_is_small):
 * at most step_tol; or below κ of its noise std, δ² ≤ step_var·var (step_var = (κ σ_I)², var the
 * parameter's variance per unit intensity variance, (JᵀJ)⁻¹: h/det); or shrinking fast, at most
 * TM_STEP_RATIO of the previous step δ₋, so that the next one, ≈ δ·|δ/δ₋|, is below κ of the std:
 * δ⁴ ≤ step_var·var·δ₋². The last saves the step that only confirms convergence (Newton converges
 * quadratically: its steps shrink far faster than that); the cap keeps a bin whose steps shrink
 * slowly, along a valley, polishing. All multiplied out: no division. */
static inline int step_is_small(double step, double last, double step_tol, double step_var, double h, double det) {
    double a = fabs(step);
    if (a <= step_tol) return 1;
    if (!(det > 0.0)) return 0;
    double lim = step_var * h, d2 = a * a * det;
    return d2 <= lim || (a <= TM_STEP_RATIO * last && d2 * a * a <= lim * last * last);
}

/* A converged bin's final evaluation, taken from its last Newton step when that step stayed in the
 * cell (the map's derivatives jump between cells, by up to ~50 % in an ill-conditioned bin's std):
 * the Jacobian there, one step below κ of the noise std away, and the residuals carried along the
 * step actually taken (after the clamps). Otherwise the finish evaluates at the solution. */
static inline void keep_final_eval(const tm_forward_grid *f, sigma_cell_t *cell, double alpha, double g,
                                   double residual2, const double J[6], final_eval_t *last) {
    if (!in_cell(f->alpha, f->na, cell->ia, alpha) || !in_cell(f->g, f->ng, cell->ig, g)) return;
    last->residual2 = residual2;
    for (int k = 0; k < 6; k++) last->J[k] = J[k];
    cell->evaluated = 1;
}

/* The damped Gauss-Newton (Levenberg-Marquardt) step on the 2×2 normal equations of (I_b, I_w) in
 * (α, g) for residuals (rb, rw), capped to a trust region (ForwardGrid._lm_step); h11, h22 and det
 * also give the step's variance (step_is_small). newton_step4 does the same lane by lane. */
typedef struct { double step_a, step_g, h11, h22, det, b1, b2; } lm_step_t;

static inline lm_step_t lm_step(double j11, double j12, double j21, double j22, double rb, double rw) {
    lm_step_t st;
    double h11 = j11 * j11 + j21 * j21, h22 = j12 * j12 + j22 * j22, h12 = j11 * j12 + j21 * j22;
    double mu = 1e-9 + 1e-6 * (h11 + h22); /* stays finite where ∂I/∂g → 0 (α → 0) */
    h11 += mu;
    h22 += mu;
    double b1 = j11 * rb + j21 * rw, b2 = j12 * rb + j22 * rw;
    double det = h11 * h22 - h12 * h12;
    /* trust region: a piecewise-trilinear map is only locally linear */
    st.step_a = clampd(-(h22 * b1 - h12 * b2) / det, -0.25, 0.25);
    st.step_g = clampd(-(h11 * b2 - h12 * b1) / det, -0.5, 0.5);
    st.h11 = h11;
    st.h22 = h22;
    st.det = det;
    st.b1 = b1;
    st.b2 = b2;
    return st;
}

/* The polish's step projected onto the map's box (ForwardGrid.hold_at_edges, operation for operation;
 * newton_step4 lane by lane, table_fit.c in its own precision): a parameter at an edge whose step
 * points out of the box is held (step 0) and the other takes its own Gauss-Newton step, −b/h capped as
 * in lm_step — the 2×2 step assumed the held one moves, so clamped it only crawls along the edge. The
 * free one's variance per unit intensity variance is then 1/h: h' = 1, det' = h. Both held: no step. */
static inline void hold_at_edges(const tm_forward_grid *f, double alpha, double g, lm_step_t *st) {
    int hold_a = (alpha <= f->alpha_lo && st->step_a < 0.0) || (alpha >= f->alpha_hi && st->step_a > 0.0);
    int hold_g = (g <= f->g_lo && st->step_g < 0.0) || (g >= f->g_hi && st->step_g > 0.0);
    if (hold_a && hold_g) {
        st->step_a = st->step_g = 0.0;
    } else if (hold_g) {
        st->step_a = clampd(-st->b1 / st->h11, -0.25, 0.25);
        st->step_g = 0.0;
        st->det = st->h11;
        st->h22 = 1.0;
    } else if (hold_a) {
        st->step_g = clampd(-st->b2 / st->h22, -0.5, 0.5);
        st->step_a = 0.0;
        st->det = st->h22;
        st->h11 = 1.0;
    }
}

/* ∂I_c/∂σt at the clamped σt (ForwardGrid.collimated_derivative ∘ clamp_sigma_t). */
static inline double collimated_derivative(const tm_forward_grid *f, double sigma_t) {
    double x = exp(-sigma_t * f->thickness_mm), bx2 = f->stack_b * x * x;
    return -f->thickness_mm * f->stack_a * x * (1.0 + bx2) / ((1.0 - bx2) * (1.0 - bx2));
}

static inline double lerp(double a, double b, double w) { return a + (b - a) * w; }

/* Two doubles as one value (GCC/clang vector extension; a pair of scalars where the target has no
 * such registers): element for element the same IEEE operations as the scalar code, so the same
 * results, for the tables that store two quantities side by side. */
typedef double v2d __attribute__((vector_size(16)));

static inline v2d load2(const double *p) {
    v2d v;
    __builtin_memcpy(&v, p, sizeof v); /* unaligned */
    return v;
}

static inline v2d splat2(double x) { return (v2d){x, x}; }


static inline int grid_ok(const tm_forward_grid *f, const tm_inverse_table *table) {
    if (!f || f->na < 2 || f->ns < 2 || f->ng < 2) return 0;
    return !table || (table->ns >= 2 && table->nx >= 2 && table->ny >= 2);
}


/* TM_FLAG_STD_APPROXIMATE: whether a bin's first-order stds hold over ±sigmas σ (ForwardGrid.first_order_holds,
 * operation for operation). From the polish's solution (α, g) and its Jacobian J2 = ∂(I_b, I_w)/∂(α, g),
 * the measured (I_b, I_w) are moved by ±sigmas·σ in I_b, then in I_w (σ: the stds propagated); each
 * move's linear prediction (α, g) + J2⁻¹·δI, clamped to the map's box, is corrected by one Newton step
 * there: where a re-fit from the moved intensities lands, up to the square of its distance from the
 * prediction. The bin holds where correction and clamp stay within tol·sigmas of each std for all
 * four moves. A bin's state between the finish (which picks the bins) and the check: */
typedef struct { double alpha, g, move_b, move_w, j11, j12, j21, j22, limit_a, limit_g; } check_t;

/* A bin's finish between its table reads and its arithmetic: its Jacobian at the solution and
 * residual², the in-scattering correction of σt, the map's error variances there, and (α, g) as
 * solved, before the in-scattering move (the check's) */
typedef struct { double Ji[9], residual2, ds_in, model_b, model_w, solved_alpha, solved_g; } finish_t;


/* The rows of a fit's output block (enum tm_row) */
typedef struct {
    double *alpha, *sigma_t, *g, *alpha_std, *sigma_t_std, *g_std, *sigma_t_beer;
    int64_t *flags;
    double *cond_alpha_std, *cond_g_std;
} tm_fit_outputs;

/* The rows of a block whose rows are `stride` values apart */
static inline tm_fit_outputs outputs_in(double *block, size_t stride) {
    tm_fit_outputs o = {block + TM_ROW_ALPHA * stride,
                        block + TM_ROW_SIGMA_T * stride,
                        block + TM_ROW_G * stride,
                        block + TM_ROW_ALPHA_STD * stride,
                        block + TM_ROW_SIGMA_T_STD * stride,
                        block + TM_ROW_G_STD * stride,
                        block + TM_ROW_SIGMA_T_BEER * stride,
                        (int64_t *)(block + TM_ROW_FLAGS * stride),
                        block + TM_ROW_CONDITIONING_ALPHA_STD * stride,
                        block + TM_ROW_CONDITIONING_G_STD * stride};
    return o;
}

/* A fit's per-bin working state between its two halves (tm_fit_prepare, tm_fit_solve): the
 * sanitized inputs, the polish's step tolerance, the σt cell, the final evaluations and the polish's
 * index list. One caller-owned block of tm_fit_scratch_size(n) bytes, carved here; tm_solve_alpha_g
 * uses the same block for its cells, evaluations and indices. */
typedef struct {
    double *ib, *iw, *rb, *rw, *step_var;
    double *var_b, *var_w, *sd_c; /* the intensities' noise: given per bin, or the noise model's */
    double *cond_var_b, *cond_var_w, *cond_sd_c; /* the same, at least the noise model's (UNDERDETERMINED) */
    sigma_cell_t *cells;
    final_eval_t *evals;
    check_t *checks;
    finish_t *finish;
    uint32_t *active;
} fit_scratch_t;

static inline fit_scratch_t carve_scratch(void *mem, size_t n) {
    fit_scratch_t sc;
    /* doubles first, then the cells and the final evaluations (8-byte members), then the indices:
     * all aligned */
    double *d = mem;
    sc.ib = d;
    sc.iw = d + n;
    sc.rb = d + 2 * n;
    sc.rw = d + 3 * n;
    sc.step_var = d + 4 * n;
    sc.var_b = d + 5 * n;
    sc.var_w = d + 6 * n;
    sc.sd_c = d + 7 * n;
    sc.cond_var_b = d + 8 * n;
    sc.cond_var_w = d + 9 * n;
    sc.cond_sd_c = d + 10 * n;
    sc.cells = (sigma_cell_t *)(d + 11 * n);
    sc.evals = (final_eval_t *)(sc.cells + n);
    sc.checks = (check_t *)(sc.evals + n);
    sc.finish = (finish_t *)(sc.checks + n);
    sc.active = (uint32_t *)(sc.finish + n);
    return sc;
}

/* What the finish's arithmetic reads, for finish_bin (pipeline.c) and tmi_finish4 (simd.c): the options,
 * the bins' finish_t, their intensity noise (fit_scratch_t's) and the outputs, which it completes. */
typedef struct {
    const tm_forward_grid *f;
    const tm_fit_options *o;
    const finish_t *fin;
    const double *var_b, *var_w, *sd_c, *cond_var_b, *cond_var_w, *cond_sd_c;
    tm_fit_outputs out;
    double mc2;
    int g_lo_is_edge, g_hi_is_edge; /* the map's g range ends inside (-1, 1) */
} finish_ctx_t;

/* lookups.c */
void tmi_initial_guesses(const tm_inverse_table *t, size_t n, const sigma_cell_t *cells, const double *I_b,
                         const double *I_w, double *alpha, double *g);
void tmi_initial_guess(const tm_inverse_table *t, double log_sigma_t, double I_b, double I_w, double *alpha,
                       double *g);
double tmi_inscatter_log1p(const tm_forward_grid *f, int ia, double wa, double sigma_t, int ig, double wg);
void tmi_model_variance(const tm_forward_grid *f, const sigma_cell_t *c, double alpha, double g, double *var_b,
                        double *var_w);
void tmi_prefetch_finish(const tm_forward_grid *f, const sigma_cell_t *c, double sigma_t);
void tmi_prefetch_cells(const tm_forward_grid *f, size_t n, sigma_cell_t *cells, const double *alpha,
                        const double *g);

/* newton.c */
size_t tmi_polish(const tm_forward_grid *f, size_t n, sigma_cell_t *cells, const double *I_b, const double *I_w,
                  const double *rho_b, const double *rho_w, int iterations, double step_tol, const double *step_var,
                  double *alpha, double *g, uint32_t *active, final_eval_t *evals);
double tmi_final_residual2_and_jacobian(const tm_forward_grid *f, sigma_cell_t *c, const final_eval_t *e,
                                        double alpha, double g, double I_b, double I_w, double rho_b, double rho_w,
                                        double *Ji);
int tmi_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b,
                      const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w,
                      int iterations, double step_tol, const double *step_var, double *alpha, double *g,
                      double *residual, double *J, void *scratch);

/* pipeline.c: tm_fit_prepare and tm_fit_solve with their output rows `stride` apart (a part of a wider
 * block's bins) */
void tmi_fit_prepare(const tm_forward_grid *f, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w,
                     const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, void *scratch,
                     double *outputs, size_t stride, double log_lo, double log_hi, float *features);
long long tmi_fit_solve(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n,
                        const double *alpha0, const double *g0, void *scratch, double *outputs, size_t stride);

/* simd.c */
#ifdef TM_SIMD
int tmi_use_simd(void);
void tmi_newton_step4(const tm_forward_grid *f, sigma_cell_t *cells, const uint32_t *idx, const double *I_b,
                      const double *I_w, const double *rho_b, const double *rho_w, double step_tol,
                      const double *step_var, double *alpha, double *g, final_eval_t *evals, int *done);
void tmi_check_step4(const tm_forward_grid *f, sigma_cell_t *cells, const uint32_t *idx, const double *a1,
                     const double *g1, const double *tb, const double *tw, const double *rho_b, const double *rho_w,
                     double *a2, double *g2);
void tmi_combine2_4(size_t n, size_t i, const double *fits, double underdetermined_alpha_std,
                    double underdetermined_g_std, double disagree_sigmas, double *outputs);
int tmi_finish4(const finish_ctx_t *c, size_t i);
#endif

#endif
