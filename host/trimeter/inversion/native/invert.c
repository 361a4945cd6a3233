/* The inversion hot path in C: the map table's initial guess, the damped Gauss-Newton polish of
 * (α, g) at a known σt on the trilinear forward map, the Jacobian at the solution and the
 * first-order uncertainty. One pass per bin, everything in registers.
 *
 * Why C: the numpy kernel (trimeter.inversion.kernel / lut) spends its time in ~100 array
 * operations per Newton step, each a few µs of interpreter and allocation overhead at ~1000 bins;
 * the arithmetic itself is ~200 flops per bin and step. This file is the same algorithm, operation
 * for operation, so the numpy kernel stays the reference: tests/inversion/test_native_kernel.py
 * checks that both agree to ~1e-12. Loaded with ctypes (trimeter.inversion.native); no Python API,
 * no dependency beyond libm. Build: `make native` (cc -O2 -shared -fPIC).
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

#define TM_ABI_VERSION 1

typedef struct {
    int32_t na, ns, ng;
    const double *alpha, *log_sigma_t, *g; /* axes */
    const double *inv_da, *inv_ds, *inv_dg; /* 1 / axis spacing, per interval */
    const double *poly;
    double alpha_lo, alpha_hi, g_lo, g_hi;
} tm_forward_grid;

typedef struct {
    int32_t ns, ny, nx;
    const double *cells;
    const double *frame;
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

/* ln σt clamped to the grid the way ForwardGrid.sigma_cell does (NaN → lowest node, ±inf → ends). */
static inline double clamp_log_sigma(const tm_forward_grid *f, double log_sigma_t) {
    double lo = f->log_sigma_t[0], hi = f->log_sigma_t[f->ns - 1];
    return isnan(log_sigma_t) ? lo : clampd(log_sigma_t, lo, hi);
}

typedef struct { double v[3], da[3], dg[3], ds[3]; } abc_t;

/* A, B, C at (α, cell σ, g) and their derivatives (ForwardGrid.coefficients). */
static void coefficients(const tm_forward_grid *f, int is, double ws, double alpha, double g, int with_ds,
                         abc_t *out) {
    double wa, wg;
    int ia = find_cell(f->alpha, f->inv_da, f->na, alpha, &wa);
    int ig = find_cell(f->g, f->inv_dg, f->ng, g, &wg);
    const double *P = f->poly + (((size_t)ia * (size_t)(f->ns - 1) + (size_t)is) * (size_t)(f->ng - 1) + (size_t)ig) * 24u;
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

static void initial_guess(const tm_inverse_table *t, int is, double ws, double I_b, double I_w,
                          double *alpha, double *g) {
    double x = sqrt(clampd(I_b, 0.0, 1.0)), y = sqrt(clampd(I_w, 0.0, 1.0));
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

/* One Levenberg-Marquardt step on the 2×2 normal equations (ForwardGrid._newton_step). */
static void newton_step(const tm_forward_grid *f, int is, double ws, double I_b, double I_w, double rho_b,
                        double rho_w, double *alpha, double *g) {
    abc_t c;
    coefficients(f, is, ws, *alpha, *g, 0, &c);
    double fb, hb, fw, hw;
    double rb = diffuse(c.v, rho_b, &fb, &hb) - I_b;
    double rw = diffuse(c.v, rho_w, &fw, &hw) - I_w;
    double j11 = directional(fb, hb, c.da), j12 = directional(fb, hb, c.dg);
    double j21 = directional(fw, hw, c.da), j22 = directional(fw, hw, c.dg);
    double h11 = j11 * j11 + j21 * j21, h22 = j12 * j12 + j22 * j22, h12 = j11 * j12 + j21 * j22;
    double mu = 1e-9 + 1e-6 * (h11 + h22); /* stays finite where ∂I/∂g → 0 (α → 0) */
    h11 += mu;
    h22 += mu;
    double b1 = j11 * rb + j21 * rw, b2 = j12 * rb + j22 * rw;
    double det = h11 * h22 - h12 * h12;
    double step_a = -(h22 * b1 - h12 * b2) / det;
    double step_g = -(h11 * b2 - h12 * b1) / det;
    /* trust region: a piecewise-trilinear map is only locally linear */
    step_a = clampd(step_a, -0.25, 0.25);
    step_g = clampd(step_g, -0.5, 0.5);
    *alpha = clampd(*alpha + step_a, f->alpha_lo, f->alpha_hi);
    *g = clampd(*g + step_g, f->g_lo, f->g_hi);
}

/* For each bin (σt given as ln σt, clamped to the grid here): the initial (α, g) from `table` (or from alpha/g on entry when table is NULL),
 * `iterations` Newton steps, then the residual |(I_b, I_w) − model| and the rows I_b, I_w of
 * ∂(I_b, I_w, I_c)/∂(α, σt, g) at the solution (J: n × 3 × 3; row I_c is left to the caller,
 * it depends on σt alone). Returns 0, or -1 on a malformed grid. */
int tm_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b,
                     const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w,
                     int iterations, double *alpha, double *g, double *residual, double *J) {
    if (!f || f->na < 2 || f->ns < 2 || f->ng < 2) return -1;
    if (table && (table->ns != f->ns || table->nx < 2 || table->ny < 2)) return -1;
    /* Three passes over the bins rather than one bin at a time: a bin's Newton steps form one long
     * dependency chain (divisions, table reads), while consecutive bins are independent, so the
     * CPU overlaps them when the loop over bins is innermost (~2× faster here). alpha/g hold the
     * iterate; the σt cell is recomputed per pass (a few ns) instead of stored. */
    for (size_t i = 0; i < n; i++) {
        double ws;
        int is = find_cell(f->log_sigma_t, f->inv_ds, f->ns, clamp_log_sigma(f, log_sigma_t[i]), &ws);
        double a = alpha[i], gg = g[i];
        if (table) initial_guess(table, is, ws, I_b[i], I_w[i], &a, &gg);
        alpha[i] = clampd(a, f->alpha_lo, f->alpha_hi);
        g[i] = clampd(gg, f->g_lo, f->g_hi);
    }
    for (int it = 0; it < iterations; it++) {
        for (size_t i = 0; i < n; i++) {
            double ws;
            int is = find_cell(f->log_sigma_t, f->inv_ds, f->ns, clamp_log_sigma(f, log_sigma_t[i]), &ws);
            newton_step(f, is, ws, I_b[i], I_w[i], rho_b[i], rho_w[i], &alpha[i], &g[i]);
        }
    }
    for (size_t i = 0; i < n; i++) {
        double ws;
        double ls = clamp_log_sigma(f, log_sigma_t[i]);
        int is = find_cell(f->log_sigma_t, f->inv_ds, f->ns, ls, &ws);
        abc_t c;
        coefficients(f, is, ws, alpha[i], g[i], 1, &c);
        double s = exp(ls);
        double res2 = 0.0;
        double *Ji = J + i * 9u;
        for (int row = 0; row < 2; row++) {
            double fr, hr;
            double I = diffuse(c.v, row ? rho_w[i] : rho_b[i], &fr, &hr);
            double d = I - (row ? I_w[i] : I_b[i]);
            res2 += d * d;
            Ji[row * 3 + 0] = directional(fr, hr, c.da);
            Ji[row * 3 + 1] = directional(fr, hr, c.ds) / s;
            Ji[row * 3 + 2] = directional(fr, hr, c.dg);
        }
        Ji[6] = Ji[7] = Ji[8] = 0.0;
        residual[i] = sqrt(res2);
    }
    return 0;
}

/* First-order standard deviations of (α, σt, g) from independent intensity noise sigma_I (n × 3),
 * using the block structure of J (row I_c has only ∂/∂σt) — ForwardGrid.propagate. Infinite where
 * the 2×2 block is singular. */
void tm_propagate(size_t n, const double *J, const double *sigma_I, double *std_a, double *std_s, double *std_g) {
    for (size_t i = 0; i < n; i++) {
        const double *Ji = J + i * 9u;
        const double *s = sigma_I + i * 3u;
        double var_s = (s[2] / Ji[7]) * (s[2] / Ji[7]);
        double a = Ji[0], b = Ji[2], c = Ji[3], d = Ji[5];
        double det = a * d - b * c;
        /* inv = [[d, -b], [-c, a]] / det */
        double i00 = d / det, i01 = -b / det, i10 = -c / det, i11 = a / det;
        double c00 = s[0] * s[0] + Ji[1] * Ji[1] * var_s;
        double c11 = s[1] * s[1] + Ji[4] * Ji[4] * var_s;
        double c01 = Ji[1] * Ji[4] * var_s;
        double va = i00 * (i00 * c00 + i01 * c01) + i01 * (i00 * c01 + i01 * c11);
        double vg = i10 * (i10 * c00 + i11 * c01) + i11 * (i10 * c01 + i11 * c11);
        double sa = sqrt(fabs(va)), sg = sqrt(fabs(vg));
        std_a[i] = isnan(sa) ? INFINITY : sa;
        std_g[i] = isnan(sg) ? INFINITY : sg;
        std_s[i] = sqrt(var_s);
    }
}
