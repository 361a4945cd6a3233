/* The fit from the device table alone, one bin at a time, bounded stack, no state, no allocation:
 * what the firmware links (tr_fit_bins, fit_core.h) and the host calls in double precision
 * (tm_table_fit, table_fit.h). Per bin, the host's lut fit with fit()'s defaults (the
 * TM_TABLE_FIT_* constants; trimeter.inversion.api._prepare, trimeter.inversion.finish.finish) with the compact model in place of
 * the refined grid: input flags → σt from I_c (exact inverse of the Fresnel stack) → the inverse
 * table's guess → damped Gauss-Newton polish of (α, g) on the compact model → in-scattering
 * correction → NOT_CONVERGED / OUTSIDE_MAP / G_UNDEFINED / UNDERDETERMINED → NaN for unusable bins.
 * STD_APPROXIMATE is not set: it qualifies the stds, which this fit does not return. */
#include <math.h>

#include "compact.h"
#include "fit_core.h"
#include "table_fit.h"

_Static_assert(TM_TABLE_FIT_ERR_TABLE == TR_FIT_ERR_TABLE && TM_TABLE_FIT_ERR_ARGS == TR_FIT_ERR_ARGS,
               "the host's and the firmware's entries return the same codes");

enum {
    UNUSABLE = TM_FLAG_NONFINITE_INPUT | TM_FLAG_NEGATIVE_INPUT | TM_FLAG_ABOVE_ONE | TM_FLAG_BAD_BACKGROUND,
};

typedef struct { tr_real residual[2], J[2][3]; } evaluation_t; /* rows I_b, I_w; columns α, σt, g */

/* I(ρ) = A + Bρ/(1 − Cρ) and its gradient in B and C (ForwardGrid.diffuse) */
static tr_real diffuse(const tr_real *abc, tr_real rho, tr_real *grad_b, tr_real *grad_c) {
    tr_real fr = rho / (R(1.0) - abc[2] * rho);
    *grad_b = fr;
    *grad_c = abc[1] * fr * fr;
    return abc[0] + abc[1] * fr;
}

static tr_real directional(tr_real grad_b, tr_real grad_c, const tr_real *d) { return d[0] + grad_b * d[1] + grad_c * d[2]; }

/* residuals of (I_b, I_w) and ∂(I_b, I_w)/∂(α, σt, g) at (α, ln σt, g) from one model evaluation */
static void evaluate(const tr_table *t, tr_real alpha, tr_sigma_slice *slice, tr_real sigma_t, tr_real g,
                     tr_real I_b, tr_real I_w, tr_real rho_b, tr_real rho_w, evaluation_t *e) {
    tr_abc c;
    tr_compact_eval(t, alpha, slice, g, &c);
    for (int row = 0; row < 2; row++) {
        tr_real fr, hr;
        e->residual[row] = diffuse(c.v, row ? rho_w : rho_b, &fr, &hr) - (row ? I_w : I_b);
        e->J[row][0] = directional(fr, hr, c.da);
        e->J[row][1] = directional(fr, hr, c.ds) / sigma_t;
        e->J[row][2] = directional(fr, hr, c.dg);
    }
}

/* The damped Gauss-Newton step on the 2×2 normal equations, capped to a trust region (newton.lm_step) */
typedef struct { tr_real step_a, step_g, h11, h22, det, b1, b2; } lm_step_t;

static lm_step_t lm_step(tr_real j11, tr_real j12, tr_real j21, tr_real j22, tr_real rb, tr_real rw) {
    lm_step_t st;
    tr_real h11 = j11 * j11 + j21 * j21, h22 = j12 * j12 + j22 * j22;
    tr_real mu = R(1e-9) + R(1e-6) * (h11 + h22); /* stays finite where ∂I/∂g → 0 (α → 0) */
    h11 += mu;
    h22 += mu;
    tr_real b1 = j11 * rb + j21 * rw, b2 = j12 * rb + j22 * rw;
    /* h11·h22 − h12² and h22·b1 − h12·b2 written out in D = det J: the same numbers, without
     * subtracting squares that agree to all but a few digits where α and g are hard to tell apart
     * (single precision has none to spare there) */
    tr_real D = j11 * j22 - j12 * j21;
    tr_real det = D * D + mu * (h11 + h22 - mu);
    st.step_a = tr_clamp(-(D * (j22 * rb - j12 * rw) + mu * b1) / det, R(-0.25), R(0.25));
    st.step_g = tr_clamp(-(D * (j11 * rw - j21 * rb) + mu * b2) / det, R(-0.5), R(0.5));
    st.h11 = h11;
    st.h22 = h22;
    st.det = det;
    st.b1 = b1;
    st.b2 = b2;
    return st;
}

/* The step projected onto the box (newton.hold_at_edges): a parameter at an edge whose step points
 * out is held, the other takes its own Gauss-Newton step, its variance per unit variance 1/h */
static void hold_at_edges(tr_real alpha, tr_real g, tr_real a_lo, tr_real a_hi, tr_real g_lo, tr_real g_hi,
                          lm_step_t *st) {
    int hold_a = (alpha <= a_lo && st->step_a < R(0.0)) || (alpha >= a_hi && st->step_a > R(0.0));
    int hold_g = (g <= g_lo && st->step_g < R(0.0)) || (g >= g_hi && st->step_g > R(0.0));
    if (hold_a && hold_g) {
        st->step_a = st->step_g = R(0.0);
    } else if (hold_g) {
        st->step_a = tr_clamp(-st->b1 / st->h11, R(-0.25), R(0.25));
        st->step_g = R(0.0);
        st->det = st->h11;
        st->h22 = R(1.0);
    } else if (hold_a) {
        st->step_g = tr_clamp(-st->b2 / st->h22, R(-0.5), R(0.5));
        st->step_a = R(0.0);
        st->det = st->h22;
        st->h11 = R(1.0);
    }
}

/* newton.step_is_small, multiplied out as there */
static int step_is_small(tr_real step, tr_real last, tr_real step_var, tr_real h, tr_real det) {
    tr_real a = R_FABS(step);
    if (a <= R(TM_TABLE_FIT_POLISH_TOL)) return 1;
    if (!(det > R(0.0))) return 0;
    tr_real lim = step_var * h, d2 = a * a * det;
    return d2 <= lim || (a <= R(TM_STEP_RATIO) * last && d2 * a * a <= lim * last * last);
}

/* First-order stds of α and g (newton.propagate) from the intensities' variances and a further
 * variance of σt that (α, g) follow; infinite where the (α, g) block is singular */
static void propagate(const evaluation_t *e, tr_real dIc_dsigma, tr_real var_b, tr_real var_w, tr_real sd_c,
                      tr_real var_s_extra, tr_real *std_a, tr_real *std_g) {
    tr_real ds = sd_c / dIc_dsigma, var_s = ds * ds + var_s_extra;
    tr_real a = e->J[0][0], b = e->J[0][2], c = e->J[1][0], d = e->J[1][2];
    tr_real inv_det = R(1.0) / (a * d - b * c);
    tr_real i00 = d * inv_det, i01 = -b * inv_det, i10 = -c * inv_det, i11 = a * inv_det;
    tr_real c00 = var_b + e->J[0][1] * e->J[0][1] * var_s, c11 = var_w + e->J[1][1] * e->J[1][1] * var_s;
    tr_real c01 = e->J[0][1] * e->J[1][1] * var_s;
    tr_real va = i00 * (i00 * c00 + i01 * c01) + i01 * (i00 * c01 + i01 * c11);
    tr_real vg = i10 * (i10 * c00 + i11 * c01) + i11 * (i10 * c01 + i11 * c11);
    tr_real sa = R_SQRT(R_FABS(va)), sg = R_SQRT(R_FABS(vg));
    *std_a = isnan(sa) ? (tr_real)INFINITY : sa;
    *std_g = isnan(sg) ? (tr_real)INFINITY : sg;
}

/* σt from I_c: the stable root of b·I·x² + a·x − I = 0, x = exp(−σt ℓ); NaN outside (0, t_valid] */
static tr_real beer_lambert(const tr_table *t, tr_real I_c) {
    if (!(isfinite(I_c) && I_c > R(0.0) && I_c <= t->t_valid)) return (tr_real)NAN;
    tr_real a = t->stack_a, x = R(2.0) * I_c / (a + R_SQRT(a * a + R(4.0) * t->stack_b * I_c * I_c));
    tr_real sigma = -R_LOG(x) / t->thickness_mm;
    return sigma > R(0.0) ? sigma : R(0.0);
}

/* ∂I_c/∂σt (collimated.collimated_derivative) */
static tr_real collimated_derivative(const tr_table *t, tr_real sigma_t) {
    tr_real x = R_EXP(-sigma_t * t->thickness_mm), bx2 = t->stack_b * x * x;
    return -t->thickness_mm * t->stack_a * x * (R(1.0) + bx2) / ((R(1.0) - bx2) * (R(1.0) - bx2));
}

static tr_real sanitize(tr_real x, tr_real fill) { return isfinite(x) ? tr_clamp(x, R(0.0), R(1.0)) : fill; }

/* One bin: out = (α, σt, g); returns its flags */
static uint16_t fit_bin(const tr_table *t, tr_real Ib, tr_real Iw, tr_real Ic, tr_real Rb, tr_real Rw, tr_real out[3]) {
    const tr_real tol = R(TM_TABLE_FIT_INPUT_TOLERANCE), nan = (tr_real)NAN;
    unsigned fl = 0;
    /* input flags and sanitized stand-ins: unusable bins are fitted on harmless values and blanked */
    int finite = isfinite(Ib) && isfinite(Iw) && isfinite(Ic) && isfinite(Rb) && isfinite(Rw);
    if (!finite) fl |= TM_FLAG_NONFINITE_INPUT;
    if (Ib < -tol || Iw < -tol || Ic < -tol) fl |= TM_FLAG_NEGATIVE_INPUT;
    if (Ib > R(1.0) + tol || Iw > R(1.0) + tol || Ic > R(1.0) + tol) fl |= TM_FLAG_ABOVE_ONE;
    if (finite && !(Rb >= R(0.0) && Rb < Rw && Rw <= R(1.0))) fl |= TM_FLAG_BAD_BACKGROUND;
    if (finite && Ib >= Iw) fl |= TM_FLAG_BLACK_NOT_BELOW_WHITE;
    const int usable = !(fl & UNUSABLE);
    const tr_real ib = sanitize(Ib, R(0.0)), iw = sanitize(Iw, R(1.0)), ic = sanitize(Ic, R(1.0));
    const tr_real rb = usable ? Rb : t->rho_b_ref, rw = usable ? Rw : t->rho_w_ref;
    const tr_real floor_ = R(TM_TABLE_FIT_IC_FLOOR);
    if (usable && ic < floor_) fl |= TM_FLAG_IC_BELOW_FLOOR;
    /* under the floor, the floor's σt (a lower bound); above T(σt = 0), σt = 0 */
    tr_real sigma_t = beer_lambert(t, tr_clamp(ic, floor_, t->t_max));
    const tr_real ls_lo = R(t->log_sigma_t[0]), ls_hi = R(t->log_sigma_t[t->ns - 1]);
    if (usable && (sigma_t < R_EXP(ls_lo) * R(1.0 - 1e-6) || sigma_t > R_EXP(ls_hi) * R(1.0 + 1e-6)))
        fl |= TM_FLAG_OUTSIDE_MAP;
    /* the noise model σ_I = noise_rel·I + noise_abs, the map's MC std-error beside it */
    const tr_real sb = R(TM_TABLE_FIT_NOISE_REL) * ib + R(TM_TABLE_FIT_NOISE_ABS);
    const tr_real sw = R(TM_TABLE_FIT_NOISE_REL) * iw + R(TM_TABLE_FIT_NOISE_ABS);
    const tr_real sc = R(TM_TABLE_FIT_NOISE_REL) * ic + R(TM_TABLE_FIT_NOISE_ABS);
    const tr_real mc2 = t->mc_stderr * t->mc_stderr, kappa = R(TM_TABLE_FIT_POLISH_TOL_STD);
    const tr_real step_var = kappa * kappa * (R(0.5) * (sb * sb + sw * sw + R(2.0) * mc2));
    /* σt's place on the model, fixed while (α, g) are solved (ForwardGrid.sigma_cell) */
    tr_real ls = R_LOG(sigma_t);
    ls = isnan(ls) ? ls_lo : tr_clamp(ls, ls_lo, ls_hi);
    const tr_real s_cell = R_EXP(ls);
    tr_sigma_slice slice;
    tr_sigma_slice_init(t, ls, &slice);
    const tr_real a_lo = R(t->alpha[0]), a_hi = R(t->alpha[t->na - 1]), g_lo = R(t->g[0]), g_hi = R(t->g[t->ng - 1]);
    tr_real alpha, g;
    tr_inverse_guess(t, ls, ib, iw, &alpha, &g);
    alpha = tr_clamp(alpha, a_lo, a_hi);
    g = tr_clamp(g, g_lo, g_hi);
    /* the polish; a bin whose last step was small keeps that step's Jacobian and its residuals
     * carried along the step taken (newton.solve_alpha_g: the compact model has no cells to leave) */
    evaluation_t e;
    int evaluated = 0;
    tr_real last_a = R(0.0), last_g = R(0.0), residual2 = R(0.0);
    for (int it = 0; it < TM_TABLE_FIT_POLISH; it++) {
        evaluate(t, alpha, &slice, s_cell, g, ib, iw, rb, rw, &e);
        lm_step_t st = lm_step(e.J[0][0], e.J[0][2], e.J[1][0], e.J[1][2], e.residual[0], e.residual[1]);
        hold_at_edges(alpha, g, a_lo, a_hi, g_lo, g_hi, &st);
        tr_real alpha0 = alpha, g0 = g;
        alpha = tr_clamp(alpha + st.step_a, a_lo, a_hi);
        g = tr_clamp(g + st.step_g, g_lo, g_hi);
        /* var(α) = σ²·h22/det, var(g) = σ²·h11/det */
        int small = step_is_small(st.step_a, last_a, step_var, st.h22, st.det) &&
                    step_is_small(st.step_g, last_g, step_var, st.h11, st.det);
        last_a = R_FABS(st.step_a);
        last_g = R_FABS(st.step_g);
        if (small) {
            tr_real da = alpha - alpha0, dg = g - g0;
            tr_real r0 = e.residual[0] + e.J[0][0] * da + e.J[0][2] * dg;
            tr_real r1 = e.residual[1] + e.J[1][0] * da + e.J[1][2] * dg;
            residual2 = r0 * r0 + r1 * r1;
            evaluated = 1;
            break;
        }
        if (alpha == alpha0 && g == g0) {
            /* the clamps held both where they were (a solution outside the map's box): every step
             * from here would evaluate this point again and take this step again, so the loop's end
             * is known now — a small step on the next iteration (its last step this one), else the
             * evaluation after the loop, which would be this one */
            if (it + 1 < TM_TABLE_FIT_POLISH && step_is_small(st.step_a, last_a, step_var, st.h22, st.det) &&
                step_is_small(st.step_g, last_g, step_var, st.h11, st.det)) {
                tr_real r0 = e.residual[0] + e.J[0][0] * R(0.0) + e.J[0][2] * R(0.0);
                tr_real r1 = e.residual[1] + e.J[1][0] * R(0.0) + e.J[1][2] * R(0.0);
                residual2 = r0 * r0 + r1 * r1;
            } else {
                residual2 = e.residual[0] * e.residual[0] + e.residual[1] * e.residual[1];
            }
            evaluated = 1;
            break;
        }
    }
    if (!evaluated) {
        evaluate(t, alpha, &slice, s_cell, g, ib, iw, rb, rw, &e);
        residual2 = e.residual[0] * e.residual[0] + e.residual[1] * e.residual[1];
    }
    const tr_real dIc = collimated_derivative(t, s_cell), residual = R_SQRT(residual2);
    /* the light scattered into I_c's aperture: σt up by L/ℓ, (α, g) following to first order */
    tr_real ds_in = R(0.0);
    if (usable && !(fl & (TM_FLAG_IC_BELOW_FLOOR | TM_FLAG_OUTSIDE_MAP))) {
        tr_inscatter_cells cells;
        tr_inscatter_cells_init(t, alpha, g, &cells);
        tr_real s0 = sigma_t, L = tr_inscatter_log1p_at(t, &cells, s0);
        tr_real s = s0 + L / t->thickness_mm;
        if (L > R(TM_INSCATTER_ONCE)) s = s0 + tr_inscatter_log1p_at(t, &cells, s) / t->thickness_mm;
        if (L > R(0.0) && s - s0 > R(0.0)) {
            ds_in = s - s0;
            lm_step_t st = lm_step(e.J[0][0], e.J[0][2], e.J[1][0], e.J[1][2], e.J[0][1] * ds_in, e.J[1][1] * ds_in);
            alpha = tr_clamp(alpha + st.step_a, a_lo, a_hi);
            g = tr_clamp(g + st.step_g, g_lo, g_hi);
            sigma_t = s;
        }
    }
    /* flags at the solution (finish.finish) */
    const tr_real tolerance = R(3.0) * R_SQRT(sb * sb + mc2 + sw * sw + mc2) + R(1e-4);
    const int not_conv = !(residual <= tolerance);
    const int at_edge = (g <= g_lo + R(1e-9) && g_lo > R(-1.0 + 1e-6)) || (g >= g_hi - R(1e-9) && g_hi < R(1.0 - 1e-6));
    if (usable && not_conv) fl |= TM_FLAG_NOT_CONVERGED;
    if (usable && not_conv && at_edge) fl |= TM_FLAG_OUTSIDE_MAP;
    alpha = isfinite(alpha) ? tr_clamp(alpha, R(0.0), R(1.0)) : nan;
    g = isfinite(g) ? tr_clamp(g, R(-1.0), R(1.0)) : nan;
    sigma_t = sigma_t > R(0.0) ? sigma_t : (isnan(sigma_t) ? sigma_t : R(0.0));
    tr_real model_b, model_w, std_a, std_g;
    tr_model_variance(t, alpha, ls, g, &model_b, &model_w);
    tr_real ds_rel = R(TM_TABLE_FIT_INSCATTER_REL_STD) * ds_in;
    propagate(&e, dIc, sb * sb + model_b, sw * sw + model_w, sc, ds_rel * ds_rel, &std_a, &std_g);
    if (usable && !(alpha >= R(TM_TABLE_FIT_ALPHA_MIN_G))) {
        fl |= TM_FLAG_G_UNDEFINED;
        g = std_g = nan;
    }
    /* a NaN std_g (g undefined) does not count */
    if (usable && (std_a > R(TM_TABLE_FIT_UNDERDETERMINED_ALPHA_STD) || std_g > R(TM_TABLE_FIT_UNDERDETERMINED_G_STD)))
        fl |= TM_FLAG_UNDERDETERMINED;
    out[0] = usable ? alpha : nan;
    out[1] = usable ? sigma_t : nan;
    out[2] = usable ? g : nan;
    return (uint16_t)fl;
}

int tr_fit_bins(const uint8_t *table, size_t len, const float *in, size_t n, float *out, uint16_t *flags) {
    tr_table t;
    if (tr_table_open(table, len, &t)) return TR_FIT_ERR_TABLE;
    if (n && (!in || !out || !flags)) return TR_FIT_ERR_ARGS;
    for (size_t i = 0; i < n; i++) {
        const float *b = in + i * TR_FIT_IN_PER_BIN;
        tr_real res[3];
        flags[i] = fit_bin(&t, R(b[TR_FIT_IN_I_B]), R(b[TR_FIT_IN_I_W]), R(b[TR_FIT_IN_I_C]), R(b[TR_FIT_IN_RHO_B]),
                           R(b[TR_FIT_IN_RHO_W]), res);
        out[i * TR_FIT_OUT_PER_BIN + TR_FIT_OUT_ALPHA] = (float)res[0];
        out[i * TR_FIT_OUT_PER_BIN + TR_FIT_OUT_SIGMA_T] = (float)res[1];
        out[i * TR_FIT_OUT_PER_BIN + TR_FIT_OUT_G] = (float)res[2];
    }
    return TR_FIT_OK;
}

int tm_table_fit(const uint8_t *table, size_t len, const double *in, size_t n, double *out, int64_t *flags) {
    tr_table t;
    if (tr_table_open(table, len, &t)) return TR_FIT_ERR_TABLE;
    if (n && (!in || !out || !flags)) return TR_FIT_ERR_ARGS;
    for (size_t i = 0; i < n; i++) {
        const double *b = in + i * TR_FIT_IN_PER_BIN;
        tr_real res[3];
        flags[i] = fit_bin(&t, (tr_real)b[TR_FIT_IN_I_B], (tr_real)b[TR_FIT_IN_I_W], (tr_real)b[TR_FIT_IN_I_C],
                           (tr_real)b[TR_FIT_IN_RHO_B], (tr_real)b[TR_FIT_IN_RHO_W], res);
        for (int k = 0; k < 3; k++) out[i * TR_FIT_OUT_PER_BIN + (size_t)k] = (double)res[k];
    }
    return TR_FIT_OK;
}
