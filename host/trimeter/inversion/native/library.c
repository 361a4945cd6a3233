/* The host library's extras around the kernel (not linked into the firmware): the entry points
 * that allocate their scratch, and the hash of the sources the library was built from. */
#include <pthread.h>
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

/* One thickness of tm_fit_thicknesses: tm_fit's two halves into its block, with scratch of its own */
typedef struct {
    const tm_forward_grid *f;
    const tm_inverse_table *table;
    const tm_fit_options *o;
    size_t n;
    const double *I_b, *I_w, *I_c, *rho_b, *rho_w, *sd_in;
    double *block;
    long long steps; /* tm_fit's result */
} thickness_job_t;

static void *fit_thickness(void *arg) {
    thickness_job_t *j = arg;
    void *scratch = malloc(tm_fit_scratch_size(j->n));
    if (!scratch) {
        j->steps = -2;
        return NULL;
    }
    tm_fit_prepare(j->f, j->o, j->n, j->I_b, j->I_w, j->I_c, j->rho_b, j->rho_w, j->sd_in, scratch, j->block, 0.0, 0.0,
                   NULL);
    j->steps = tm_fit_solve(j->f, j->table, j->o, j->n, NULL, NULL, scratch, j->block);
    free(scratch);
    return NULL;
}

/* Below this many bins a thickness is fitted in the calling thread: starting a thread costs about what
 * fitting this many bins does */
#define THREAD_MIN_BINS 128

long long tm_fit_thicknesses(size_t k, const tm_forward_grid *grids, const tm_inverse_table *tables,
                             const tm_fit_options *options, size_t n, const double *I_b, const double *I_w,
                             const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in,
                             double underdetermined_alpha_std, double underdetermined_g_std, double disagree_sigmas,
                             double *fits, double *outputs, int threads) {
    if (!k || !tables) return -1;
    for (size_t j = 0; j < k; j++)
        if (!grid_ok(&grids[j], &tables[j])) return -1;
    thickness_job_t *jobs = n > UINT32_MAX ? NULL : malloc(k * sizeof *jobs);
    pthread_t *started = malloc(k * sizeof *started);
    if (!jobs || !started) {
        free(jobs);
        free(started);
        return -2;
    }
    for (size_t j = 0; j < k; j++) {
        const size_t at = j * n;
        jobs[j] = (thickness_job_t){&grids[j], &tables[j], &options[j], n, I_b + at, I_w + at, I_c + at, rho_b + at,
                                    rho_w + at, sd_in ? sd_in + 3u * at : NULL, fits + j * (size_t)TM_ROW_COUNT * n,
                                    0};
    }
    /* thicknesses 1.. in threads of their own (up to threads - 1 of them) while this one fits thickness 0,
     * then the rest here in turn; each bin's fit is its own, so the results are the same for any threads */
    size_t helpers = threads > 1 && n >= THREAD_MIN_BINS ? (size_t)threads - 1 : 0, running = 0;
    while (running < helpers && running + 1 < k &&
           pthread_create(&started[running], NULL, fit_thickness, &jobs[running + 1]) == 0)
        running++;
    for (size_t j = 0; j < k; j++)
        if (j == 0 || j > running) fit_thickness(&jobs[j]);
    for (size_t t = 0; t < running; t++) pthread_join(started[t], NULL);
    long long steps = 0;
    for (size_t j = 0; j < k && steps >= 0; j++) steps = jobs[j].steps < 0 ? jobs[j].steps : steps + jobs[j].steps;
    free(jobs);
    free(started);
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
