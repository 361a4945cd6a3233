/* The damped Gauss-Newton polish of (α, g) at a bin's fixed σt on the trilinear forward map, bins
 * innermost, each stopping once converged; the residual and Jacobian at the solution. */
#include "invert_internal.h"

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
    hold_at_edges(f, *alpha, *g, &st);
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


/* Up to `iterations` Newton steps per bin; a bin leaves once a step was small (newton_step;
 * step_var: per bin, or NULL for none; step_tol = 0 and no step_var: a fixed count). The loop over
 * bins is innermost: a bin's steps form one long dependency chain (divisions, table reads) while
 * consecutive bins are independent, so the CPU overlaps them, and
 * with AVX2 four of them share each instruction (newton_step4; the rest of a round bin by bin).
 * `active` is scratch for n indices; returns the number of steps taken over all bins. */
size_t tmi_polish(const tm_forward_grid *f, size_t n, sigma_cell_t *cells, const double *I_b,
                     const double *I_w, const double *rho_b, const double *rho_w, int iterations,
                     double step_tol, const double *step_var, double *alpha, double *g, uint32_t *active,
                     final_eval_t *evals) {
    size_t m = n, steps = 0;
    for (size_t i = 0; i < n; i++) active[i] = (uint32_t)i;
    for (int it = 0; it < iterations && m > 0; it++) {
        size_t kept = 0, j = 0;
        steps += m;
#ifdef TM_SIMD
        if (tmi_use_simd())
            for (; j + 4 <= m; j += 4) {
                uint32_t idx[4] = {active[j], active[j + 1], active[j + 2], active[j + 3]};
                int done[4];
                tmi_newton_step4(f, cells, idx, I_b, I_w, rho_b, rho_w, step_tol, step_var, alpha, g, evals, done);
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
double tmi_final_residual2_and_jacobian(const tm_forward_grid *f, sigma_cell_t *c, const final_eval_t *e,
                                           double alpha, double g, double I_b, double I_w, double rho_b,
                                           double rho_w, double *Ji) {
    if (!c->evaluated) return residual2_and_jacobian(f, c, alpha, g, I_b, I_w, rho_b, rho_w, Ji);
    for (int k = 0; k < 6; k++) Ji[k] = e->J[k];
    Ji[6] = Ji[8] = 0.0;
    Ji[7] = collimated_derivative(f, c->sigma_t);
    return e->residual2;
}

/* tm_solve_alpha_g (invert.h) in a caller-owned scratch block of tm_fit_scratch_size(n) bytes (its
 * cells, evaluations and indices). Returns 0, or -1 on a malformed grid. */
int tmi_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b,
                      const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w,
                      int iterations, double step_tol, const double *step_var, double *alpha, double *g,
                      double *residual, double *J, void *scratch) {
    if (!grid_ok(f, table)) return -1;
    fit_scratch_t sc = carve_scratch(scratch, n);
    sigma_cell_t *cells = sc.cells;
    for (size_t i = 0; i < n; i++) {
        cells[i] = sigma_cell(f, log_sigma_t[i], NAN);
        double a = alpha[i], gg = g[i];
        if (table) tmi_initial_guess(table, clamp_log_sigma(f, log_sigma_t[i]), I_b[i], I_w[i], &a, &gg);
        alpha[i] = clampd(a, f->alpha_lo, f->alpha_hi);
        g[i] = clampd(gg, f->g_lo, f->g_hi);
    }
    tmi_prefetch_cells(f, n, cells, alpha, g);
    tmi_polish(f, n, cells, I_b, I_w, rho_b, rho_w, iterations, step_tol, step_var, alpha, g, sc.active, sc.evals);
    for (size_t i = 0; i < n; i++)
        residual[i] = sqrt(tmi_final_residual2_and_jacobian(f, &cells[i], &sc.evals[i], alpha[i], g[i], I_b[i], I_w[i],
                                                            rho_b[i], rho_w[i], J + i * 9u));
    return 0;
}
