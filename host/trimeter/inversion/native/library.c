/* The host library's extras around the kernel (not linked into the firmware): the entry points
 * that allocate their scratch, and the hash of the sources the library was built from. */
#include <stdlib.h>

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
