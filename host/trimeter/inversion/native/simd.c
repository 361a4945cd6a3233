/* Four bins at once with AVX2 (x86-64, chosen at run time; elsewhere, or with tm_set_simd(0), the scalar
 * loops run): newton_step (newton.c), the σ check's step and two thicknesses' combination (pipeline.c).
 * The same operations in the same order, lane by lane, and no FMA (-std=c11 does not contract, and the
 * target does not enable it): bit for bit the scalar result, which tests/inversion/test_native_kernel.py
 * and test_native_combine.py check. Most of a step's arithmetic does not depend on the cell, and here it
 * runs 4 lanes wide. Each lane still walks to its own cell (scalar: short loops), and its 24 polynomial
 * coefficients are loaded as 6 rows of 4 and transposed. */
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
        int ia = walk_alpha(f, alpha[l], &c->ia, &wa[l]);
        int ig = walk_g(f, g[l], &c->ig, &wg[l]);
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

/* pipeline.c weighted() for two thicknesses, lane by lane: the inverse-variance mean of va, vb (stds sa,
 * sb) and its std; where no weight is positive, the plain mean of the finite values and the smallest of
 * their stds; NaN (C's NAN, not the instructions' default NaN) where neither is finite. ua, ub (or NULL): a
 * second column with the same stds, whose mean alone goes to *value2. Every operation as weighted()'s,
 * in its order (its sums from +0, so that a −0 product gives +0). */
__attribute__((target("avx2"))) static inline v4 finite4(v4 x) {
    return _mm256_cmp_pd(_mm256_andnot_pd(_mm256_set1_pd(-0.0), x), _mm256_set1_pd(INFINITY), _CMP_LT_OQ);
}

/* fmin: a NaN loses to a number (min_pd alone returns its second operand where either is NaN) */
__attribute__((target("avx2"))) static inline v4 fmin4(v4 a, v4 b) {
    return _mm256_blendv_pd(_mm256_min_pd(a, b), a, _mm256_cmp_pd(b, b, _CMP_UNORD_Q));
}

/* mean or, where no weight is positive, the plain mean (NaN where no value is finite) */
__attribute__((target("avx2"))) static inline v4 mean4(v4 va, v4 vb, v4 fa, v4 fb, v4 wa, v4 wb, v4 wsum,
                                                       v4 positive, v4 count) {
    v4 vaz = _mm256_and_pd(fa, va), vbz = _mm256_and_pd(fb, vb), zero = _mm256_setzero_pd();
    v4 mean = _mm256_div_pd(_mm256_add_pd(_mm256_add_pd(zero, _mm256_mul_pd(vaz, wa)), _mm256_mul_pd(vbz, wb)), wsum);
    if (_mm256_movemask_pd(positive) == 0xF) return mean; /* the common case: no division for the fallback */
    v4 plain = _mm256_div_pd(_mm256_add_pd(_mm256_add_pd(zero, vaz), vbz), count);
    plain = _mm256_blendv_pd(plain, _mm256_set1_pd(NAN), _mm256_cmp_pd(count, zero, _CMP_EQ_OQ));
    return _mm256_blendv_pd(plain, mean, positive);
}

__attribute__((target("avx2"))) static inline void weighted4(v4 va, v4 vb, v4 sa, v4 sb, const double *ua,
                                                             const double *ub, v4 *value, v4 *std, v4 *value2) {
    const v4 one = _mm256_set1_pd(1.0), zero = _mm256_setzero_pd(), inf = _mm256_set1_pd(INFINITY);
    v4 usable_a = _mm256_and_pd(_mm256_cmp_pd(sa, zero, _CMP_GT_OQ), _mm256_cmp_pd(sa, inf, _CMP_LT_OQ));
    v4 usable_b = _mm256_and_pd(_mm256_cmp_pd(sb, zero, _CMP_GT_OQ), _mm256_cmp_pd(sb, inf, _CMP_LT_OQ));
    v4 inv_a = _mm256_div_pd(one, _mm256_mul_pd(sa, sa)), inv_b = _mm256_div_pd(one, _mm256_mul_pd(sb, sb));
    v4 fa = finite4(va), fb = finite4(vb);
    v4 wa = _mm256_and_pd(_mm256_and_pd(fa, usable_a), inv_a), wb = _mm256_and_pd(_mm256_and_pd(fb, usable_b), inv_b);
    v4 wsum = _mm256_add_pd(wa, wb); /* weighted()'s +0 + wa is wa: wa is +0 or positive */
    v4 positive = _mm256_cmp_pd(wsum, zero, _CMP_GT_OQ);
    v4 count = _mm256_add_pd(_mm256_and_pd(fa, one), _mm256_and_pd(fb, one));
    *value = mean4(va, vb, fa, fb, wa, wb, wsum, positive, count);
    *std = _mm256_div_pd(one, _mm256_sqrt_pd(wsum));
    if (_mm256_movemask_pd(positive) != 0xF) {
        v4 smallest = fmin4(_mm256_blendv_pd(inf, sa, fa), _mm256_blendv_pd(inf, sb, fb));
        smallest = _mm256_blendv_pd(smallest, _mm256_set1_pd(NAN), _mm256_cmp_pd(count, zero, _CMP_EQ_OQ));
        *std = _mm256_blendv_pd(smallest, *std, positive);
    }
    if (ua) {
        v4 u0 = _mm256_loadu_pd(ua), u1 = _mm256_loadu_pd(ub), f0 = finite4(u0), f1 = finite4(u1);
        v4 w0 = _mm256_and_pd(_mm256_and_pd(f0, usable_a), inv_a), w1 = _mm256_and_pd(_mm256_and_pd(f1, usable_b), inv_b);
        v4 wsum2 = _mm256_add_pd(w0, w1);
        *value2 = mean4(u0, u1, f0, f1, w0, w1, wsum2, _mm256_cmp_pd(wsum2, zero, _CMP_GT_OQ),
                        _mm256_add_pd(_mm256_and_pd(f0, one), _mm256_and_pd(f1, one)));
    }
}

#define ROW(p, r) ((p) + (size_t)(r) * n)

/* pipeline.c combine_bin for two thicknesses and the bins i .. i+3: the same operations, lane by lane. */
void tmi_combine2_4(size_t n, size_t i, const double *fits, double underdetermined_alpha_std,
                    double underdetermined_g_std, double disagree_sigmas, double *outputs)
    __attribute__((target("avx2")));
void tmi_combine2_4(size_t n, size_t i, const double *fits, double underdetermined_alpha_std,
                    double underdetermined_g_std, double disagree_sigmas, double *outputs) {
    const double *a = fits + i, *b = fits + (size_t)TM_ROW_COUNT * n + i;
    double *o = outputs + i;
    const v4 quarter = _mm256_set1_pd(0.25), sigmas = _mm256_set1_pd(disagree_sigmas);
    static const int value_rows[3] = {TM_ROW_ALPHA, TM_ROW_SIGMA_T, TM_ROW_G};
    static const int std_rows[3] = {TM_ROW_ALPHA_STD, TM_ROW_SIGMA_T_STD, TM_ROW_G_STD};
    v4 std[3], disagree = _mm256_setzero_pd(), heavy_a = disagree, heavy_b = disagree;
    const int64_t *fa = (const int64_t *)ROW(a, TM_ROW_FLAGS), *fb = (const int64_t *)ROW(b, TM_ROW_FLAGS);
    int64_t approx_any = 0; /* the weights of a flagged thickness are weighed only where there is one */
    for (int l = 0; l < 4; l++) approx_any |= (fa[l] | fb[l]) & TM_FLAG_STD_APPROXIMATE;
    for (int c = 0; c < 3; c++) {
        int sigma = value_rows[c] == TM_ROW_SIGMA_T; /* the Beer-Lambert column goes with σt's stds */
        v4 va = _mm256_loadu_pd(ROW(a, value_rows[c])), vb = _mm256_loadu_pd(ROW(b, value_rows[c]));
        v4 sa = _mm256_loadu_pd(ROW(a, std_rows[c])), sb = _mm256_loadu_pd(ROW(b, std_rows[c]));
        v4 value, beer = _mm256_setzero_pd(); /* set where sigma */
        weighted4(va, vb, sa, sb, sigma ? ROW(a, TM_ROW_SIGMA_T_BEER) : NULL, ROW(b, TM_ROW_SIGMA_T_BEER), &value,
                  &std[c], &beer);
        _mm256_storeu_pd(ROW(o, value_rows[c]), value);
        _mm256_storeu_pd(ROW(o, std_rows[c]), std[c]);
        if (sigma) {
            _mm256_storeu_pd(ROW(o, TM_ROW_SIGMA_T_BEER), beer);
        } else if (approx_any) { /* a flagged thickness weighs in where it carries a quarter of α's or g's weight */
            v4 ra = _mm256_div_pd(std[c], sa), rb = _mm256_div_pd(std[c], sb);
            heavy_a = _mm256_or_pd(heavy_a, _mm256_cmp_pd(_mm256_mul_pd(ra, ra), quarter, _CMP_GE_OQ));
            heavy_b = _mm256_or_pd(heavy_b, _mm256_cmp_pd(_mm256_mul_pd(rb, rb), quarter, _CMP_GE_OQ));
        }
        v4 diff = _mm256_andnot_pd(_mm256_set1_pd(-0.0), _mm256_sub_pd(va, vb));
        v4 scale = _mm256_mul_pd(sigmas, _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(sa, sa), _mm256_mul_pd(sb, sb))));
        disagree = _mm256_or_pd(disagree, _mm256_cmp_pd(diff, scale, _CMP_GT_OQ));
    }
    /* the conditioning stds combined alike where they are not the stds themselves (bit for bit) */
    v4 cond[2] = {std[0], std[2]};
    static const int cond_rows[2] = {TM_ROW_CONDITIONING_ALPHA_STD, TM_ROW_CONDITIONING_G_STD};
    for (int c = 0; c < 2; c++) {
        int vrow = c ? TM_ROW_G : TM_ROW_ALPHA, srow = c ? TM_ROW_G_STD : TM_ROW_ALPHA_STD;
        v4 ca = _mm256_loadu_pd(ROW(a, cond_rows[c])), cb = _mm256_loadu_pd(ROW(b, cond_rows[c]));
        __m256i same_a = _mm256_cmpeq_epi64(_mm256_castpd_si256(ca), _mm256_castpd_si256(_mm256_loadu_pd(ROW(a, srow))));
        __m256i same_b = _mm256_cmpeq_epi64(_mm256_castpd_si256(cb), _mm256_castpd_si256(_mm256_loadu_pd(ROW(b, srow))));
        v4 same = _mm256_castsi256_pd(_mm256_and_si256(same_a, same_b));
        if (_mm256_movemask_pd(same) == 0xF) continue;
        v4 unused, combined;
        weighted4(_mm256_loadu_pd(ROW(a, vrow)), _mm256_loadu_pd(ROW(b, vrow)), ca, cb, NULL, NULL, &unused, &combined,
                  NULL);
        cond[c] = _mm256_blendv_pd(combined, cond[c], same);
    }
    _mm256_storeu_pd(ROW(o, TM_ROW_CONDITIONING_ALPHA_STD), cond[0]);
    _mm256_storeu_pd(ROW(o, TM_ROW_CONDITIONING_G_STD), cond[1]);
    v4 under = _mm256_or_pd(_mm256_cmp_pd(cond[0], _mm256_set1_pd(underdetermined_alpha_std), _CMP_GT_OQ),
                            _mm256_cmp_pd(cond[1], _mm256_set1_pd(underdetermined_g_std), _CMP_GT_OQ));
    int heavy0 = _mm256_movemask_pd(heavy_a), heavy1 = _mm256_movemask_pd(heavy_b);
    int dis = _mm256_movemask_pd(disagree), und = _mm256_movemask_pd(under);
    int64_t *fo = (int64_t *)ROW(o, TM_ROW_FLAGS);
    for (int l = 0; l < 4; l++) {
        int64_t f0 = fa[l], f1 = fb[l], fl = f0 | f1;
        if (!((f0 & TM_FLAGS_UNUSABLE) && (f1 & TM_FLAGS_UNUSABLE))) fl &= ~(int64_t)TM_FLAGS_UNUSABLE;
        fl &= ~(int64_t)(TM_FLAG_UNDERDETERMINED | TM_FLAG_STD_APPROXIMATE);
        if (((f0 & TM_FLAG_STD_APPROXIMATE) && (heavy0 >> l & 1)) || ((f1 & TM_FLAG_STD_APPROXIMATE) && (heavy1 >> l & 1)))
            fl |= TM_FLAG_STD_APPROXIMATE;
        if (dis >> l & 1) fl |= TM_FLAG_THICKNESS_DISAGREE;
        if (!(fl & TM_FLAGS_UNUSABLE) && (und >> l & 1)) fl |= TM_FLAG_UNDERDETERMINED;
        fo[l] = fl;
    }
}
#undef ROW

/* propagate_one (pipeline.c), four lanes: the stds of (α, σt, g) from the Jacobian's entries J0..J5, J7
 * (Ji's), the intensities' variances and I_c's std, and σt's further variance */
__attribute__((target("avx2"))) static inline void propagate4(const v4 *J, v4 var_b, v4 var_w, v4 sd_c,
                                                              v4 var_s_extra, v4 *std_a, v4 *std_s, v4 *std_g) {
    const v4 sign = _mm256_set1_pd(-0.0), inf = _mm256_set1_pd(INFINITY);
    v4 ds = _mm256_div_pd(sd_c, J[7]);
    v4 var_s = _mm256_add_pd(_mm256_mul_pd(ds, ds), var_s_extra);
    v4 inv_det = _mm256_div_pd(_mm256_set1_pd(1.0), _mm256_sub_pd(_mm256_mul_pd(J[0], J[5]), _mm256_mul_pd(J[2], J[3])));
    v4 i00 = _mm256_mul_pd(J[5], inv_det), i01 = _mm256_mul_pd(_mm256_xor_pd(J[2], sign), inv_det);
    v4 i10 = _mm256_mul_pd(_mm256_xor_pd(J[3], sign), inv_det), i11 = _mm256_mul_pd(J[0], inv_det);
    v4 c00 = _mm256_add_pd(var_b, _mm256_mul_pd(_mm256_mul_pd(J[1], J[1]), var_s));
    v4 c11 = _mm256_add_pd(var_w, _mm256_mul_pd(_mm256_mul_pd(J[4], J[4]), var_s));
    v4 c01 = _mm256_mul_pd(_mm256_mul_pd(J[1], J[4]), var_s);
    v4 va = _mm256_add_pd(
        _mm256_mul_pd(i00, _mm256_add_pd(_mm256_mul_pd(i00, c00), _mm256_mul_pd(i01, c01))),
        _mm256_mul_pd(i01, _mm256_add_pd(_mm256_mul_pd(i00, c01), _mm256_mul_pd(i01, c11))));
    v4 vg = _mm256_add_pd(
        _mm256_mul_pd(i10, _mm256_add_pd(_mm256_mul_pd(i10, c00), _mm256_mul_pd(i11, c01))),
        _mm256_mul_pd(i11, _mm256_add_pd(_mm256_mul_pd(i10, c01), _mm256_mul_pd(i11, c11))));
    v4 sa = _mm256_sqrt_pd(_mm256_andnot_pd(sign, va)), sg = _mm256_sqrt_pd(_mm256_andnot_pd(sign, vg));
    *std_a = _mm256_blendv_pd(sa, inf, _mm256_cmp_pd(sa, sa, _CMP_UNORD_Q));
    *std_g = _mm256_blendv_pd(sg, inf, _mm256_cmp_pd(sg, sg, _CMP_UNORD_Q));
    *std_s = _mm256_sqrt_pd(var_s);
}

/* flags |= bit in the lanes of mask */
__attribute__((target("avx2"))) static inline __m256i flag4(__m256i flags, v4 mask, int64_t bit) {
    return _mm256_or_si256(flags, _mm256_and_si256(_mm256_castpd_si256(mask), _mm256_set1_epi64x(bit)));
}

/* lanes whose flags have any of bits */
__attribute__((target("avx2"))) static inline v4 flagged4(__m256i flags, int64_t bits) {
    __m256i none = _mm256_cmpeq_epi64(_mm256_and_si256(flags, _mm256_set1_epi64x(bits)), _mm256_setzero_si256());
    return _mm256_castsi256_pd(_mm256_xor_si256(none, _mm256_set1_epi64x(-1)));
}

/* pipeline.c finish_bin for the bins i .. i+3: the same operations, lane by lane; returns the lanes
 * (bit l: bin i+l) whose stds go to check_first_order. */
int tmi_finish4(const finish_ctx_t *c, size_t i) __attribute__((target("avx2")));
int tmi_finish4(const finish_ctx_t *c, size_t i) {
    const tm_forward_grid *f = c->f;
    const tm_fit_options *o = c->o;
    const tm_fit_outputs *out = &c->out;
    const finish_t *b = c->fin + i;
    const v4 nan = _mm256_set1_pd(NAN), inf = _mm256_set1_pd(INFINITY), zero = _mm256_setzero_pd();
    const v4 all = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
    v4 J[8];
    for (int k = 0; k < 8; k++) J[k] = set4(b[0].Ji[k], b[1].Ji[k], b[2].Ji[k], b[3].Ji[k]);
#define FIELD(x) set4(b[0].x, b[1].x, b[2].x, b[3].x)
    v4 residual2 = FIELD(residual2), ds_in = FIELD(ds_in), model_b = FIELD(model_b), model_w = FIELD(model_w);
#undef FIELD
    __m256i fl = _mm256_loadu_si256((const __m256i *)(out->flags + i));
    v4 usable = _mm256_xor_pd(flagged4(fl, TM_FLAGS_UNUSABLE), all);
    v4 alpha = _mm256_loadu_pd(out->alpha + i), g = _mm256_loadu_pd(out->g + i);
    v4 in_var_b = _mm256_loadu_pd(c->var_b + i), in_var_w = _mm256_loadu_pd(c->var_w + i);
    v4 sd_c = _mm256_loadu_pd(c->sd_c + i), mc2 = _mm256_set1_pd(c->mc2);
    v4 var_b = _mm256_add_pd(in_var_b, mc2), var_w = _mm256_add_pd(in_var_w, mc2);
    v4 tolerance = _mm256_add_pd(_mm256_mul_pd(_mm256_set1_pd(3.0), _mm256_sqrt_pd(_mm256_add_pd(var_b, var_w))),
                                 _mm256_set1_pd(1e-4));
    v4 not_conv = _mm256_and_pd(usable, _mm256_cmp_pd(residual2, _mm256_mul_pd(tolerance, tolerance), _CMP_NLE_UQ));
    v4 at_edge = _mm256_or_pd(
        _mm256_and_pd(_mm256_cmp_pd(g, _mm256_set1_pd(f->g_lo + 1e-9), _CMP_LE_OQ), c->g_lo_is_edge ? all : zero),
        _mm256_and_pd(_mm256_cmp_pd(g, _mm256_set1_pd(f->g_hi - 1e-9), _CMP_GE_OQ), c->g_hi_is_edge ? all : zero));
    fl = flag4(fl, not_conv, TM_FLAG_NOT_CONVERGED);
    fl = flag4(fl, _mm256_and_pd(not_conv, at_edge), TM_FLAG_OUTSIDE_MAP);
    v4 a = _mm256_blendv_pd(nan, clamp4(alpha, zero, _mm256_set1_pd(1.0)), finite4(alpha));
    v4 gg = _mm256_blendv_pd(nan, clamp4(g, _mm256_set1_pd(-1.0), _mm256_set1_pd(1.0)), finite4(g));
    v4 ds_rel = _mm256_mul_pd(_mm256_set1_pd(o->inscatter_rel_std), ds_in), extra = _mm256_mul_pd(ds_rel, ds_rel);
    v4 sa, ss, sg;
    propagate4(J, _mm256_add_pd(in_var_b, model_b), _mm256_add_pd(in_var_w, model_w), sd_c, extra, &sa, &ss, &sg);
    v4 sigma_t = _mm256_loadu_pd(out->sigma_t + i);
    v4 thick = _mm256_mul_pd(_mm256_set1_pd(o->thickness_rel_std), sigma_t);
    ss = _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(ss, ss), _mm256_mul_pd(thick, thick)));
    ss = _mm256_blendv_pd(ss, inf, flagged4(fl, TM_FLAG_IC_BELOW_FLOOR));
    v4 g_undefined = _mm256_andnot_pd(_mm256_cmp_pd(a, _mm256_set1_pd(o->alpha_min_g), _CMP_GE_OQ), usable);
    fl = flag4(fl, g_undefined, TM_FLAG_G_UNDEFINED);
    gg = _mm256_blendv_pd(gg, nan, g_undefined);
    sg = _mm256_blendv_pd(sg, nan, g_undefined);
    v4 ua = sa, ug = sg;
    v4 cond_var_b = _mm256_loadu_pd(c->cond_var_b + i), cond_var_w = _mm256_loadu_pd(c->cond_var_w + i);
    v4 cond_sd_c = _mm256_loadu_pd(c->cond_sd_c + i);
    v4 differ = _mm256_or_pd(_mm256_or_pd(_mm256_cmp_pd(cond_var_b, in_var_b, _CMP_NEQ_UQ),
                                          _mm256_cmp_pd(cond_var_w, in_var_w, _CMP_NEQ_UQ)),
                             _mm256_cmp_pd(cond_sd_c, sd_c, _CMP_NEQ_UQ));
    if (_mm256_movemask_pd(differ)) {
        v4 ua2, us2, ug2;
        propagate4(J, _mm256_add_pd(cond_var_b, model_b), _mm256_add_pd(cond_var_w, model_w), cond_sd_c, extra, &ua2,
                   &us2, &ug2);
        ug2 = _mm256_blendv_pd(ug2, nan, _mm256_cmp_pd(gg, gg, _CMP_UNORD_Q));
        ua = _mm256_blendv_pd(ua, ua2, differ);
        ug = _mm256_blendv_pd(ug, ug2, differ);
    }
    v4 under = _mm256_and_pd(usable, _mm256_or_pd(_mm256_cmp_pd(ua, _mm256_set1_pd(o->underdetermined_alpha_std), _CMP_GT_OQ),
                                                  _mm256_cmp_pd(ug, _mm256_set1_pd(o->underdetermined_g_std), _CMP_GT_OQ)));
    fl = flag4(fl, under, TM_FLAG_UNDERDETERMINED);
    v4 check = _mm256_andnot_pd(flagged4(fl, TM_FLAGS_STD_CHECK_SKIP), _mm256_and_pd(finite4(sa), finite4(sg)));
    check = _mm256_and_pd(check, _mm256_or_pd(_mm256_cmp_pd(sa, _mm256_set1_pd(o->std_check_alpha), _CMP_GT_OQ),
                                              _mm256_cmp_pd(sg, _mm256_set1_pd(o->std_check_g), _CMP_GT_OQ)));
    /* unusable bins: NaN */
    _mm256_storeu_pd(out->alpha + i, _mm256_blendv_pd(nan, a, usable));
    _mm256_storeu_pd(out->g + i, _mm256_blendv_pd(nan, gg, usable));
    _mm256_storeu_pd(out->alpha_std + i, _mm256_blendv_pd(nan, sa, usable));
    _mm256_storeu_pd(out->sigma_t_std + i, _mm256_blendv_pd(nan, ss, usable));
    _mm256_storeu_pd(out->g_std + i, _mm256_blendv_pd(nan, sg, usable));
    _mm256_storeu_pd(out->cond_alpha_std + i, _mm256_blendv_pd(nan, ua, usable));
    _mm256_storeu_pd(out->cond_g_std + i, _mm256_blendv_pd(nan, ug, usable));
    _mm256_storeu_pd(out->sigma_t + i, _mm256_blendv_pd(nan, sigma_t, usable));
    _mm256_storeu_pd(out->sigma_t_beer + i, _mm256_blendv_pd(nan, _mm256_loadu_pd(out->sigma_t_beer + i), usable));
    _mm256_storeu_si256((__m256i *)(out->flags + i), fl);
    return _mm256_movemask_pd(check);
}

/* -1: not decided yet; atomic, as the threads of tm_fit_thicknesses read it (on x86 a plain load) */
static _Atomic int simd_enabled = -1;

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

