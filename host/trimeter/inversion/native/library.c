/* The host library's extras around the kernel (not linked into the firmware): the entry points
 * that allocate their scratch, and the hash of the sources the library was built from. */
#include <stdlib.h>

#include "compact.h"
#include "invert_internal.h"

#ifndef TM_SOURCE_HASH
#define TM_SOURCE_HASH 0 /* not built by `make native`: Python then cannot tell whether it is current */
#endif

uint64_t tm_source_hash(void) { return (uint64_t)TM_SOURCE_HASH; }

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

long long tm_fit_thicknesses(size_t k, const tm_forward_grid *grids, const tm_inverse_table *tables,
                             const tm_fit_options *options, size_t n, const double *I_b, const double *I_w,
                             const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in,
                             double underdetermined_alpha_std, double underdetermined_g_std, double disagree_sigmas,
                             double *fits, double *outputs) {
    if (!k || !tables) return -1;
    for (size_t j = 0; j < k; j++)
        if (!grid_ok(&grids[j], &tables[j])) return -1;
    void *scratch = n > UINT32_MAX ? NULL : malloc(tm_fit_scratch_size(n));
    if (!scratch) return -2;
    long long steps = 0;
    for (size_t j = 0; j < k && steps >= 0; j++) {
        const size_t at = j * n;
        double *block = fits + j * (size_t)TM_ROW_COUNT * n;
        tm_fit_prepare(&grids[j], &options[j], n, I_b + at, I_w + at, I_c + at, rho_b + at, rho_w + at,
                       sd_in ? sd_in + 3u * at : NULL, scratch, block, 0.0, 0.0, NULL);
        long long taken = tm_fit_solve(&grids[j], &tables[j], &options[j], n, NULL, NULL, scratch, block);
        steps = taken < 0 ? taken : steps + taken;
    }
    free(scratch);
    if (steps >= 0) tm_combine(k, n, fits, underdetermined_alpha_std, underdetermined_g_std, disagree_sigmas, outputs);
    return steps;
}

int tm_solve_alpha_g(const tm_forward_grid *f, const tm_inverse_table *table, size_t n, const double *I_b,
                     const double *I_w, const double *log_sigma_t, const double *rho_b, const double *rho_w,
                     int iterations, double step_tol, const double *step_var, double *alpha, double *g,
                     double *residual, double *J) {
    if (!grid_ok(f, table)) return -1;
    void *scratch = n > UINT32_MAX ? NULL : malloc(tm_fit_scratch_size(n)); /* tm_fit's, its inputs unused */
    if (!scratch) return -2;
    int rc = tmi_solve_alpha_g(f, table, n, I_b, I_w, log_sigma_t, rho_b, rho_w, iterations, step_tol, step_var, alpha,
                               g, residual, J, scratch);
    free(scratch);
    return rc;
}

static tr_real finite_in_box(double x, float lo, float hi) { return isfinite(x) ? tr_clamp(x, lo, hi) : lo; }

int tm_table_eval(const uint8_t *table, size_t len, size_t n, const double *alpha, const double *log_sigma_t,
                  const double *g, double *out) {
    tr_table t;
    if (tr_table_open(table, len, &t)) return TM_TABLE_FIT_ERR_TABLE;
    if (n && (!alpha || !log_sigma_t || !g || !out)) return TM_TABLE_FIT_ERR_ARGS;
    for (size_t i = 0; i < n; i++) {
        tr_sigma_slice slice;
        tr_abc c;
        /* a NaN would index outside the table: it reads as the box's lower corner (the caller's bins with a
         * NaN point are NaN already) */
        tr_sigma_slice_init(&t, finite_in_box(log_sigma_t[i], t.log_sigma_t[0], t.log_sigma_t[t.ns - 1]), &slice);
        tr_compact_eval(&t, finite_in_box(alpha[i], t.alpha[0], t.alpha[t.na - 1]), &slice,
                        finite_in_box(g[i], t.g[0], t.g[t.ng - 1]), &c);
        for (int k = 0; k < 3; k++) {
            out[12 * i + (size_t)k] = c.v[k];
            out[12 * i + 3 + (size_t)k] = c.da[k];
            out[12 * i + 6 + (size_t)k] = c.ds[k];
            out[12 * i + 9 + (size_t)k] = c.dg[k];
        }
    }
    return 0;
}
