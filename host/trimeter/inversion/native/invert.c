/* The inversion hot path in C: a whole single-thickness fit (tm_fit: input flags, σt from I_c, the
 * map table's initial guess or a given one, the damped Gauss-Newton polish of (α, g) at that σt on
 * the trilinear forward map, stopping each bin once converged, the Jacobian at the solution (from
 * the converging step's evaluation), the in-scattering correction of σt (where the map has a table),
 * the first-order uncertainty and the validity flags, STD_APPROXIMATE's check included; or its two
 * halves tm_fit_prepare / tm_fit_solve with an MLP's guess in between), and its parts for the
 * numpy-side callers (tm_solve_alpha_g, tm_propagate). One pass per bin, everything in registers;
 * the polish takes four bins per step with AVX2 where the CPU has it (newton_step4).
 *
 * Why C: the numpy kernel (trimeter.inversion.kernel / lut / api) spends its time in ~100 array
 * operations per Newton step, each a few µs of interpreter and allocation overhead at ~1000 bins;
 * the arithmetic itself is ~200 flops per bin and step. This file is the same algorithm, operation
 * for operation, so the numpy code stays the reference: tests/inversion/test_native_kernel.py
 * checks that both agree to ~1e-9, flags bit for bit. Loaded with ctypes (trimeter.inversion.native);
 * no Python API, no dependency beyond libm. Build: `make native` (cc -O2 -shared -fPIC).
 *
 * Data layouts are those of the numpy kernel (C order, float64):
 *   poly  [(na-1)(ns-1)(ng-1)][8 terms][3 coefs]  trilinear polynomial per forward cell, terms
 *         1, wa, ws, wg, wa·ws, wa·wg, ws·wg, wa·ws·wg; coefs A, B, C
 *   cells [ns][ny-1][nx-1][4 terms][2]            bilinear inverse cell, terms 1, fu, fv, fu·fv; (α, g)
 *   frame [ns][6]                                 (x0, y0, m00·(nx-1), m01·(nx-1), m10·(ny-1), m11·(ny-1))
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

#define TM_ABI_VERSION 15

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
     * this grid's α and g nodes and in_nt evenly spaced optical depths τ = σt·ℓ from 0 to in_tau_max. */
    int32_t in_nt;
    const double *inscatter_L; /* [na][in_nt][ng] */
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

int tm_abi_version(void) { return TM_ABI_VERSION; }

static inline double clampd(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* numpy: i = clip(searchsorted(axis, x, side="right") - 1, 0, n-2); w = clip((x - axis[i]) inv_d[i], 0, 1) */
static inline int find_cell(const double *axis, const double *inv_d, int n, double x, double *w) {
    /* Branchless binary search for the last node <= x (a conditional move per halving: the
     * branchy version mispredicts on every other step at random bins, ~2× slower here). */
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

/* find_cell starting from the cell found last time (*hint; < 0: none yet): Newton iterates move a
 * cell or two at most, so a short walk replaces the ~6 dependent loads of the binary search. */
static inline int walk_cell(const double *axis, const double *inv_d, int n, double x, int32_t *hint, double *w) {
    int i = (*hint < 0 || isnan(x)) ? find_cell(axis, inv_d, n, x, w) : walk_from(axis, inv_d, n, x, *hint, w);
    *hint = i;
    return i;
}

/* ln σt clamped to the grid the way ForwardGrid.sigma_cell does (NaN → lowest node, ±inf → ends). */
static inline double clamp_log_sigma(const tm_forward_grid *f, double log_sigma_t) {
    double lo = f->log_sigma_t[0], hi = f->log_sigma_t[f->ns - 1];
    return isnan(log_sigma_t) ? lo : clampd(log_sigma_t, lo, hi);
}

/* Where a bin's ln σt sits on the grid; fixed while its (α, g) are solved. */
typedef struct {
    int32_t is;
    int32_t ia, ig; /* the α and g cells of the last evaluation: walk_cell's hints (-1: none yet) */
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

typedef struct { double v[3], da[3], dg[3], ds[3]; } abc_t;

/* A bin's residual² |(I_b, I_w) − model|² and its ∂(I_b, I_w)/∂(α, σt, g) (rows I_b, I_w) at the
 * solution, for the uncertainty and the convergence flag. */
typedef struct { double residual2, J[6]; } final_eval_t;

/* A, B, C at (α, cell σ, g) and their derivatives (ForwardGrid.coefficients). */
static void coefficients(const tm_forward_grid *f, sigma_cell_t *cell, double alpha, double g, int with_ds,
                         abc_t *out) {
    double wa, wg, ws = cell->ws;
    int is = cell->is;
    int ia = walk_cell(f->alpha, f->inv_da, f->na, alpha, &cell->ia, &wa);
    int ig = walk_cell(f->g, f->inv_dg, f->ng, g, &cell->ig, &wg);
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

/* The table's guess at ln σt (already clamped to the forward grid, whose range is the table's):
 * bilinear in the two slices bracketing it, blended linearly in ln σt (TableInverter.initial_guess). */
static void initial_guess(const tm_inverse_table *t, double log_sigma_t, double I_b, double I_w,
                          double *alpha, double *g) {
    double ws;
    int is = find_cell_on(t->log_sigma_t, t->inv_ds, t->ns, t->uniform_ds, log_sigma_t, &ws);
    /* a NaN intensity counts as 0 here (it would index outside the table); the polish then returns NaN */
    double x = sqrt(I_b > 0.0 ? fmin(I_b, 1.0) : 0.0), y = sqrt(I_w > 0.0 ? fmin(I_w, 1.0) : 0.0);
    double out_a = 0.0, out_g = 0.0;
    for (int dk = 0; dk < 2; dk++) {
        int k = is + dk;
        double wk = dk ? ws : 1.0 - ws;
        const double *fr = t->frame + (size_t)k * 6u;
        double dx = x - fr[0], dy = y - fr[1];
        double u = clampd(fr[2] * dx + fr[3] * dy, 0.0, t->nx - 1.0);
        double v = clampd(fr[4] * dx + fr[5] * dy, 0.0, t->ny - 1.0);
        int iu = (int)u, iv = (int)v;
        if (iu > t->nx - 2) iu = t->nx - 2;
        if (iv > t->ny - 2) iv = t->ny - 2;
        double fu = u - iu, fv = v - iv;
        const double *q = t->cells + (((size_t)k * (size_t)(t->ny - 1) + (size_t)iv) * (size_t)(t->nx - 1) + (size_t)iu) * 8u;
        out_a += (q[0] + q[2] * fu + (q[4] + q[6] * fu) * fv) * wk;
        out_g += (q[1] + q[3] * fu + (q[5] + q[7] * fu) * fv) * wk;
    }
    *alpha = out_a;
    *g = out_g;
}

/* Whether a polish step δ in one parameter ends that parameter's polish (ForwardGrid.step_is_small):
 * at most step_tol; or below κ of its noise std, δ² ≤ step_var·var (step_var = (κ σ_I)², var the
 * parameter's variance per unit intensity variance, (JᵀJ)⁻¹: h/det); or shrinking fast, at most
 * STEP_RATIO of the previous step δ₋, so that the next one, ≈ δ·|δ/δ₋|, is below κ of the std:
 * δ⁴ ≤ step_var·var·δ₋². The last saves the step that only confirms convergence (Newton converges
 * quadratically: its steps shrink far faster than 4× per step). Measured on the device held-out sets
 * (table guess, noise-free): 3.28 → 2.96 steps per bin on l0.4, 3.56 → 3.23 on l0.8, the largest
 * distance from the 16-step solution unchanged (0.07 / 0.10 of the std; with 0.5 % noise 0.21 /
 * 0.43); without the ratio cap (any shrinking step) 2.91 / 3.14, but one noisy l0.8 bin then
 * stopped 1.4 std away. Bins whose steps shrink slowly, along a valley, are not stopped by it. All
 * multiplied out: no division. */
#define STEP_RATIO 0.25
double tm_step_ratio(void) { return STEP_RATIO; } /* Python refuses the library unless it is native.STEP_RATIO */
static inline int step_is_small(double step, double last, double step_tol, double step_var, double h, double det) {
    double a = fabs(step);
    if (a <= step_tol) return 1;
    if (!(det > 0.0)) return 0;
    double lim = step_var * h, d2 = a * a * det;
    return d2 <= lim || (a <= STEP_RATIO * last && d2 * a * a <= lim * last * last);
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
typedef struct { double step_a, step_g, h11, h22, det; } lm_step_t;

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
    return st;
}

/* One Levenberg-Marquardt step on the 2×2 normal equations (ForwardGrid._newton_step). Returns 1
 * when the step just taken ends the bin's polish in both α and g (step_is_small). */
static int newton_step(const tm_forward_grid *f, sigma_cell_t *cell, double I_b, double I_w, double rho_b,
                       double rho_w, double step_tol, double step_var, double *alpha, double *g,
                       final_eval_t *last) {
    abc_t c;
    coefficients(f, cell, *alpha, *g, 1, &c);
    double fb, hb, fw, hw;
    double rb = diffuse(c.v, rho_b, &fb, &hb) - I_b;
    double rw = diffuse(c.v, rho_w, &fw, &hw) - I_w;
    double j11 = directional(fb, hb, c.da), j12 = directional(fb, hb, c.dg);
    double j21 = directional(fw, hw, c.da), j22 = directional(fw, hw, c.dg);
    lm_step_t st = lm_step(j11, j12, j21, j22, rb, rw);
    double step_a = st.step_a, step_g = st.step_g, h11 = st.h11, h22 = st.h22, det = st.det;
    double alpha0 = *alpha, g0 = *g;
    *alpha = clampd(*alpha + step_a, f->alpha_lo, f->alpha_hi);
    *g = clampd(*g + step_g, f->g_lo, f->g_hi);
    /* var(α) = σ²·h22/det, var(g) = σ²·h11/det */
    int small_a = step_is_small(step_a, cell->last_step_a, step_tol, step_var, h22, det);
    int small_g = step_is_small(step_g, cell->last_step_g, step_tol, step_var, h11, det);
    cell->last_step_a = fabs(step_a);
    cell->last_step_g = fabs(step_g);
    int done = small_a && small_g;
    if (done) {
        double da = *alpha - alpha0, dg = *g - g0, s = cell->sigma_t;
        double ra = rb + j11 * da + j12 * dg, rwn = rw + j21 * da + j22 * dg;
        const double J[6] = {j11, directional(fb, hb, c.ds) / s, j12, j21, directional(fw, hw, c.ds) / s, j22};
        keep_final_eval(f, cell, *alpha, *g, ra * ra + rwn * rwn, J, last);
    }
    return done;
}


/* ------------------------------------------------------------------- four bins per instruction
 * newton_step for four bins at once with AVX2 (x86-64, chosen at run time; elsewhere, or with
 * tm_set_simd(0), the scalar loop runs). The same operations in the same order, lane by lane, and no
 * FMA (-std=c11 does not contract, and the target does not enable it): bit for bit the scalar
 * result, which tests/inversion/test_native_kernel.py checks. Per step and bin the scalar code
 * spends ~250 instructions, ~200 of them arithmetic that does not depend on the cell; here that
 * arithmetic runs 4 lanes wide. Each lane still walks to its own cell (scalar: short loops), and its
 * 24 polynomial coefficients are loaded as 6 rows of 4 and transposed. */
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define TM_SIMD 1
typedef __m256d v4;

__attribute__((target("avx2"))) static inline v4 clamp4(v4 x, v4 lo, v4 hi) {
    /* clampd: max_pd/min_pd return their second operand when either is NaN, as clampd keeps a NaN */
    return _mm256_min_pd(hi, _mm256_max_pd(lo, x));
}

__attribute__((target("avx2"))) static inline v4 set4(double a, double b, double c, double d) {
    return _mm256_set_pd(d, c, b, a);
}

/* rows[k] = (P0[k], P1[k], P2[k], P3[k]) for k = 4r .. 4r+3: one 4 × 4 transpose */
__attribute__((target("avx2"))) static inline void transpose_rows(const double *P0, const double *P1, const double *P2,
                                                                  const double *P3, int r, v4 *rows) {
    v4 a = _mm256_loadu_pd(P0 + 4 * r), b = _mm256_loadu_pd(P1 + 4 * r);
    v4 c = _mm256_loadu_pd(P2 + 4 * r), d = _mm256_loadu_pd(P3 + 4 * r);
    v4 ab_lo = _mm256_unpacklo_pd(a, b), ab_hi = _mm256_unpackhi_pd(a, b);
    v4 cd_lo = _mm256_unpacklo_pd(c, d), cd_hi = _mm256_unpackhi_pd(c, d);
    rows[4 * r + 0] = _mm256_permute2f128_pd(ab_lo, cd_lo, 0x20);
    rows[4 * r + 1] = _mm256_permute2f128_pd(ab_hi, cd_hi, 0x20);
    rows[4 * r + 2] = _mm256_permute2f128_pd(ab_lo, cd_lo, 0x31);
    rows[4 * r + 3] = _mm256_permute2f128_pd(ab_hi, cd_hi, 0x31);
}

/* step_is_small, four lanes: an all-ones lane where the step ends that parameter's polish */
__attribute__((target("avx2"))) static inline v4 small4(v4 step, v4 last, v4 step_tol, v4 step_var, v4 h, v4 det) {
    const v4 sign = _mm256_set1_pd(-0.0);
    v4 a = _mm256_andnot_pd(sign, step);
    v4 d2 = _mm256_mul_pd(_mm256_mul_pd(a, a), det);
    v4 lim = _mm256_mul_pd(step_var, h);
    v4 below_std = _mm256_cmp_pd(d2, lim, _CMP_LE_OQ);
    v4 shrinking = _mm256_and_pd(
        _mm256_cmp_pd(a, _mm256_mul_pd(_mm256_set1_pd(STEP_RATIO), last), _CMP_LE_OQ),
        _mm256_cmp_pd(_mm256_mul_pd(_mm256_mul_pd(d2, a), a), _mm256_mul_pd(_mm256_mul_pd(lim, last), last),
                      _CMP_LE_OQ));
    v4 positive = _mm256_cmp_pd(det, _mm256_setzero_pd(), _CMP_GT_OQ);
    return _mm256_or_pd(_mm256_cmp_pd(a, step_tol, _CMP_LE_OQ),
                        _mm256_and_pd(positive, _mm256_or_pd(below_std, shrinking)));
}

/* directional(grad_b, grad_c, d) = d0 + grad_b·d1 + grad_c·d2, four lanes */
__attribute__((target("avx2"))) static inline v4 directional4(v4 gb, v4 gc, v4 d0, v4 d1, v4 d2) {
    return _mm256_add_pd(_mm256_add_pd(d0, _mm256_mul_pd(gb, d1)), _mm256_mul_pd(gc, d2));
}

/* newton_step for the bins idx[0..3]; done[l] as newton_step returns it */
__attribute__((target("avx2"))) static void newton_step4(const tm_forward_grid *f, sigma_cell_t *cells,
                                                         const uint32_t *idx, const double *I_b, const double *I_w,
                                                         const double *rho_b, const double *rho_w, double step_tol,
                                                         const double *step_var, double *alpha, double *g,
                                                         final_eval_t *evals, int *done) {
    const double *P[4];
    double wa[4], wg[4], ws[4], ida[4], idg[4], ids[4], a0[4], g0[4];
    for (int l = 0; l < 4; l++) {
        sigma_cell_t *c = &cells[idx[l]];
        a0[l] = alpha[idx[l]];
        g0[l] = g[idx[l]];
        int ia = walk_cell(f->alpha, f->inv_da, f->na, a0[l], &c->ia, &wa[l]);
        int ig = walk_cell(f->g, f->inv_dg, f->ng, g0[l], &c->ig, &wg[l]);
        P[l] = poly_row(f, ia, c->is, ig);
        ws[l] = c->ws;
        ida[l] = f->inv_da[ia];
        idg[l] = f->inv_dg[ig];
        ids[l] = f->inv_ds[c->is];
    }
    v4 T[24];
    for (int r = 0; r < 6; r++) transpose_rows(P[0], P[1], P[2], P[3], r, T);
    v4 Wa = _mm256_loadu_pd(wa), Wg = _mm256_loadu_pd(wg), Ws = _mm256_loadu_pd(ws);
    v4 Ida = _mm256_loadu_pd(ida), Idg = _mm256_loadu_pd(idg), Ids = _mm256_loadu_pd(ids);
    v4 V[3], DA[3], DG[3], DS[3];
    for (int c = 0; c < 3; c++) { /* coefficients(), term by term */
        v4 p0 = _mm256_add_pd(T[0 * 3 + c], _mm256_mul_pd(T[2 * 3 + c], Ws));
        v4 p1 = _mm256_add_pd(T[1 * 3 + c], _mm256_mul_pd(T[4 * 3 + c], Ws));
        v4 p3 = _mm256_add_pd(T[3 * 3 + c], _mm256_mul_pd(T[6 * 3 + c], Ws));
        v4 p5 = _mm256_add_pd(T[5 * 3 + c], _mm256_mul_pd(T[7 * 3 + c], Ws));
        V[c] = _mm256_add_pd(_mm256_add_pd(p0, _mm256_mul_pd(p1, Wa)),
                             _mm256_mul_pd(_mm256_add_pd(p3, _mm256_mul_pd(p5, Wa)), Wg));
        DA[c] = _mm256_mul_pd(_mm256_add_pd(p1, _mm256_mul_pd(p5, Wg)), Ida);
        DG[c] = _mm256_mul_pd(_mm256_add_pd(p3, _mm256_mul_pd(p5, Wa)), Idg);
        DS[c] = _mm256_mul_pd(_mm256_add_pd(_mm256_add_pd(T[2 * 3 + c], _mm256_mul_pd(T[4 * 3 + c], Wa)),
                                            _mm256_mul_pd(_mm256_add_pd(T[6 * 3 + c], _mm256_mul_pd(T[7 * 3 + c], Wa)),
                                                          Wg)),
                              Ids);
    }
    const v4 one = _mm256_set1_pd(1.0);
    v4 Rb = set4(rho_b[idx[0]], rho_b[idx[1]], rho_b[idx[2]], rho_b[idx[3]]);
    v4 Rw = set4(rho_w[idx[0]], rho_w[idx[1]], rho_w[idx[2]], rho_w[idx[3]]);
    /* diffuse(): I = A + B·fr, grad_B = fr = ρ/(1 − Cρ), grad_C = B·fr² */
    v4 fb = _mm256_div_pd(Rb, _mm256_sub_pd(one, _mm256_mul_pd(V[2], Rb)));
    v4 fw = _mm256_div_pd(Rw, _mm256_sub_pd(one, _mm256_mul_pd(V[2], Rw)));
    v4 hb = _mm256_mul_pd(_mm256_mul_pd(V[1], fb), fb), hw = _mm256_mul_pd(_mm256_mul_pd(V[1], fw), fw);
    v4 rb = _mm256_sub_pd(_mm256_add_pd(V[0], _mm256_mul_pd(V[1], fb)),
                          set4(I_b[idx[0]], I_b[idx[1]], I_b[idx[2]], I_b[idx[3]]));
    v4 rw = _mm256_sub_pd(_mm256_add_pd(V[0], _mm256_mul_pd(V[1], fw)),
                          set4(I_w[idx[0]], I_w[idx[1]], I_w[idx[2]], I_w[idx[3]]));
    v4 j11 = directional4(fb, hb, DA[0], DA[1], DA[2]), j12 = directional4(fb, hb, DG[0], DG[1], DG[2]);
    v4 j21 = directional4(fw, hw, DA[0], DA[1], DA[2]), j22 = directional4(fw, hw, DG[0], DG[1], DG[2]);
    v4 h11 = _mm256_add_pd(_mm256_mul_pd(j11, j11), _mm256_mul_pd(j21, j21));
    v4 h22 = _mm256_add_pd(_mm256_mul_pd(j12, j12), _mm256_mul_pd(j22, j22));
    v4 h12 = _mm256_add_pd(_mm256_mul_pd(j11, j12), _mm256_mul_pd(j21, j22));
    v4 mu = _mm256_add_pd(_mm256_set1_pd(1e-9), _mm256_mul_pd(_mm256_set1_pd(1e-6), _mm256_add_pd(h11, h22)));
    h11 = _mm256_add_pd(h11, mu);
    h22 = _mm256_add_pd(h22, mu);
    v4 b1 = _mm256_add_pd(_mm256_mul_pd(j11, rb), _mm256_mul_pd(j21, rw));
    v4 b2 = _mm256_add_pd(_mm256_mul_pd(j12, rb), _mm256_mul_pd(j22, rw));
    v4 det = _mm256_sub_pd(_mm256_mul_pd(h11, h22), _mm256_mul_pd(h12, h12));
    const v4 sign = _mm256_set1_pd(-0.0);
    v4 step_a = _mm256_div_pd(_mm256_xor_pd(sign, _mm256_sub_pd(_mm256_mul_pd(h22, b1), _mm256_mul_pd(h12, b2))), det);
    v4 step_g = _mm256_div_pd(_mm256_xor_pd(sign, _mm256_sub_pd(_mm256_mul_pd(h11, b2), _mm256_mul_pd(h12, b1))), det);
    step_a = clamp4(step_a, _mm256_set1_pd(-0.25), _mm256_set1_pd(0.25));
    step_g = clamp4(step_g, _mm256_set1_pd(-0.5), _mm256_set1_pd(0.5));
    v4 A0 = _mm256_loadu_pd(a0), G0 = _mm256_loadu_pd(g0);
    v4 A1 = clamp4(_mm256_add_pd(A0, step_a), _mm256_set1_pd(f->alpha_lo), _mm256_set1_pd(f->alpha_hi));
    v4 G1 = clamp4(_mm256_add_pd(G0, step_g), _mm256_set1_pd(f->g_lo), _mm256_set1_pd(f->g_hi));
    double last_a[4], last_g[4], var[4];
    for (int l = 0; l < 4; l++) {
        last_a[l] = cells[idx[l]].last_step_a;
        last_g[l] = cells[idx[l]].last_step_g;
        var[l] = step_var ? step_var[idx[l]] : 0.0;
    }
    v4 Tol = _mm256_set1_pd(step_tol), Var = _mm256_loadu_pd(var);
    v4 small = _mm256_and_pd(small4(step_a, _mm256_loadu_pd(last_a), Tol, Var, h22, det),
                             small4(step_g, _mm256_loadu_pd(last_g), Tol, Var, h11, det));
    /* the final evaluation's pieces (used for the lanes that end here in their cell) */
    v4 dA = _mm256_sub_pd(A1, A0), dG = _mm256_sub_pd(G1, G0);
    v4 ra = _mm256_add_pd(_mm256_add_pd(rb, _mm256_mul_pd(j11, dA)), _mm256_mul_pd(j12, dG));
    v4 rwn = _mm256_add_pd(_mm256_add_pd(rw, _mm256_mul_pd(j21, dA)), _mm256_mul_pd(j22, dG));
    v4 res2 = _mm256_add_pd(_mm256_mul_pd(ra, ra), _mm256_mul_pd(rwn, rwn));
    v4 S = set4(cells[idx[0]].sigma_t, cells[idx[1]].sigma_t, cells[idx[2]].sigma_t, cells[idx[3]].sigma_t);
    v4 js_b = _mm256_div_pd(directional4(fb, hb, DS[0], DS[1], DS[2]), S);
    v4 js_w = _mm256_div_pd(directional4(fw, hw, DS[0], DS[1], DS[2]), S);
    double out_a[4], out_g[4], sa[4], sg[4], r2[4], J[6][4];
    _mm256_storeu_pd(out_a, A1);
    _mm256_storeu_pd(out_g, G1);
    _mm256_storeu_pd(sa, _mm256_andnot_pd(sign, step_a));
    _mm256_storeu_pd(sg, _mm256_andnot_pd(sign, step_g));
    _mm256_storeu_pd(r2, res2);
    _mm256_storeu_pd(J[0], j11);
    _mm256_storeu_pd(J[1], js_b);
    _mm256_storeu_pd(J[2], j12);
    _mm256_storeu_pd(J[3], j21);
    _mm256_storeu_pd(J[4], js_w);
    _mm256_storeu_pd(J[5], j22);
    int mask = _mm256_movemask_pd(small);
    for (int l = 0; l < 4; l++) {
        uint32_t i = idx[l];
        sigma_cell_t *c = &cells[i];
        alpha[i] = out_a[l];
        g[i] = out_g[l];
        c->last_step_a = sa[l];
        c->last_step_g = sg[l];
        done[l] = (mask >> l) & 1;
        if (done[l]) {
            const double Jl[6] = {J[0][l], J[1][l], J[2][l], J[3][l], J[4][l], J[5][l]};
            keep_final_eval(f, c, out_a[l], out_g[l], r2[l], Jl, &evals[i]);
        }
    }
}

static int simd_enabled = -1; /* -1: not decided yet */

static int use_simd(void) {
    if (simd_enabled < 0) {
        __builtin_cpu_init();
        simd_enabled = __builtin_cpu_supports("avx2") ? 1 : 0;
    }
    return simd_enabled;
}
#endif

/* 0: the scalar loop only (tests compare both), 1: AVX2 where the CPU has it. Returns whether the
 * four-lane step is in use now. */
int tm_set_simd(int enabled) {
#ifdef TM_SIMD
    simd_enabled = -1;
    if (enabled) return use_simd();
    simd_enabled = 0;
#else
    (void)enabled;
#endif
    return 0;
}

/* Every bin's first forward cell, found (kept as walk_cell's hints) and prefetched in one pass before
 * the polish: a bin's cell is a random 192 B in a ~22 MB grid, so in a cold cache each first visit
 * is a memory round trip that the polish would otherwise wait on bin by bin. Measured (l0.8 held-out,
 * 1024 bins, tm_fit): 0.25 → 0.235 ms warm, 0.43 → 0.39 ms right after a paper fit. Prefetching the
 * table's guess cells the same way gained nothing, nor did prefetching each bin's next cell after
 * every Newton step (4 % slower warm, no faster cold). */
static void prefetch_cells(const tm_forward_grid *f, size_t n, sigma_cell_t *cells, const double *alpha,
                           const double *g) {
    for (size_t i = 0; i < n; i++) {
        double w;
        int ia = find_cell(f->alpha, f->inv_da, f->na, alpha[i], &w);
        int ig = find_cell(f->g, f->inv_dg, f->ng, g[i], &w);
        cells[i].ia = ia;
        cells[i].ig = ig;
        const double *P = poly_row(f, ia, cells[i].is, ig);
        __builtin_prefetch(P);
        __builtin_prefetch(P + 8);
        __builtin_prefetch(P + 16);
    }
}

/* ∂I_c/∂σt at the clamped σt (ForwardGrid.collimated_derivative ∘ clamp_sigma_t). */
static inline double collimated_derivative(const tm_forward_grid *f, double sigma_t) {
    double x = exp(-sigma_t * f->thickness_mm), bx2 = f->stack_b * x * x;
    return -f->thickness_mm * f->stack_a * x * (1.0 + bx2) / ((1.0 - bx2) * (1.0 - bx2));
}

static inline double lerp(double a, double b, double w) { return a + (b - a) * w; }

/* L = ln(1 + r) of the in-scattered light at (α cell ia/wa, σt, g cell ig/wg):
 * ForwardGrid.inscatter_log1p, operation for operation. Trilinear; τ clamped to [0, in_tau_max]. */
static double inscatter_log1p(const tm_forward_grid *f, int ia, double wa, double sigma_t, int ig, double wg) {
    double p = clampd(sigma_t * f->thickness_mm, 0.0, f->in_tau_max) * f->in_inv_dt;
    double fi = floor(p);
    fi = fi > f->in_nt - 2 ? f->in_nt - 2 : fi;
    int it = (int)fi;
    double wt = clampd(p - fi, 0.0, 1.0);
    const size_t nt = (size_t)f->in_nt, ng = (size_t)f->ng;
#define L_AT(i, j, k) f->inscatter_L[((size_t)(i) * nt + (size_t)(j)) * ng + (size_t)(k)]
#define ALONG_G(i, j) lerp(L_AT(i, j, ig), L_AT(i, j, ig + 1), wg)
    double value = lerp(lerp(ALONG_G(ia, it), ALONG_G(ia, it + 1), wt),
                        lerp(ALONG_G(ia + 1, it), ALONG_G(ia + 1, it + 1), wt), wa);
#undef ALONG_G
#undef L_AT
    return value;
}

/* Up to `iterations` Newton steps per bin; a bin leaves once a step was small (newton_step;
 * step_var: per bin, or NULL for none; step_tol = 0 and no step_var: a fixed count). The loop over
 * bins is innermost: a bin's steps form one long dependency chain (divisions, table reads) while
 * consecutive bins are independent, so the CPU overlaps them (~2× faster here than bin by bin), and
 * with AVX2 four of them share each instruction (newton_step4; the rest of a round bin by bin).
 * `active` is scratch for n indices; returns the number of steps taken over all bins. */
static size_t polish(const tm_forward_grid *f, size_t n, sigma_cell_t *cells, const double *I_b,
                     const double *I_w, const double *rho_b, const double *rho_w, int iterations,
                     double step_tol, const double *step_var, double *alpha, double *g, uint32_t *active,
                     final_eval_t *evals) {
    size_t m = n, steps = 0;
    for (size_t i = 0; i < n; i++) active[i] = (uint32_t)i;
    for (int it = 0; it < iterations && m > 0; it++) {
        size_t kept = 0, j = 0;
        steps += m;
#ifdef TM_SIMD
        if (use_simd())
            for (; j + 4 <= m; j += 4) {
                uint32_t idx[4] = {active[j], active[j + 1], active[j + 2], active[j + 3]};
                int done[4];
                newton_step4(f, cells, idx, I_b, I_w, rho_b, rho_w, step_tol, step_var, alpha, g, evals, done);
                for (int l = 0; l < 4; l++) {
                    active[kept] = idx[l];
                    kept += !done[l];
                }
            }
#endif
        for (; j < m; j++) {
            uint32_t i = active[j];
            int done = newton_step(f, &cells[i], I_b[i], I_w[i], rho_b[i], rho_w[i], step_tol,
                                   step_var ? step_var[i] : 0.0, &alpha[i], &g[i], &evals[i]);
            active[kept] = i;
            kept += !done;
        }
        m = kept;
    }
    return steps;
}

/* |(I_b, I_w) − model|² at (α, g) and the bin's ∂(I_b, I_w, I_c)/∂(α, σt, g) (Ji: 3 × 3, row I_c has
 * only ∂/∂σt) from one evaluation (ForwardGrid.residual_and_jacobian, which returns the norm). */
static double residual2_and_jacobian(const tm_forward_grid *f, sigma_cell_t *c, double alpha, double g,
                                    double I_b, double I_w, double rho_b, double rho_w, double *Ji) {
    abc_t abc;
    coefficients(f, c, alpha, g, 1, &abc);
    double s = c->sigma_t, res2 = 0.0;
    for (int row = 0; row < 2; row++) {
        double fr, hr;
        double d = diffuse(abc.v, row ? rho_w : rho_b, &fr, &hr) - (row ? I_w : I_b);
        res2 += d * d;
        Ji[row * 3 + 0] = directional(fr, hr, abc.da);
        Ji[row * 3 + 1] = directional(fr, hr, abc.ds) / s;
        Ji[row * 3 + 2] = directional(fr, hr, abc.dg);
    }
    Ji[6] = Ji[8] = 0.0;
    Ji[7] = collimated_derivative(f, c->sigma_t);
    return res2;
}

/* residual2_and_jacobian at a bin's solution: from the polish's converging step where it stored
 * one (ForwardGrid.solve_alpha_g does the same), else evaluated here (bins out of steps, or none). */
static double final_residual2_and_jacobian(const tm_forward_grid *f, sigma_cell_t *c, const final_eval_t *e,
                                           double alpha, double g, double I_b, double I_w, double rho_b,
                                           double rho_w, double *Ji) {
    if (!c->evaluated) return residual2_and_jacobian(f, c, alpha, g, I_b, I_w, rho_b, rho_w, Ji);
    for (int k = 0; k < 6; k++) Ji[k] = e->J[k];
    Ji[6] = Ji[8] = 0.0;
    Ji[7] = collimated_derivative(f, c->sigma_t);
    return e->residual2;
}

/* First-order standard deviations of (α, σt, g) from independent intensity noise (variances var_b,
 * var_w of I_b, I_w; std sd_c of I_c) and a further variance var_s_extra of σt that (α, g) follow
 * (the in-scattering correction's) through one bin's J, using its block structure
 * (ForwardGrid.propagate). Infinite where the (α, g) block is singular. */
static inline void propagate_one(const double *Ji, double var_b, double var_w, double sd_c, double var_s_extra,
                                 double *std_a, double *std_s, double *std_g) {
    double ds = sd_c / Ji[7]; /* σt's std from I_c, signed */
    double var_s = ds * ds + var_s_extra;
    double a = Ji[0], b = Ji[2], c = Ji[3], d = Ji[5];
    double inv_det = 1.0 / (a * d - b * c);
    /* inv = [[d, -b], [-c, a]] / det */
    double i00 = d * inv_det, i01 = -b * inv_det, i10 = -c * inv_det, i11 = a * inv_det;
    double c00 = var_b + Ji[1] * Ji[1] * var_s;
    double c11 = var_w + Ji[4] * Ji[4] * var_s;
    double c01 = Ji[1] * Ji[4] * var_s;
    double va = i00 * (i00 * c00 + i01 * c01) + i01 * (i00 * c01 + i01 * c11);
    double vg = i10 * (i10 * c00 + i11 * c01) + i11 * (i10 * c01 + i11 * c11);
    double sa = sqrt(fabs(va)), sg = sqrt(fabs(vg));
    *std_a = isnan(sa) ? INFINITY : sa;
    *std_g = isnan(sg) ? INFINITY : sg;
    *std_s = sqrt(var_s);
}

static int grid_ok(const tm_forward_grid *f, const tm_inverse_table *table) {
    if (!f || f->na < 2 || f->ns < 2 || f->ng < 2) return 0;
    return !table || (table->ns >= 2 && table->nx >= 2 && table->ny >= 2);
}

/* FLAG_STD_APPROXIMATE: whether a bin's first-order stds hold over ±sigmas σ (ForwardGrid.first_order_holds,
 * operation for operation). From the polish's solution (α, g) and its Jacobian J2 = ∂(I_b, I_w)/∂(α, g),
 * the measured (I_b, I_w) are moved by ±sigmas·σ in I_b, then in I_w (σ: the stds propagated); each
 * move's linear prediction (α, g) + J2⁻¹·δI, clamped to the map's box, is corrected by one Newton step
 * there: where a re-fit from the moved intensities lands, up to the square of its distance from the
 * prediction. The bin holds where correction and clamp stay within tol·sigmas of each std for all
 * four moves. A bin's state between the finish (which picks the bins) and the check: */
typedef struct { double alpha, g, move_b, move_w, j11, j12, j21, j22, limit_a, limit_g; } check_t;

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
    uint32_t *active;
} fit_scratch_t;

size_t tm_fit_scratch_size(size_t n) {
    return (n ? n : 1) *
           (11 * sizeof(double) + sizeof(sigma_cell_t) + sizeof(final_eval_t) + sizeof(check_t) + sizeof(uint32_t));
}

static fit_scratch_t carve_scratch(void *mem, size_t n) {
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
    sc.active = (uint32_t *)(sc.checks + n);
    return sc;
}

/* For each bin (σt given as ln σt, clamped to the grid here): the initial (α, g) from `table` (or
 * from alpha/g on entry when table is NULL), up to `iterations` Newton steps (see polish; step_var
 * may be NULL), then the residual |(I_b, I_w) − model| and ∂(I_b, I_w, I_c)/∂(α, σt, g) at the
 * solution (J: n × 3 × 3).
 * Returns 0, -1 on a malformed grid, -2 when out of memory. */
int tm_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b,
                     const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w,
                     int iterations, double step_tol, const double *step_var, double *alpha, double *g,
                     double *residual, double *J) {
    if (!grid_ok(f, table)) return -1;
    void *scratch = n > UINT32_MAX ? NULL : malloc(tm_fit_scratch_size(n)); /* tm_fit's, its inputs unused */
    if (!scratch) return -2;
    fit_scratch_t sc = carve_scratch(scratch, n);
    sigma_cell_t *cells = sc.cells;
    for (size_t i = 0; i < n; i++) {
        cells[i] = sigma_cell(f, log_sigma_t[i], NAN);
        double a = alpha[i], gg = g[i];
        if (table) initial_guess(table, clamp_log_sigma(f, log_sigma_t[i]), I_b[i], I_w[i], &a, &gg);
        alpha[i] = clampd(a, f->alpha_lo, f->alpha_hi);
        g[i] = clampd(gg, f->g_lo, f->g_hi);
    }
    prefetch_cells(f, n, cells, alpha, g);
    polish(f, n, cells, I_b, I_w, rho_b, rho_w, iterations, step_tol, step_var, alpha, g, sc.active, sc.evals);
    for (size_t i = 0; i < n; i++)
        residual[i] = sqrt(final_residual2_and_jacobian(f, &cells[i], &sc.evals[i], alpha[i], g[i], I_b[i], I_w[i],
                                                        rho_b[i], rho_w[i], J + i * 9u));
    free(scratch);
    return 0;
}

/* First-order standard deviations for n bins (ForwardGrid.propagate); sigma_I is n × 3, sigma_t_var
 * (n, or NULL) a further variance of σt that (α, g) follow. */
void tm_propagate(size_t n, const double *J, const double *sigma_I, const double *sigma_t_var, double *std_a,
                  double *std_s, double *std_g) {
    for (size_t i = 0; i < n; i++) {
        const double *s = sigma_I + i * 3u;
        propagate_one(J + i * 9u, s[0] * s[0], s[1] * s[1], s[2], sigma_t_var ? sigma_t_var[i] : 0.0, &std_a[i],
                      &std_s[i], &std_g[i]);
    }
}

/* ------------------------------------------------------------------------------ the whole fit
 * trimeter.inversion.api._fit_one + _finish for one thickness, bin by bin: input flags → σt from
 * I_c (exact inverse of the Fresnel stack; the floor's σt, a lower bound, under ic_floor) → (α, g)
 * by guess + polish → flags for not converged / outside the map / g undefined → first-order stds →
 * NaN for unusable bins. The numpy path in api.py is the reference (same operations, same order);
 * tests/inversion/test_native_kernel.py checks both bin for bin, flags included. */

/* FitFlag bits (trimeter.inversion.flags). tm_flag_bits hands them to Python, which refuses the
 * library if they differ from FitFlag, so the two declarations cannot drift apart silently. */
enum {
    FLAG_NONFINITE_INPUT = 1 << 0,
    FLAG_NEGATIVE_INPUT = 1 << 1,
    FLAG_ABOVE_ONE = 1 << 2,
    FLAG_BLACK_NOT_BELOW_WHITE = 1 << 3,
    FLAG_IC_BELOW_FLOOR = 1 << 4,
    FLAG_G_UNDEFINED = 1 << 5,
    FLAG_OUTSIDE_MAP = 1 << 6,
    FLAG_NOT_CONVERGED = 1 << 7,
    FLAG_BAD_BACKGROUND = 1 << 9,
    FLAG_UNDERDETERMINED = 1 << 10,
    FLAG_STD_APPROXIMATE = 1 << 11,
    FLAG_UNUSABLE = FLAG_NONFINITE_INPUT | FLAG_NEGATIVE_INPUT | FLAG_ABOVE_ONE | FLAG_BAD_BACKGROUND,
    /* bins whose stds already come with a caveat are not checked for FLAG_STD_APPROXIMATE */
    STD_CHECK_SKIP = FLAG_UNUSABLE | FLAG_UNDERDETERMINED | FLAG_G_UNDEFINED | FLAG_OUTSIDE_MAP | FLAG_NOT_CONVERGED,
};

void tm_flag_bits(int64_t out[11]) {
    const int64_t bits[11] = {FLAG_NONFINITE_INPUT, FLAG_NEGATIVE_INPUT, FLAG_ABOVE_ONE, FLAG_BLACK_NOT_BELOW_WHITE,
                              FLAG_IC_BELOW_FLOOR, FLAG_G_UNDEFINED, FLAG_OUTSIDE_MAP, FLAG_NOT_CONVERGED,
                              FLAG_BAD_BACKGROUND, FLAG_UNDERDETERMINED, FLAG_STD_APPROXIMATE};
    for (int k = 0; k < 11; k++) out[k] = bits[k];
}

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

/* A fit's outputs: one caller-owned block of 10 rows of n, in this order (flags: int64), so that
 * Python hands over one address (NativeSolver: one allocation, no struct to build per call).
 * cond_*: α's and g's std at no less than the noise model, which UNDERDETERMINED is judged on. */
typedef struct {
    double *alpha, *sigma_t, *g, *alpha_std, *sigma_t_std, *g_std, *sigma_t_beer;
    int64_t *flags;
    double *cond_alpha_std, *cond_g_std;
} tm_fit_outputs;

static tm_fit_outputs outputs_in(double *block, size_t n) {
    tm_fit_outputs o = {block, block + n, block + 2 * n, block + 3 * n, block + 4 * n, block + 5 * n, block + 6 * n,
                        (int64_t *)(block + 7 * n), block + 8 * n, block + 9 * n};
    return o;
}

/* beer_lambert_sigma_t: solve b·I·x² + a·x − I = 0 for x = exp(−σt ℓ) (the stable root); NaN where
 * I_c is not in (0, t_valid]. */
static inline double beer_lambert(const tm_forward_grid *f, const tm_fit_options *o, double I_c) {
    if (!(isfinite(I_c) && I_c > 0.0 && I_c <= o->t_valid)) return NAN;
    double a = f->stack_a;
    double x = 2.0 * I_c / (a + sqrt(a * a + 4.0 * f->stack_b * I_c * I_c));
    double sigma = -log(x) / f->thickness_mm;
    return sigma > 0.0 ? sigma : 0.0;
}

static inline double sanitize(double x, double fill) { return isfinite(x) ? clampd(x, 0.0, 1.0) : fill; }

/* One bin's input flags, sanitized stand-ins (unusable bins are computed on harmless stand-ins and
 * blanked at the end), σt from I_c (under the floor the floor's σt, a lower bound; above
 * T(σt = 0), σt = 0) and the Beer-Lambert consistency column: api._prepare. Returns the flags. */
typedef struct { double lo, hi; } sigma_bounds_t; /* the grid's σt range, widened by 1e-6 for rounding */

static sigma_bounds_t sigma_bounds(const tm_forward_grid *f) {
    sigma_bounds_t b = {exp(f->log_sigma_t[0]) * (1 - 1e-6), exp(f->log_sigma_t[f->ns - 1]) * (1 + 1e-6)};
    return b;
}

static int64_t prepare_bin(const tm_forward_grid *f, const tm_fit_options *o, sigma_bounds_t bounds, double Ib,
                           double Iw, double Ic, double Rb, double Rw, double *ib, double *iw, double *rb, double *rw,
                           double *sigma_t, double *sigma_beer) {
    const double tol = o->input_tolerance;
    int64_t fl = 0;
    int finite = isfinite(Ib) && isfinite(Iw) && isfinite(Ic) && isfinite(Rb) && isfinite(Rw);
    if (!finite) fl |= FLAG_NONFINITE_INPUT;
    if (Ib < -tol || Iw < -tol || Ic < -tol) fl |= FLAG_NEGATIVE_INPUT;
    if (Ib > 1 + tol || Iw > 1 + tol || Ic > 1 + tol) fl |= FLAG_ABOVE_ONE;
    if (finite && !(Rb >= 0 && Rb < Rw && Rw <= 1)) fl |= FLAG_BAD_BACKGROUND;
    if (finite && Ib >= Iw) fl |= FLAG_BLACK_NOT_BELOW_WHITE;
    int usable = !(fl & FLAG_UNUSABLE);
    *ib = sanitize(Ib, 0.0);
    *iw = sanitize(Iw, 1.0);
    double ic = sanitize(Ic, 1.0);
    *rb = usable ? Rb : o->ref_rho_b;
    *rw = usable ? Rw : o->ref_rho_w;
    if (usable && ic < o->ic_floor) fl |= FLAG_IC_BELOW_FLOOR;
    double s = beer_lambert(f, o, fmin(fmax(ic, o->ic_floor), o->t_max));
    int in_range = isfinite(Ic) && Ic >= o->ic_floor && Ic <= o->t_max;
    *sigma_beer = in_range ? s : beer_lambert(f, o, Ic);
    if (usable && (s < bounds.lo || s > bounds.hi)) fl |= FLAG_OUTSIDE_MAP;
    *sigma_t = s;
    return fl;
}

/* The first half of a fit: input flags, σt from I_c and the Beer-Lambert column into `outputs`, the
 * sanitized inputs and σt cells into `scratch`; with `features` (n × 5 float32, else NULL) also the
 * MLP's input (trimeter.inversion.mlp.features; ln σt clamped to [log_lo, log_hi]), so that the
 * network's guess can go to tm_fit_solve without preparing the bins twice. */
void tm_fit_prepare(const tm_forward_grid *f, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w,
                    const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, void *scratch,
                    double *outputs, double log_lo, double log_hi, float *features) {
    fit_scratch_t sc = carve_scratch(scratch, n);
    const tm_fit_outputs o_ = outputs_in(outputs, n), *out = &o_;
    const double mc2 = o->mc_stderr * o->mc_stderr, kappa2 = o->step_tol_std * o->step_tol_std;
    const sigma_bounds_t bounds = sigma_bounds(f);
    for (size_t i = 0; i < n; i++) {
        double s, beer;
        out->flags[i] = prepare_bin(f, o, bounds, I_b[i], I_w[i], I_c[i], rho_b[i], rho_w[i], &sc.ib[i], &sc.iw[i],
                                    &sc.rb[i], &sc.rw[i], &s, &beer);
        out->sigma_t_beer[i] = beer;
        out->sigma_t[i] = s;
        double sb = o->noise_rel * sc.ib[i] + o->noise_abs, sw = o->noise_rel * sc.iw[i] + o->noise_abs;
        double sc_ = o->noise_rel * sanitize(I_c[i], 1.0) + o->noise_abs;
        sc.cond_var_b[i] = sc.var_b[i] = sb * sb;
        sc.cond_var_w[i] = sc.var_w[i] = sw * sw;
        sc.cond_sd_c[i] = sc.sd_c[i] = sc_;
        if (sd_in) { /* the intensities' own stds (n × 3; api.fit has put the noise model where they were missing) */
            const double *sd = sd_in + i * 3u;
            sc.var_b[i] = sd[0] * sd[0];
            sc.var_w[i] = sd[1] * sd[1];
            sc.sd_c[i] = sd[2];
            sc.cond_var_b[i] = fmax(sc.var_b[i], sc.cond_var_b[i]);
            sc.cond_var_w[i] = fmax(sc.var_w[i], sc.cond_var_w[i]);
            sc.cond_sd_c[i] = fmax(sc.sd_c[i], sc.cond_sd_c[i]);
        }
        /* (κ σ)², σ² the mean of I_b's and I_w's */
        sc.step_var[i] = kappa2 * 0.5 * (sc.var_b[i] + sc.var_w[i] + 2.0 * mc2);
        double ls = log(s);
        sc.cells[i] = sigma_cell(f, ls, s);
        if (features) {
            float *xi = features + i * 5u;
            xi[0] = (float)sqrt(sc.ib[i]); /* ib, iw: already in [0, 1] */
            xi[1] = (float)sqrt(sc.iw[i]);
            xi[2] = (float)clampd(s > 1e-30 ? ls : log(1e-30), log_lo, log_hi); /* as mlp.features */
            xi[3] = (float)sc.rb[i];
            xi[4] = (float)sc.rw[i];
        }
    }
}

/* In-scattered light in I_c (ForwardGrid.correct_inscatter, operation for operation): a measured I_c
 * is T(σt)·e^L(α, σt, g), so with (α, g) solved, σt moves up by L/ℓ (ln T falls by ℓ per unit σt;
 * the Fresnel stack adds at most 3.6e-3 of that slope), L taken again at the moved σt (it grows
 * with σt), and (α, g) follow to first order so that (I_b, I_w) stay fitted: J2·δ(α, g) = −∂I/∂σt·δσt,
 * solved as a Newton step (lm_step). One bin; Ji its 3 × 3
 * Jacobian at the solution, which stays that of the result (first order). */
#define INSCATTER_ONCE 1e-3
double tm_inscatter_once(void) { return INSCATTER_ONCE; } /* Python refuses the library unless it is native's */

static double correct_inscatter(const tm_forward_grid *f, const sigma_cell_t *c, const double *Ji, double *alpha,
                                double *sigma_t, double *g) {
    double wa, wg, s0 = *sigma_t;
    int ia = c->ia < 0 ? find_cell(f->alpha, f->inv_da, f->na, *alpha, &wa)
                       : walk_from(f->alpha, f->inv_da, f->na, *alpha, c->ia, &wa);
    int ig = c->ig < 0 ? find_cell(f->g, f->inv_dg, f->ng, *g, &wg) : walk_from(f->g, f->inv_dg, f->ng, *g, c->ig, &wg);
    double L = inscatter_log1p(f, ia, wa, s0, ig, wg);
    if (!(L > 0.0)) return 0.0; /* nothing scattered in */
    double s = s0 + L / f->thickness_mm;
    /* L again at the moved σt: it changes σt by ~L·dL/dτ, below 1e-6 of σt where L ≤ INSCATTER_ONCE */
    if (L > INSCATTER_ONCE) s = s0 + inscatter_log1p(f, ia, wa, s, ig, wg) / f->thickness_mm;
    double ds = s - s0;
    if (!(ds > 0.0)) return 0.0;
    /* the residual the σt move alone would leave in (I_b, I_w), taken out by one step in (α, g) */
    lm_step_t st = lm_step(Ji[0], Ji[2], Ji[3], Ji[5], Ji[1] * ds, Ji[4] * ds);
    *alpha = clampd(*alpha + st.step_a, f->alpha_lo, f->alpha_hi);
    *g = clampd(*g + st.step_g, f->g_lo, f->g_hi);
    *sigma_t = s;
    return ds;
}

/* The map's error variances of I_b, I_w at (α, the bin's σt cell, g): trilinear on model_var's nodes,
 * along g, then σt, then α (ForwardGrid.model_variance). */
static void model_variance(const tm_forward_grid *f, const sigma_cell_t *c, double alpha, double g, double *var_b,
                           double *var_w) {
    double wa, wg, ws = c->ws;
    /* from the last evaluation's cells (the solution is at most a step away): find_cell's result for any
     * non-NaN (α, g), without its search */
    int ia = c->ia < 0 ? find_cell(f->alpha, f->inv_da, f->na, alpha, &wa)
                       : walk_from(f->alpha, f->inv_da, f->na, alpha, c->ia, &wa);
    int ig = c->ig < 0 ? find_cell(f->g, f->inv_dg, f->ng, g, &wg) : walk_from(f->g, f->inv_dg, f->ng, g, c->ig, &wg);
    int is = c->is;
    double out[2];
    for (int k = 0; k < 2; k++) {
        double along_s[2];
        for (int da = 0; da < 2; da++) {
            double along_g[2];
            for (int ds = 0; ds < 2; ds++) {
                const double *v = f->model_var + ((((size_t)(ia + da) * (size_t)f->ns + (size_t)(is + ds)) *
                                                   (size_t)f->ng + (size_t)ig) * 2u + (size_t)k);
                along_g[ds] = v[0] + (v[2] - v[0]) * wg;
            }
            along_s[da] = along_g[0] + (along_g[1] - along_g[0]) * ws;
        }
        out[k] = along_s[0] + (along_s[1] - along_s[0]) * wa;
    }
    *var_b = out[0];
    *var_w = out[1];
}

/* One move (on_b: in I_b, else I_w; dI its signed size): the prediction's offset (da, dg) and where
 * it lands clamped (a1, g1). */
static inline void check_target(const tm_forward_grid *f, const check_t *k, int on_b, double dI, double *da,
                                double *dg, double *a1, double *g1) {
    double det = k->j11 * k->j22 - k->j12 * k->j21;
    /* J2⁻¹'s column for I_b is (j22, −j21)/det, for I_w (−j12, j11)/det */
    *da = on_b ? (k->j22 * dI) / det : (-k->j12 * dI) / det;
    *dg = on_b ? (-k->j21 * dI) / det : (k->j11 * dI) / det;
    *a1 = clampd(k->alpha + *da, f->alpha_lo, f->alpha_hi);
    *g1 = clampd(k->g + *dg, f->g_lo, f->g_hi);
}

/* The check for the bins listed in idx (m of them), move by move with the bins innermost (their
 * table reads, cells a few σ from the solution's, then overlap). Sets FLAG_STD_APPROXIMATE in flags. */
static void check_first_order(const tm_forward_grid *f, size_t m, const uint32_t *idx, const check_t *checks,
                              sigma_cell_t *cells, const double *I_b, const double *I_w, const double *rho_b,
                              const double *rho_w, double sigmas, int64_t *flags) {
    for (int move = 0; move < 4; move++) {
        int on_b = move < 2;
        for (size_t j = 0; j < m; j++) {
            size_t i = idx[j];
            const check_t *k = &checks[i];
            if (flags[i] & FLAG_STD_APPROXIMATE) continue;
            double dI = (move & 1 ? -sigmas : sigmas) * (on_b ? k->move_b : k->move_w);
            double da, dg, a1, g1;
            check_target(f, k, on_b, dI, &da, &dg, &a1, &g1);
            abc_t e;
            coefficients(f, &cells[i], a1, g1, 0, &e);
            double gb, kb, gw, kw;
            double rb = diffuse(e.v, rho_b[i], &gb, &kb) - (on_b ? I_b[i] + dI : I_b[i]);
            double rw = diffuse(e.v, rho_w[i], &gw, &kw) - (on_b ? I_w[i] : I_w[i] + dI);
            lm_step_t st = lm_step(directional(gb, kb, e.da), directional(gb, kb, e.dg), directional(gw, kw, e.da),
                                   directional(gw, kw, e.dg), rb, rw);
            double a2 = clampd(a1 + st.step_a, f->alpha_lo, f->alpha_hi);
            double g2 = clampd(g1 + st.step_g, f->g_lo, f->g_hi);
            if (!(fabs(a2 - k->alpha - da) <= k->limit_a && fabs(g2 - k->g - dg) <= k->limit_g))
                flags[i] |= FLAG_STD_APPROXIMATE;
        }
    }
}

/* The second half: the initial (α, g) from alpha0/g0 (the MLP's) or, where those are NULL or not
 * finite (a broken network), from `table` (without one: the middle of the map's box); the polish,
 * then flags for not converged / outside the map / g undefined / underdetermined, first-order stds
 * and NaN for unusable bins. Returns the number of Newton steps taken (≥ 0), -1 on a malformed grid
 * or a missing guess. */
long long tm_fit_solve(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n,
                       const double *alpha0, const double *g0, void *scratch,
                       double *outputs) {
    if (!grid_ok(f, table) || (!alpha0 && !table) || (alpha0 && !g0) || n > UINT32_MAX) return -1;
    fit_scratch_t sc = carve_scratch(scratch, n);
    const tm_fit_outputs o_ = outputs_in(outputs, n), *out = &o_;
    const double *ib = sc.ib, *iw = sc.iw, *rb = sc.rb, *rw = sc.rw;
    sigma_cell_t *cells = sc.cells;
    const double mc2 = o->mc_stderr * o->mc_stderr;
    double *alpha = out->alpha, *g = out->g, *sigma_t = out->sigma_t;
    for (size_t i = 0; i < n; i++) {
        double a = alpha0 ? alpha0[i] : NAN, gg = g0 ? g0[i] : NAN;
        if (!(isfinite(a) && isfinite(gg))) {
            a = 0.5 * (f->alpha_lo + f->alpha_hi);
            gg = 0.5 * (f->g_lo + f->g_hi);
            if (table) initial_guess(table, cells[i].log_sigma_t, ib[i], iw[i], &a, &gg);
        }
        alpha[i] = clampd(a, f->alpha_lo, f->alpha_hi);
        g[i] = clampd(gg, f->g_lo, f->g_hi);
    }
    prefetch_cells(f, n, cells, alpha, g);
    size_t steps = polish(f, n, cells, ib, iw, rb, rw, o->iterations, o->step_tol, sc.step_var, alpha, g, sc.active,
                          sc.evals);
    const int g_lo_is_edge = f->g_lo > -1 + 1e-6, g_hi_is_edge = f->g_hi < 1 - 1e-6;
    size_t checked = 0; /* bins for check_first_order, listed in sc.active (the polish is done with it) */
    for (size_t i = 0; i < n; i++) {
        double Ji[9];
        int64_t fl = out->flags[i];
        int usable = !(fl & FLAG_UNUSABLE);
        double residual2 = final_residual2_and_jacobian(f, &cells[i], &sc.evals[i], alpha[i], g[i], ib[i], iw[i], rb[i],
                                                        rw[i], Ji);
        check_t *k = &sc.checks[i];
        k->alpha = alpha[i];
        k->g = g[i];
        k->j11 = Ji[0];
        k->j12 = Ji[2];
        k->j21 = Ji[3];
        k->j22 = Ji[5];
        double ds_in = 0.0; /* the in-scattering correction of σt */
        if (f->inscatter_L && !(fl & (FLAG_UNUSABLE | FLAG_IC_BELOW_FLOOR | FLAG_OUTSIDE_MAP)))
            ds_in = correct_inscatter(f, &cells[i], Ji, &alpha[i], &sigma_t[i], &g[i]);
        /* variances, not stds: only their sums are needed (sqrt(x² + y²), not hypot: these are small
         * positive numbers, nothing to guard, and hypot is slower) */
        double var_b = sc.var_b[i] + mc2, var_w = sc.var_w[i] + mc2;
        double tolerance = 3.0 * sqrt(var_b + var_w) + 1e-4;
        int not_conv = !(residual2 <= tolerance * tolerance); /* |residual| ≤ tolerance, squared */
        int at_edge = (g[i] <= f->g_lo + 1e-9 && g_lo_is_edge) || (g[i] >= f->g_hi - 1e-9 && g_hi_is_edge);
        if (usable && not_conv) fl |= FLAG_NOT_CONVERGED;
        if (usable && not_conv && at_edge) fl |= FLAG_OUTSIDE_MAP;
        double a = isfinite(alpha[i]) ? clampd(alpha[i], 0.0, 1.0) : NAN;
        double gg = isfinite(g[i]) ? clampd(g[i], -1.0, 1.0) : NAN;
        /* the map's own error at the solution, in place of its median MC std-error where the grid has it */
        double model_b = mc2, model_w = mc2;
        if (f->model_var) model_variance(f, &cells[i], alpha[i], g[i], &model_b, &model_w);
        double sa, ss, sg, ds_rel = o->inscatter_rel_std * ds_in;
        propagate_one(Ji, sc.var_b[i] + model_b, sc.var_w[i] + model_w, sc.sd_c[i], ds_rel * ds_rel, &sa, &ss, &sg);
        double thick = o->thickness_rel_std * sigma_t[i];
        ss = sqrt(ss * ss + thick * thick);
        if (fl & FLAG_IC_BELOW_FLOOR) ss = INFINITY;
        if (usable && !(a >= o->alpha_min_g)) {
            fl |= FLAG_G_UNDEFINED;
            gg = sg = NAN;
        }
        /* UNDERDETERMINED is the map's conditioning at no less than the instrument's noise model: a
         * capture's frame scatter alone misses drift and calibration error, and one quiet capture
         * must not make α and g look told apart where a realistic noise leaves them not */
        double ua = sa, us = ss, ug = sg;
        if (sc.cond_var_b[i] != sc.var_b[i] || sc.cond_var_w[i] != sc.var_w[i] || sc.cond_sd_c[i] != sc.sd_c[i]) {
            propagate_one(Ji, sc.cond_var_b[i] + model_b, sc.cond_var_w[i] + model_w, sc.cond_sd_c[i], ds_rel * ds_rel,
                          &ua, &us, &ug);
            if (isnan(gg)) ug = NAN;
        }
        if (usable && (ua > o->underdetermined_alpha_std || ug > o->underdetermined_g_std)) fl |= FLAG_UNDERDETERMINED;
        if (!(fl & STD_CHECK_SKIP) && isfinite(sa) && isfinite(sg) && (sa > o->std_check_alpha || sg > o->std_check_g)) {
            k->move_b = sqrt(sc.var_b[i] + model_b);
            k->move_w = sqrt(sc.var_w[i] + model_w);
            k->limit_a = o->std_check_tol * o->std_check_sigmas * sa;
            k->limit_g = o->std_check_tol * o->std_check_sigmas * sg;
            sc.active[checked++] = (uint32_t)i;
        }
        if (!usable) {
            a = gg = sa = ss = sg = ua = ug = NAN;
            sigma_t[i] = out->sigma_t_beer[i] = NAN;
        }
        alpha[i] = a;
        g[i] = gg;
        out->alpha_std[i] = sa;
        out->sigma_t_std[i] = ss;
        out->g_std[i] = sg;
        out->cond_alpha_std[i] = ua;
        out->cond_g_std[i] = ug;
        out->flags[i] = fl;
    }
    check_first_order(f, checked, sc.active, sc.checks, cells, ib, iw, rb, rw, o->std_check_sigmas, out->flags);
    return (long long)steps;
}

/* Both halves with the table's guess (or alpha0/g0): -1 on a malformed grid, -2 when out of memory. */
long long tm_fit(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n,
                 const double *I_b, const double *I_w, const double *I_c, const double *rho_b, const double *rho_w,
                 const double *sd_in, const double *alpha0, const double *g0, double *outputs) {
    if (!grid_ok(f, table) || (!alpha0 && !table) || (alpha0 && !g0)) return -1;
    void *scratch = n > UINT32_MAX ? NULL : malloc(tm_fit_scratch_size(n));
    if (!scratch) return -2;
    tm_fit_prepare(f, o, n, I_b, I_w, I_c, rho_b, rho_w, sd_in, scratch, outputs, 0.0, 0.0, NULL);
    long long steps = tm_fit_solve(f, table, o, n, alpha0, g0, scratch, outputs);
    free(scratch);
    return steps;
}
