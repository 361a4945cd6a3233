/* newton_step (newton.c) for four bins at once with AVX2 (x86-64, chosen at run time; elsewhere, or with
 * tm_set_simd(0), the scalar loop runs). The same operations in the same order, lane by lane, and no
 * FMA (-std=c11 does not contract, and the target does not enable it): bit for bit the scalar
 * result, which tests/inversion/test_native_kernel.py checks. Most of a step's arithmetic does not
 * depend on the cell, and here it runs 4 lanes wide. Each lane still walks to its own cell (scalar: short loops), and its
 * 24 polynomial coefficients are loaded as 6 rows of 4 and transposed. */
#include "invert_internal.h"

#ifdef TM_SIMD
#include <immintrin.h>

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
        _mm256_cmp_pd(a, _mm256_mul_pd(_mm256_set1_pd(TM_STEP_RATIO), last), _CMP_LE_OQ),
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

/* coefficients() for the bins idx[0..3] at (alpha[l], g[l]) (walking each lane's cell hints): A, B, C and
 * their derivatives in α and g, and in ln σt where DS is not NULL; term by term as the scalar code */
__attribute__((target("avx2"))) static inline void coefficients4(const tm_forward_grid *f, sigma_cell_t *cells,
                                                                 const uint32_t *idx, const double *alpha,
                                                                 const double *g, v4 *V, v4 *DA, v4 *DG, v4 *DS) {
    const double *P[4];
    double wa[4], wg[4], ws[4], ida[4], idg[4], ids[4];
    for (int l = 0; l < 4; l++) {
        sigma_cell_t *c = &cells[idx[l]];
        int ia = walk_cell(f->alpha, f->inv_da, f->na, alpha[l], &c->ia, &wa[l]);
        int ig = walk_cell(f->g, f->inv_dg, f->ng, g[l], &c->ig, &wg[l]);
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
    for (int c = 0; c < 3; c++) {
        v4 p0 = _mm256_add_pd(T[0 * 3 + c], _mm256_mul_pd(T[2 * 3 + c], Ws));
        v4 p1 = _mm256_add_pd(T[1 * 3 + c], _mm256_mul_pd(T[4 * 3 + c], Ws));
        v4 p3 = _mm256_add_pd(T[3 * 3 + c], _mm256_mul_pd(T[6 * 3 + c], Ws));
        v4 p5 = _mm256_add_pd(T[5 * 3 + c], _mm256_mul_pd(T[7 * 3 + c], Ws));
        V[c] = _mm256_add_pd(_mm256_add_pd(p0, _mm256_mul_pd(p1, Wa)),
                             _mm256_mul_pd(_mm256_add_pd(p3, _mm256_mul_pd(p5, Wa)), Wg));
        DA[c] = _mm256_mul_pd(_mm256_add_pd(p1, _mm256_mul_pd(p5, Wg)), Ida);
        DG[c] = _mm256_mul_pd(_mm256_add_pd(p3, _mm256_mul_pd(p5, Wa)), Idg);
        if (DS)
            DS[c] = _mm256_mul_pd(_mm256_add_pd(_mm256_add_pd(T[2 * 3 + c], _mm256_mul_pd(T[4 * 3 + c], Wa)),
                                                _mm256_mul_pd(_mm256_add_pd(T[6 * 3 + c],
                                                                            _mm256_mul_pd(T[7 * 3 + c], Wa)),
                                                              Wg)),
                                  Ids);
    }
}

/* lm_step() for four lanes: the damped, trust-region-capped step and h11, h22, det */
__attribute__((target("avx2"))) static inline void lm_step4(v4 j11, v4 j12, v4 j21, v4 j22, v4 rb, v4 rw, v4 *step_a,
                                                            v4 *step_g, v4 *h11_out, v4 *h22_out, v4 *det_out,
                                                            v4 *b1_out, v4 *b2_out) {
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
    v4 sa = _mm256_div_pd(_mm256_xor_pd(sign, _mm256_sub_pd(_mm256_mul_pd(h22, b1), _mm256_mul_pd(h12, b2))), det);
    v4 sg = _mm256_div_pd(_mm256_xor_pd(sign, _mm256_sub_pd(_mm256_mul_pd(h11, b2), _mm256_mul_pd(h12, b1))), det);
    *step_a = clamp4(sa, _mm256_set1_pd(-0.25), _mm256_set1_pd(0.25));
    *step_g = clamp4(sg, _mm256_set1_pd(-0.5), _mm256_set1_pd(0.5));
    *h11_out = h11;
    *h22_out = h22;
    *det_out = det;
    *b1_out = b1;
    *b2_out = b2;
}

/* hold_at_edges (invert_internal.h), four lanes: the lanes' choices as blends of the same values */
__attribute__((target("avx2"))) static inline void hold_at_edges4(const tm_forward_grid *f, v4 A0, v4 G0, v4 *step_a,
                                                                  v4 *step_g, v4 *h11, v4 *h22, v4 *det, v4 b1,
                                                                  v4 b2) {
    const v4 zero = _mm256_setzero_pd(), one = _mm256_set1_pd(1.0), sign = _mm256_set1_pd(-0.0);
    v4 hold_a = _mm256_or_pd(_mm256_and_pd(_mm256_cmp_pd(A0, _mm256_set1_pd(f->alpha_lo), _CMP_LE_OQ),
                                           _mm256_cmp_pd(*step_a, zero, _CMP_LT_OQ)),
                             _mm256_and_pd(_mm256_cmp_pd(A0, _mm256_set1_pd(f->alpha_hi), _CMP_GE_OQ),
                                           _mm256_cmp_pd(*step_a, zero, _CMP_GT_OQ)));
    v4 hold_g = _mm256_or_pd(_mm256_and_pd(_mm256_cmp_pd(G0, _mm256_set1_pd(f->g_lo), _CMP_LE_OQ),
                                           _mm256_cmp_pd(*step_g, zero, _CMP_LT_OQ)),
                             _mm256_and_pd(_mm256_cmp_pd(G0, _mm256_set1_pd(f->g_hi), _CMP_GE_OQ),
                                           _mm256_cmp_pd(*step_g, zero, _CMP_GT_OQ)));
    if (_mm256_movemask_pd(_mm256_or_pd(hold_a, hold_g)) == 0) return;
    v4 only_a = _mm256_andnot_pd(hold_g, hold_a), only_g = _mm256_andnot_pd(hold_a, hold_g);
    v4 along_a = clamp4(_mm256_div_pd(_mm256_xor_pd(sign, b1), *h11), _mm256_set1_pd(-0.25), _mm256_set1_pd(0.25));
    v4 along_g = clamp4(_mm256_div_pd(_mm256_xor_pd(sign, b2), *h22), _mm256_set1_pd(-0.5), _mm256_set1_pd(0.5));
    *step_a = _mm256_blendv_pd(_mm256_blendv_pd(*step_a, along_a, only_g), zero, hold_a);
    *step_g = _mm256_blendv_pd(_mm256_blendv_pd(*step_g, along_g, only_a), zero, hold_g);
    *det = _mm256_blendv_pd(_mm256_blendv_pd(*det, *h11, only_g), *h22, only_a);
    *h11 = _mm256_blendv_pd(*h11, one, only_a);
    *h22 = _mm256_blendv_pd(*h22, one, only_g);
}

/* newton_step for the bins idx[0..3]; done[l] as newton_step returns it */
__attribute__((target("avx2"))) void tmi_newton_step4(const tm_forward_grid *f, sigma_cell_t *cells,
                                                      const uint32_t *idx, const double *I_b, const double *I_w,
                                                      const double *rho_b, const double *rho_w, double step_tol,
                                                      const double *step_var, double *alpha, double *g,
                                                      final_eval_t *evals, int *done) {
    double a0[4], g0[4];
    for (int l = 0; l < 4; l++) {
        a0[l] = alpha[idx[l]];
        g0[l] = g[idx[l]];
    }
    v4 V[3], DA[3], DG[3], DS[3];
    coefficients4(f, cells, idx, a0, g0, V, DA, DG, DS);
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
    v4 step_a, step_g, h11, h22, det, b1, b2;
    lm_step4(j11, j12, j21, j22, rb, rw, &step_a, &step_g, &h11, &h22, &det, &b1, &b2);
    const v4 sign = _mm256_set1_pd(-0.0);
    v4 A0 = _mm256_loadu_pd(a0), G0 = _mm256_loadu_pd(g0);
    hold_at_edges4(f, A0, G0, &step_a, &step_g, &h11, &h22, &det, b1, b2);
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

/* pipeline.c's check_step for the bins idx[0..3] at their predictions (a1[l], g1[l]), the moved
 * intensities (tb[l], tw[l]): one damped step from there, clamped to the box, into (a2[l], g2[l]) */
__attribute__((target("avx2"))) void tmi_check_step4(const tm_forward_grid *f, sigma_cell_t *cells, const uint32_t *idx,
                                                     const double *a1, const double *g1, const double *tb,
                                                     const double *tw, const double *rho_b, const double *rho_w,
                                                     double *a2, double *g2) {
    v4 V[3], DA[3], DG[3];
    coefficients4(f, cells, idx, a1, g1, V, DA, DG, NULL);
    const v4 one = _mm256_set1_pd(1.0);
    v4 Rb = set4(rho_b[idx[0]], rho_b[idx[1]], rho_b[idx[2]], rho_b[idx[3]]);
    v4 Rw = set4(rho_w[idx[0]], rho_w[idx[1]], rho_w[idx[2]], rho_w[idx[3]]);
    v4 fb = _mm256_div_pd(Rb, _mm256_sub_pd(one, _mm256_mul_pd(V[2], Rb)));
    v4 fw = _mm256_div_pd(Rw, _mm256_sub_pd(one, _mm256_mul_pd(V[2], Rw)));
    v4 hb = _mm256_mul_pd(_mm256_mul_pd(V[1], fb), fb), hw = _mm256_mul_pd(_mm256_mul_pd(V[1], fw), fw);
    v4 rb = _mm256_sub_pd(_mm256_add_pd(V[0], _mm256_mul_pd(V[1], fb)), _mm256_loadu_pd(tb));
    v4 rw = _mm256_sub_pd(_mm256_add_pd(V[0], _mm256_mul_pd(V[1], fw)), _mm256_loadu_pd(tw));
    v4 step_a, step_g, h11, h22, det, b1, b2;
    lm_step4(directional4(fb, hb, DA[0], DA[1], DA[2]), directional4(fb, hb, DG[0], DG[1], DG[2]),
             directional4(fw, hw, DA[0], DA[1], DA[2]), directional4(fw, hw, DG[0], DG[1], DG[2]), rb, rw, &step_a,
             &step_g, &h11, &h22, &det, &b1, &b2);
    _mm256_storeu_pd(a2, clamp4(_mm256_add_pd(_mm256_loadu_pd(a1), step_a), _mm256_set1_pd(f->alpha_lo),
                                _mm256_set1_pd(f->alpha_hi)));
    _mm256_storeu_pd(g2, clamp4(_mm256_add_pd(_mm256_loadu_pd(g1), step_g), _mm256_set1_pd(f->g_lo),
                                _mm256_set1_pd(f->g_hi)));
}

/* Inverse-variance weights of two thicknesses' values v0, v1 with stds s0, s1 (pipeline.c weighted(),
 * k = 2, lane by lane): w = 1/s² where the value is finite and the std in (0, ∞), else 0. */
__attribute__((target("avx2"))) static inline v4 finite4(v4 x) {
    return _mm256_cmp_pd(_mm256_andnot_pd(_mm256_set1_pd(-0.0), x), _mm256_set1_pd(INFINITY), _CMP_LT_OQ);
}

__attribute__((target("avx2"))) static inline v4 usable_std4(v4 s) {
    return _mm256_and_pd(_mm256_cmp_pd(s, _mm256_setzero_pd(), _CMP_GT_OQ),
                         _mm256_cmp_pd(s, _mm256_set1_pd(INFINITY), _CMP_LT_OQ));
}

/* Σ w·v from +0 as weighted() sums (so a −0 product gives +0), and its division by Σ w */
__attribute__((target("avx2"))) static inline v4 weighted_mean4(v4 v0, v4 w0, v4 v1, v4 w1, v4 wsum) {
    v4 v0z = _mm256_and_pd(finite4(v0), v0), v1z = _mm256_and_pd(finite4(v1), v1);
    v4 sum = _mm256_add_pd(_mm256_add_pd(_mm256_setzero_pd(), _mm256_mul_pd(v0z, w0)), _mm256_mul_pd(v1z, w1));
    return _mm256_div_pd(sum, wsum);
}

#define ROW4(p, r) _mm256_loadu_pd((p) + (size_t)(r) * n)

/* tm_combine for two thicknesses and the bins i .. i+3, where every weight sum is positive (the common
 * case): the same operations as combine_bin's, lane by lane. Writes those bins' outputs and returns a
 * 4-bit mask of the lanes where a sum is not positive, which the caller redoes with combine_bin (the
 * fallback's plain mean). */
int tmi_combine2_4(size_t n, size_t i, const double *fits, double underdetermined_alpha_std,
                   double underdetermined_g_std, double disagree_sigmas, double *outputs)
    __attribute__((target("avx2")));
int tmi_combine2_4(size_t n, size_t i, const double *fits, double underdetermined_alpha_std,
                   double underdetermined_g_std, double disagree_sigmas, double *outputs) {
    const double *a = fits + i, *b = fits + (size_t)TM_ROW_COUNT * n + i;
    double *o = outputs + i;
    const v4 one = _mm256_set1_pd(1.0), quarter = _mm256_set1_pd(0.25), sigmas = _mm256_set1_pd(disagree_sigmas);
    static const int value_rows[3] = {TM_ROW_ALPHA, TM_ROW_SIGMA_T, TM_ROW_G};
    static const int std_rows[3] = {TM_ROW_ALPHA_STD, TM_ROW_SIGMA_T_STD, TM_ROW_G_STD};
    v4 value[3], std[3], fallback = _mm256_setzero_pd(), disagree = _mm256_setzero_pd();
    v4 w0s = _mm256_setzero_pd(), w1s = w0s;
    for (int c = 0; c < 3; c++) {
        v4 va = ROW4(a, value_rows[c]), vb = ROW4(b, value_rows[c]);
        v4 sa = ROW4(a, std_rows[c]), sb = ROW4(b, std_rows[c]);
        v4 inv_a = _mm256_div_pd(one, _mm256_mul_pd(sa, sa)), inv_b = _mm256_div_pd(one, _mm256_mul_pd(sb, sb));
        v4 usable_a = usable_std4(sa), usable_b = usable_std4(sb);
        v4 wa = _mm256_and_pd(_mm256_and_pd(finite4(va), usable_a), inv_a);
        v4 wb = _mm256_and_pd(_mm256_and_pd(finite4(vb), usable_b), inv_b);
        v4 wsum = _mm256_add_pd(wa, wb); /* weighted()'s +0 + wa is wa: wa is +0 or positive */
        fallback = _mm256_or_pd(fallback, _mm256_cmp_pd(wsum, _mm256_setzero_pd(), _CMP_NGT_UQ));
        value[c] = weighted_mean4(va, wa, vb, wb, wsum);
        std[c] = _mm256_div_pd(one, _mm256_sqrt_pd(wsum));
        if (value_rows[c] == TM_ROW_SIGMA_T) { /* the Beer-Lambert column, with σt's stds */
            v4 ua = ROW4(a, TM_ROW_SIGMA_T_BEER), ub = ROW4(b, TM_ROW_SIGMA_T_BEER);
            v4 wa2 = _mm256_and_pd(_mm256_and_pd(finite4(ua), usable_a), inv_a);
            v4 wb2 = _mm256_and_pd(_mm256_and_pd(finite4(ub), usable_b), inv_b);
            v4 wsum2 = _mm256_add_pd(wa2, wb2);
            fallback = _mm256_or_pd(fallback, _mm256_cmp_pd(wsum2, _mm256_setzero_pd(), _CMP_NGT_UQ));
            _mm256_storeu_pd(o + (size_t)TM_ROW_SIGMA_T_BEER * n, weighted_mean4(ua, wa2, ub, wb2, wsum2));
        }
        v4 diff = _mm256_andnot_pd(_mm256_set1_pd(-0.0), _mm256_sub_pd(va, vb));
        v4 scale = _mm256_mul_pd(sigmas, _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(sa, sa), _mm256_mul_pd(sb, sb))));
        disagree = _mm256_or_pd(disagree, _mm256_cmp_pd(diff, scale, _CMP_GT_OQ));
        _mm256_storeu_pd(o + (size_t)value_rows[c] * n, value[c]);
        _mm256_storeu_pd(o + (size_t)std_rows[c] * n, std[c]);
        if (value_rows[c] != TM_ROW_SIGMA_T) { /* a flagged thickness weighs in where it carries a quarter of α's or g's weight */
            v4 ra = _mm256_div_pd(std[c], sa), rb = _mm256_div_pd(std[c], sb);
            w0s = _mm256_or_pd(w0s, _mm256_cmp_pd(_mm256_mul_pd(ra, ra), quarter, _CMP_GE_OQ));
            w1s = _mm256_or_pd(w1s, _mm256_cmp_pd(_mm256_mul_pd(rb, rb), quarter, _CMP_GE_OQ));
        }
    }
    /* the conditioning stds combined alike where they are not the stds themselves (bit for bit) */
    v4 cond[2] = {std[0], std[2]};
    static const int cond_rows[2] = {TM_ROW_CONDITIONING_ALPHA_STD, TM_ROW_CONDITIONING_G_STD};
    for (int c = 0; c < 2; c++) {
        int vrow = c ? TM_ROW_G : TM_ROW_ALPHA, srow = c ? TM_ROW_G_STD : TM_ROW_ALPHA_STD;
        v4 ca = ROW4(a, cond_rows[c]), cb = ROW4(b, cond_rows[c]);
        __m256i same = _mm256_and_si256(_mm256_cmpeq_epi64(_mm256_castpd_si256(ca), _mm256_castpd_si256(ROW4(a, srow))),
                                        _mm256_cmpeq_epi64(_mm256_castpd_si256(cb), _mm256_castpd_si256(ROW4(b, srow))));
        if (_mm256_movemask_pd(_mm256_castsi256_pd(same)) == 0xF) continue;
        v4 wa = _mm256_and_pd(_mm256_and_pd(finite4(ROW4(a, vrow)), usable_std4(ca)),
                              _mm256_div_pd(one, _mm256_mul_pd(ca, ca)));
        v4 wb = _mm256_and_pd(_mm256_and_pd(finite4(ROW4(b, vrow)), usable_std4(cb)),
                              _mm256_div_pd(one, _mm256_mul_pd(cb, cb)));
        v4 wsum = _mm256_add_pd(wa, wb);
        v4 differs = _mm256_xor_pd(_mm256_castsi256_pd(same), _mm256_castsi256_pd(_mm256_set1_epi64x(-1)));
        fallback = _mm256_or_pd(fallback,
                                _mm256_and_pd(differs, _mm256_cmp_pd(wsum, _mm256_setzero_pd(), _CMP_NGT_UQ)));
        cond[c] = _mm256_blendv_pd(_mm256_div_pd(one, _mm256_sqrt_pd(wsum)), cond[c], _mm256_castsi256_pd(same));
    }
    _mm256_storeu_pd(o + (size_t)TM_ROW_CONDITIONING_ALPHA_STD * n, cond[0]);
    _mm256_storeu_pd(o + (size_t)TM_ROW_CONDITIONING_G_STD * n, cond[1]);
    v4 under = _mm256_or_pd(_mm256_cmp_pd(cond[0], _mm256_set1_pd(underdetermined_alpha_std), _CMP_GT_OQ),
                            _mm256_cmp_pd(cond[1], _mm256_set1_pd(underdetermined_g_std), _CMP_GT_OQ));
    int heavy_a = _mm256_movemask_pd(w0s), heavy_b = _mm256_movemask_pd(w1s);
    int dis = _mm256_movemask_pd(disagree), und = _mm256_movemask_pd(under);
    const int64_t *fa = (const int64_t *)(a + (size_t)TM_ROW_FLAGS * n), *fb = (const int64_t *)(b + (size_t)TM_ROW_FLAGS * n);
    int64_t *fo = (int64_t *)(o + (size_t)TM_ROW_FLAGS * n);
    for (int l = 0; l < 4; l++) {
        int64_t f0 = fa[l], f1 = fb[l], fl = f0 | f1;
        if (!((f0 & TM_FLAGS_UNUSABLE) && (f1 & TM_FLAGS_UNUSABLE))) fl &= ~(int64_t)TM_FLAGS_UNUSABLE;
        fl &= ~(int64_t)(TM_FLAG_UNDERDETERMINED | TM_FLAG_STD_APPROXIMATE);
        if (((f0 & TM_FLAG_STD_APPROXIMATE) && (heavy_a >> l & 1)) || ((f1 & TM_FLAG_STD_APPROXIMATE) && (heavy_b >> l & 1)))
            fl |= TM_FLAG_STD_APPROXIMATE;
        if (dis >> l & 1) fl |= TM_FLAG_THICKNESS_DISAGREE;
        if (!(fl & TM_FLAGS_UNUSABLE) && (und >> l & 1)) fl |= TM_FLAG_UNDERDETERMINED;
        fo[l] = fl;
    }
    return _mm256_movemask_pd(fallback);
}
#undef ROW4

static int simd_enabled = -1; /* -1: not decided yet */

int tmi_use_simd(void) {
    if (simd_enabled < 0) {
        __builtin_cpu_init();
        simd_enabled = __builtin_cpu_supports("avx2") ? 1 : 0;
    }
    return simd_enabled;
}
#endif

int tm_set_simd(int enabled) {
#ifdef TM_SIMD
    simd_enabled = -1;
    if (enabled) return tmi_use_simd();
    simd_enabled = 0;
#else
    (void)enabled;
#endif
    return 0;
}

