/* The whole single-thickness fit: api._fit_one + finish.finish, bin by bin (the module comment of
 * invert_internal.h says where the other stages live). */
#include "invert_internal.h"
#include "invert_abi.h"

uint64_t tm_abi_hash(void) { return TM_ABI_HASH; }

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

/* trimeter.inversion.api._fit_one + finish.finish for one thickness, bin by bin: input flags → σt from
 * I_c (exact inverse of the Fresnel stack; the floor's σt, a lower bound, under ic_floor) → (α, g)
 * by guess + polish → flags for not converged / outside the map / g undefined → first-order stds →
 * NaN for unusable bins. The numpy path in api.py is the reference (same operations, same order);
 * tests/inversion/test_native_kernel.py checks both bin for bin, flags included. */

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
    if (!finite) fl |= TM_FLAG_NONFINITE_INPUT;
    if (Ib < -tol || Iw < -tol || Ic < -tol) fl |= TM_FLAG_NEGATIVE_INPUT;
    if (Ib > 1 + tol || Iw > 1 + tol || Ic > 1 + tol) fl |= TM_FLAG_ABOVE_ONE;
    if (finite && !(Rb >= 0 && Rb < Rw && Rw <= 1)) fl |= TM_FLAG_BAD_BACKGROUND;
    if (finite && Ib >= Iw) fl |= TM_FLAG_BLACK_NOT_BELOW_WHITE;
    int usable = !(fl & TM_FLAGS_UNUSABLE);
    *ib = sanitize(Ib, 0.0);
    *iw = sanitize(Iw, 1.0);
    double ic = sanitize(Ic, 1.0);
    *rb = usable ? Rb : o->ref_rho_b;
    *rw = usable ? Rw : o->ref_rho_w;
    if (usable && ic < o->ic_floor) fl |= TM_FLAG_IC_BELOW_FLOOR;
    /* fmin(fmax(ic, floor), t_max) without libm's calls: ic is finite here */
    double ic_in = ic > o->ic_floor ? ic : o->ic_floor;
    double s = beer_lambert(f, o, ic_in < o->t_max ? ic_in : o->t_max);
    int in_range = isfinite(Ic) && Ic >= o->ic_floor && Ic <= o->t_max;
    *sigma_beer = in_range ? s : beer_lambert(f, o, Ic);
    if (usable && (s < bounds.lo || s > bounds.hi)) fl |= TM_FLAG_OUTSIDE_MAP;
    *sigma_t = s;
    return fl;
}

/* The first half of a fit: input flags, σt from I_c and the Beer-Lambert column into `outputs`, the
 * sanitized inputs and σt cells into `scratch`; with `features` (n × 5 float32, else NULL) also the
 * MLP's input (trimeter.inversion.mlp.features; ln σt clamped to [log_lo, log_hi]), so that the
 * network's guess can go to tm_fit_solve without preparing the bins twice. The output rows are `stride`
 * apart: n for tm_fit_prepare, a larger block's width where these n bins are a part of its bins. */
void tmi_fit_prepare(const tm_forward_grid *f, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w,
                     const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, void *scratch,
                     double *outputs, size_t stride, double log_lo, double log_hi, float *features) {
    fit_scratch_t sc = carve_scratch(scratch, n);
    const tm_fit_outputs o_ = outputs_in(outputs, stride), *out = &o_;
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

static double correct_inscatter(const tm_forward_grid *f, const sigma_cell_t *c, const double *Ji, double *alpha,
                                double *sigma_t, double *g) {
    double wa, wg, s0 = *sigma_t;
    int ia = alpha_near(f, *alpha, c->ia, &wa), ig = g_near(f, *g, c->ig, &wg);
    double L = tmi_inscatter_log1p(f, ia, wa, s0, ig, wg);
    if (!(L > 0.0)) return 0.0; /* nothing scattered in */
    double s = s0 + L / f->thickness_mm;
    /* L again at the moved σt: it changes σt by ~L·dL/dτ, below 1e-6 of σt where L ≤ TM_INSCATTER_ONCE */
    if (L > TM_INSCATTER_ONCE) s = s0 + tmi_inscatter_log1p(f, ia, wa, s, ig, wg) / f->thickness_mm;
    double ds = s - s0;
    if (!(ds > 0.0)) return 0.0;
    /* the residual the σt move alone would leave in (I_b, I_w), taken out by one step in (α, g) */
    lm_step_t st = lm_step(Ji[0], Ji[2], Ji[3], Ji[5], Ji[1] * ds, Ji[4] * ds);
    *alpha = clampd(*alpha + st.step_a, f->alpha_lo, f->alpha_hi);
    *g = clampd(*g + st.step_g, f->g_lo, f->g_hi);
    *sigma_t = s;
    return ds;
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

/* The check's corrected step for one bin: from (a1, g1), where the linear prediction of the moved
 * intensities (tb, tw) lands, one damped step at the map's evaluation there, clamped to the box
 * (tmi_check_step4 does four bins at once, the same operations lane by lane). */
static inline void check_step(const tm_forward_grid *f, sigma_cell_t *cell, double a1, double g1, double tb, double tw,
                              double rho_b, double rho_w, double *a2, double *g2) {
    abc_t e;
    coefficients(f, cell, a1, g1, 0, &e);
    double gb, kb, gw, kw;
    double rb = diffuse(e.v, rho_b, &gb, &kb) - tb;
    double rw = diffuse(e.v, rho_w, &gw, &kw) - tw;
    lm_step_t st = lm_step(directional(gb, kb, e.da), directional(gb, kb, e.dg), directional(gw, kw, e.da),
                           directional(gw, kw, e.dg), rb, rw);
    *a2 = clampd(a1 + st.step_a, f->alpha_lo, f->alpha_hi);
    *g2 = clampd(g1 + st.step_g, f->g_lo, f->g_hi);
}

/* One bin's move as the check takes it: the prediction (a1, g1, its offset da, dg) and the moved
 * intensities (tb, tw). */
typedef struct { double a1, g1, da, dg, tb, tw; } check_move_t;

static inline check_move_t check_move(const tm_forward_grid *f, const check_t *k, int move, double sigmas, double I_b,
                                      double I_w) {
    check_move_t mv;
    int on_b = move < 2;
    double dI = (move & 1 ? -sigmas : sigmas) * (on_b ? k->move_b : k->move_w);
    check_target(f, k, on_b, dI, &mv.da, &mv.dg, &mv.a1, &mv.g1);
    mv.tb = on_b ? I_b + dI : I_b;
    mv.tw = on_b ? I_w : I_w + dI;
    return mv;
}

static inline int check_holds(const check_t *k, double da, double dg, double a2, double g2) {
    return fabs(a2 - k->alpha - da) <= k->limit_a && fabs(g2 - k->g - dg) <= k->limit_g;
}

/* Bins per block of the check: each block's moved cells are found and prefetched in one pass before
 * they are evaluated (the moved cells, a few σ from the solution's, are mostly not in cache, and a
 * pass without dependent loads keeps many of those misses in flight); its arrays take ~1 KB of stack. */
#define CHECK_BLOCK 16

/* The check for the bins listed in idx (m of them; checks[j] is idx[j]'s), move by move, a block of bins
 * at a time: the moves' cells prefetched, then evaluated four bins per step with AVX2 where the polish
 * uses it. A bin that failed a move is not moved again. Sets TM_FLAG_STD_APPROXIMATE in flags. */
static void check_first_order(const tm_forward_grid *f, size_t m, const uint32_t *idx, const check_t *checks,
                              sigma_cell_t *cells, const double *I_b, const double *I_w, const double *rho_b,
                              const double *rho_w, double sigmas, int64_t *flags) {
    for (int move = 0; move < 4; move++) {
        for (size_t j0 = 0; j0 < m; j0 += CHECK_BLOCK) {
            uint32_t lane[CHECK_BLOCK], slot[CHECK_BLOCK];
            double a1[CHECK_BLOCK], g1[CHECK_BLOCK], tb[CHECK_BLOCK], tw[CHECK_BLOCK], a2[CHECK_BLOCK], g2[CHECK_BLOCK];
            double da[CHECK_BLOCK], dg[CHECK_BLOCK];
            size_t k = 0, j1 = m - j0 < CHECK_BLOCK ? m : j0 + CHECK_BLOCK;
            for (size_t j = j0; j < j1; j++) {
                uint32_t i = idx[j];
                if (flags[i] & TM_FLAG_STD_APPROXIMATE) continue;
                check_move_t mv = check_move(f, &checks[j], move, sigmas, I_b[i], I_w[i]);
                a1[k] = mv.a1;
                g1[k] = mv.g1;
                tb[k] = mv.tb;
                tw[k] = mv.tw;
                da[k] = mv.da;
                dg[k] = mv.dg;
                prefetch_cell(f, &cells[i], a1[k], g1[k]);
                slot[k] = (uint32_t)j;
                lane[k++] = i;
            }
            size_t l = 0;
#ifdef TM_SIMD
            if (tmi_use_simd())
                for (; l + 4 <= k; l += 4)
                    tmi_check_step4(f, cells, lane + l, a1 + l, g1 + l, tb + l, tw + l, rho_b, rho_w, a2 + l, g2 + l);
#endif
            for (; l < k; l++) {
                uint32_t i = lane[l];
                check_step(f, &cells[i], a1[l], g1[l], tb[l], tw[l], rho_b[i], rho_w[i], &a2[l], &g2[l]);
            }
            for (l = 0; l < k; l++)
                if (!check_holds(&checks[slot[l]], da[l], dg[l], a2[l], g2[l])) flags[lane[l]] |= TM_FLAG_STD_APPROXIMATE;
        }
    }
}

/* How many bins ahead the per-bin pass prefetches its table cells (tmi_prefetch_finish) */
#define FINISH_AHEAD 8

/* The finish's arithmetic for bin i, after its table reads (fin[i]): flags for not converged / outside
 * the map / g undefined / underdetermined, first-order stds, NaN for unusable bins, all written to the
 * outputs; returns whether the bin's stds go to check_first_order (tmi_finish4 does four bins at once,
 * the same operations lane by lane). */
static int finish_bin(const finish_ctx_t *c, size_t i) {
    const tm_forward_grid *f = c->f;
    const tm_fit_options *o = c->o;
    const tm_fit_outputs *out = &c->out;
    const finish_t *b = &c->fin[i];
    const double *Ji = b->Ji;
    int64_t fl = out->flags[i];
    int usable = !(fl & TM_FLAGS_UNUSABLE);
    double alpha = out->alpha[i], g = out->g[i];
    /* variances, not stds: only their sums are needed (sqrt(x² + y²), not hypot: these are small
     * positive numbers, nothing to guard, and hypot is slower) */
    double var_b = c->var_b[i] + c->mc2, var_w = c->var_w[i] + c->mc2;
    double tolerance = 3.0 * sqrt(var_b + var_w) + 1e-4;
    int not_conv = !(b->residual2 <= tolerance * tolerance); /* |residual| ≤ tolerance, squared */
    int at_edge = (g <= f->g_lo + 1e-9 && c->g_lo_is_edge) || (g >= f->g_hi - 1e-9 && c->g_hi_is_edge);
    if (usable && not_conv) fl |= TM_FLAG_NOT_CONVERGED;
    if (usable && not_conv && at_edge) fl |= TM_FLAG_OUTSIDE_MAP;
    double a = isfinite(alpha) ? clampd(alpha, 0.0, 1.0) : NAN;
    double gg = isfinite(g) ? clampd(g, -1.0, 1.0) : NAN;
    double sa, ss, sg, ds_rel = o->inscatter_rel_std * b->ds_in;
    propagate_one(Ji, c->var_b[i] + b->model_b, c->var_w[i] + b->model_w, c->sd_c[i], ds_rel * ds_rel, &sa, &ss, &sg);
    double thick = o->thickness_rel_std * out->sigma_t[i];
    ss = sqrt(ss * ss + thick * thick);
    if (fl & TM_FLAG_IC_BELOW_FLOOR) ss = INFINITY;
    if (usable && !(a >= o->alpha_min_g)) {
        fl |= TM_FLAG_G_UNDEFINED;
        gg = sg = NAN;
    }
    /* UNDERDETERMINED is the map's conditioning at no less than the instrument's noise model: a
     * capture's frame scatter alone misses drift and calibration error, and one quiet capture
     * must not make α and g look told apart where a realistic noise leaves them not */
    double ua = sa, us = ss, ug = sg;
    if (c->cond_var_b[i] != c->var_b[i] || c->cond_var_w[i] != c->var_w[i] || c->cond_sd_c[i] != c->sd_c[i]) {
        propagate_one(Ji, c->cond_var_b[i] + b->model_b, c->cond_var_w[i] + b->model_w, c->cond_sd_c[i],
                      ds_rel * ds_rel, &ua, &us, &ug);
        if (isnan(gg)) ug = NAN;
    }
    if (usable && (ua > o->underdetermined_alpha_std || ug > o->underdetermined_g_std)) fl |= TM_FLAG_UNDERDETERMINED;
    int check = !(fl & TM_FLAGS_STD_CHECK_SKIP) && isfinite(sa) && isfinite(sg) &&
                (sa > o->std_check_alpha || sg > o->std_check_g);
    if (!usable) {
        a = gg = sa = ss = sg = ua = ug = NAN;
        out->sigma_t[i] = out->sigma_t_beer[i] = NAN;
    }
    out->alpha[i] = a;
    out->g[i] = gg;
    out->alpha_std[i] = sa;
    out->sigma_t_std[i] = ss;
    out->g_std[i] = sg;
    out->cond_alpha_std[i] = ua;
    out->cond_g_std[i] = ug;
    out->flags[i] = fl;
    return check;
}

/* Bin i's state for check_first_order, from its finish (its stds as finish_bin wrote them) */
static void add_check(const finish_ctx_t *c, size_t i, check_t *k, uint32_t *slot) {
    const tm_fit_options *o = c->o;
    const finish_t *b = &c->fin[i];
    k->alpha = b->solved_alpha;
    k->g = b->solved_g;
    k->j11 = b->Ji[0];
    k->j12 = b->Ji[2];
    k->j21 = b->Ji[3];
    k->j22 = b->Ji[5];
    k->move_b = sqrt(c->var_b[i] + b->model_b);
    k->move_w = sqrt(c->var_w[i] + b->model_w);
    k->limit_a = o->std_check_tol * o->std_check_sigmas * c->out.alpha_std[i];
    k->limit_g = o->std_check_tol * o->std_check_sigmas * c->out.g_std[i];
    *slot = (uint32_t)i;
}

/* The second half: the initial (α, g) from alpha0/g0 (the MLP's) or, where those are NULL or not
 * finite (a broken network), from `table` (without one: the middle of the map's box); the polish,
 * then flags for not converged / outside the map / g undefined / underdetermined, first-order stds
 * and NaN for unusable bins, into output rows `stride` apart (as tmi_fit_prepare's). Returns the number
 * of Newton steps taken (≥ 0), -1 on a malformed grid or a missing guess. */
long long tmi_fit_solve(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n,
                        const double *alpha0, const double *g0, void *scratch, double *outputs, size_t stride) {
    if (!grid_ok(f, table) || (!alpha0 && !table) || (alpha0 && !g0) || n > UINT32_MAX) return -1;
    fit_scratch_t sc = carve_scratch(scratch, n);
    const tm_fit_outputs o_ = outputs_in(outputs, stride), *out = &o_;
    const double *ib = sc.ib, *iw = sc.iw, *rb = sc.rb, *rw = sc.rw;
    sigma_cell_t *cells = sc.cells;
    const double mc2 = o->mc_stderr * o->mc_stderr;
    double *alpha = out->alpha, *g = out->g, *sigma_t = out->sigma_t;
    if (!alpha0) tmi_initial_guesses(table, n, cells, ib, iw, alpha, g); /* table is there (checked above) */
    for (size_t i = 0; i < n; i++) {
        double a = alpha0 ? alpha0[i] : alpha[i], gg = alpha0 ? g0[i] : g[i];
        if (alpha0 && !(isfinite(a) && isfinite(gg))) {
            a = 0.5 * (f->alpha_lo + f->alpha_hi);
            gg = 0.5 * (f->g_lo + f->g_hi);
            if (table) tmi_initial_guess(table, cells[i].log_sigma_t, ib[i], iw[i], &a, &gg);
        }
        alpha[i] = clampd(a, f->alpha_lo, f->alpha_hi);
        g[i] = clampd(gg, f->g_lo, f->g_hi);
    }
    tmi_prefetch_cells(f, n, cells, alpha, g);
    size_t steps = tmi_polish(f, n, cells, ib, iw, rb, rw, o->iterations, o->step_tol, sc.step_var, alpha, g, sc.active,
                          sc.evals);
    const int g_lo_is_edge = f->g_lo > -1 + 1e-6, g_hi_is_edge = f->g_hi < 1 - 1e-6;
    /* bins for check_first_order, listed in sc.active (the polish is done with it), their states side by
     * side in sc.checks: only those bins' (a few of them) are written */
    size_t checked = 0;
    for (size_t i = 0; i < FINISH_AHEAD && i < n; i++) tmi_prefetch_finish(f, &cells[i], sigma_t[i]);
    /* the finish in two passes: each bin's table reads (Jacobian, in-scattering, model error) into its
     * finish_t, then the arithmetic, which four lanes take at once */
    finish_t *fin = sc.finish;
    for (size_t i = 0; i < n; i++) {
        if (i + FINISH_AHEAD < n) tmi_prefetch_finish(f, &cells[i + FINISH_AHEAD], sigma_t[i + FINISH_AHEAD]);
        finish_t *b = &fin[i];
        int64_t fl = out->flags[i];
        b->residual2 = tmi_final_residual2_and_jacobian(f, &cells[i], &sc.evals[i], alpha[i], g[i], ib[i], iw[i],
                                                        rb[i], rw[i], b->Ji);
        b->solved_alpha = alpha[i];
        b->solved_g = g[i];
        b->ds_in = 0.0;
        if (f->inscatter_L && !(fl & (TM_FLAGS_UNUSABLE | TM_FLAG_IC_BELOW_FLOOR | TM_FLAG_OUTSIDE_MAP)))
            b->ds_in = correct_inscatter(f, &cells[i], b->Ji, &alpha[i], &sigma_t[i], &g[i]);
        /* the map's own error at the solution, in place of its median MC std-error where the grid has it */
        b->model_b = b->model_w = mc2;
        if (f->model_var) tmi_model_variance(f, &cells[i], alpha[i], g[i], &b->model_b, &b->model_w);
    }
    const finish_ctx_t ctx = {f, o, fin, sc.var_b, sc.var_w, sc.sd_c, sc.cond_var_b, sc.cond_var_w, sc.cond_sd_c,
                              *out, mc2, g_lo_is_edge, g_hi_is_edge};
    for (size_t i = 0; i < n;) {
        int lanes = 1, check;
#ifdef TM_SIMD
        if (i + 4 <= n && tmi_use_simd()) {
            check = tmi_finish4(&ctx, i);
            lanes = 4;
        } else
#endif
            check = finish_bin(&ctx, i);
        for (int l = 0; l < lanes; l++)
            if (check >> l & 1) {
                add_check(&ctx, i + (size_t)l, &sc.checks[checked], &sc.active[checked]);
                checked++;
            }
        i += (size_t)lanes;
    }
    check_first_order(f, checked, sc.active, sc.checks, cells, ib, iw, rb, rw, o->std_check_sigmas, out->flags);
    return (long long)steps;
}

void tm_fit_prepare(const tm_forward_grid *f, const tm_fit_options *o, size_t n, const double *I_b, const double *I_w,
                    const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in, void *scratch,
                    double *outputs, double log_lo, double log_hi, float *features) {
    tmi_fit_prepare(f, o, n, I_b, I_w, I_c, rho_b, rho_w, sd_in, scratch, outputs, n, log_lo, log_hi, features);
}

long long tm_fit_solve(const tm_forward_grid *f, const tm_inverse_table *table, const tm_fit_options *o, size_t n,
                       const double *alpha0, const double *g0, void *scratch, double *outputs) {
    return tmi_fit_solve(f, table, o, n, alpha0, g0, scratch, outputs, n);
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

size_t tm_fit_scratch_size(size_t n) {
    return (n ? n : 1) *
           (11 * sizeof(double) + sizeof(sigma_cell_t) + sizeof(final_eval_t) + sizeof(check_t) + sizeof(finish_t) +
            sizeof(uint32_t));
}


/* finish._weighted for one column of one bin over k thicknesses (v, s: a value and its std per thickness,
 * `stride` apart): the inverse-variance mean and its std; where no std is usable, the plain mean of
 * the finite values and the smallest of their stds; NaN where no value is finite. As numpy reduces:
 * sums from +0 (so even a zero's sign agrees), the smallest from the first thickness's (looked for only
 * in that fallback, a rare case). v2 (or NULL): a second column with the same stds, whose mean alone
 * goes to *value2 (the divisions shared). Inlined into tm_combine's loop, where k = 2 is unrolled. */
static inline __attribute__((always_inline)) void weighted(size_t k, size_t stride, const double *v, const double *v2,
                                                           const double *s, double *value, double *std,
                                                           double *value2) {
    double wsum = 0.0, wvsum = 0.0, vsum = 0.0, wsum2 = 0.0, wvsum2 = 0.0, vsum2 = 0.0;
    size_t count = 0, count2 = 0;
    for (size_t j = 0; j < k; j++) {
        double vj = v[j * stride], sj = s[j * stride];
        int finite = isfinite(vj), usable_std = sj > 0.0 && sj < INFINITY;
        double inv = 1.0 / (sj * sj);
        double w = finite && usable_std ? inv : 0.0, v0 = finite ? vj : 0.0;
        wsum += w;
        wvsum += v0 * w;
        vsum += v0;
        count += (size_t)finite;
        if (v2) {
            double uj = v2[j * stride];
            int finite2 = isfinite(uj);
            double w2 = finite2 && usable_std ? inv : 0.0, u0 = finite2 ? uj : 0.0;
            wsum2 += w2;
            wvsum2 += u0 * w2;
            vsum2 += u0;
            count2 += (size_t)finite2;
        }
    }
    if (wsum > 0.0) {
        *value = wvsum / wsum;
        *std = 1.0 / sqrt(wsum);
    } else {
        double smallest = 0.0;
        for (size_t j = 0; j < k; j++) {
            double least = isfinite(v[j * stride]) ? s[j * stride] : INFINITY;
            smallest = j ? fmin(smallest, least) : least; /* fmin: a NaN std does not win */
        }
        *value = count ? vsum / (double)count : NAN;
        *std = count ? smallest : NAN;
    }
    if (v2) *value2 = wsum2 > 0.0 ? wvsum2 / wsum2 : (count2 ? vsum2 / (double)count2 : NAN);
}

/* Whether rows a and b (k thicknesses, `stride` apart) hold the same stds bit for bit. */
static int same_stds(size_t k, size_t stride, const double *a, const double *b) {
    for (size_t j = 0; j < k; j++)
        if (__builtin_memcmp(a + j * stride, b + j * stride, sizeof(double))) return 0;
    return 1;
}

/* tm_combine for bin i; inlined twice, so that the common two thicknesses run with k a constant */
static inline __attribute__((always_inline)) void combine_bin(size_t k, size_t n, size_t i, const double *fits,
                                                              double underdetermined_alpha_std,
                                                              double underdetermined_g_std, double disagree_sigmas,
                                                              const tm_fit_outputs out) {
    const size_t stride = (size_t)TM_ROW_COUNT * n; /* from one thickness's block to the next */
    static const int value_rows[3] = {TM_ROW_ALPHA, TM_ROW_SIGMA_T, TM_ROW_G};
    static const int std_rows[3] = {TM_ROW_ALPHA_STD, TM_ROW_SIGMA_T_STD, TM_ROW_G_STD};
#define ROW(p, r) ((p) + (size_t)(r) * n)
    {
        const double *bin = fits + i;
        int64_t fl = 0, all_unusable = 1;
        for (size_t j = 0; j < k; j++) {
            int64_t fj = ((const int64_t *)ROW(bin + j * stride, TM_ROW_FLAGS))[0];
            fl |= fj;
            all_unusable &= (fj & TM_FLAGS_UNUSABLE) != 0;
        }
        /* a thickness whose bin was unusable drops out; UNUSABLE stays only if all dropped */
        if (!all_unusable) fl &= ~(int64_t)TM_FLAGS_UNUSABLE;
        fl &= ~(int64_t)(TM_FLAG_UNDERDETERMINED | TM_FLAG_STD_APPROXIMATE); /* judged again below */
        double value[3], std[3], beer = NAN; /* set by the σt column's weighted() */
        weighted(k, stride, ROW(bin, TM_ROW_ALPHA), NULL, ROW(bin, TM_ROW_ALPHA_STD), &value[0], &std[0], NULL);
        /* the Beer-Lambert column takes σt's std */
        weighted(k, stride, ROW(bin, TM_ROW_SIGMA_T), ROW(bin, TM_ROW_SIGMA_T_BEER), ROW(bin, TM_ROW_SIGMA_T_STD),
                 &value[1], &std[1], &beer);
        weighted(k, stride, ROW(bin, TM_ROW_G), NULL, ROW(bin, TM_ROW_G_STD), &value[2], &std[2], NULL);
        int approx = 0, disagree = 0;
        for (size_t j = 0; j < k; j++) {
            const double *a = bin + j * stride;
            if (((const int64_t *)ROW(a, TM_ROW_FLAGS))[0] & TM_FLAG_STD_APPROXIMATE) {
                /* first order failing at one thickness matters where it carries a quarter of the weight */
                double ra = std[0] / *ROW(a, TM_ROW_ALPHA_STD), rg = std[2] / *ROW(a, TM_ROW_G_STD);
                approx |= ra * ra >= 0.25 || rg * rg >= 0.25;
            }
            for (size_t m = j + 1; m < k; m++)
                for (int c = 0; c < 3; c++) { /* not the consistency column */
                    const double *b = bin + m * stride;
                    double sa = *ROW(a, std_rows[c]), sb = *ROW(b, std_rows[c]);
                    double diff = fabs(*ROW(a, value_rows[c]) - *ROW(b, value_rows[c]));
                    disagree |= diff > disagree_sigmas * sqrt(sa * sa + sb * sb);
                }
        }
        if (approx) fl |= TM_FLAG_STD_APPROXIMATE;
        if (disagree) fl |= TM_FLAG_THICKNESS_DISAGREE;
        /* UNDERDETERMINED on the conditioning stds combined alike (the stds themselves where they are) */
        double cond_a = std[0], cond_g = std[2], unused;
        if (!same_stds(k, stride, ROW(bin, TM_ROW_CONDITIONING_ALPHA_STD), ROW(bin, TM_ROW_ALPHA_STD)))
            weighted(k, stride, ROW(bin, TM_ROW_ALPHA), NULL, ROW(bin, TM_ROW_CONDITIONING_ALPHA_STD), &unused, &cond_a,
                     NULL);
        if (!same_stds(k, stride, ROW(bin, TM_ROW_CONDITIONING_G_STD), ROW(bin, TM_ROW_G_STD)))
            weighted(k, stride, ROW(bin, TM_ROW_G), NULL, ROW(bin, TM_ROW_CONDITIONING_G_STD), &unused, &cond_g, NULL);
        if (!(fl & TM_FLAGS_UNUSABLE) && (cond_a > underdetermined_alpha_std || cond_g > underdetermined_g_std))
            fl |= TM_FLAG_UNDERDETERMINED;
        out.alpha[i] = value[0];
        out.sigma_t[i] = value[1];
        out.g[i] = value[2];
        out.sigma_t_beer[i] = beer;
        out.alpha_std[i] = std[0];
        out.sigma_t_std[i] = std[1];
        out.g_std[i] = std[2];
        out.flags[i] = fl;
        out.cond_alpha_std[i] = cond_a;
        out.cond_g_std[i] = cond_g;
    }
#undef ROW
}

void tm_combine(size_t k, size_t n, const double *fits, double underdetermined_alpha_std, double underdetermined_g_std,
                double disagree_sigmas, double *outputs) {
    const tm_fit_outputs out = outputs_in(outputs, n);
    if (k == 2) {
        size_t i = 0;
#ifdef TM_SIMD
        if (tmi_use_simd())
            for (; i + 4 <= n; i += 4)
                tmi_combine2_4(n, i, fits, underdetermined_alpha_std, underdetermined_g_std, disagree_sigmas, outputs);
#endif
        for (; i < n; i++)
            combine_bin(2, n, i, fits, underdetermined_alpha_std, underdetermined_g_std, disagree_sigmas, out);
    } else
        for (size_t i = 0; i < n; i++)
            combine_bin(k, n, i, fits, underdetermined_alpha_std, underdetermined_g_std, disagree_sigmas, out);
}
