/* The host library's extras around the kernel (not linked into the firmware): the entry points
 * that allocate their scratch, the threads that fit several thicknesses at once, and the hash of the
 * sources the library was built from. */
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

/* Threads kept between calls to fit thicknesses beside the caller's: starting a thread each call costs
 * about a tenth of a two-thickness fit where its CPU had gone idle. A helper is started on its first job
 * and then waits for the next; one given to no caller is free. */
#define HELPERS 7

typedef struct {
    pthread_mutex_t lock;
    pthread_cond_t cond;      /* a job handed over (the helper waits for it), or finished (the caller does) */
    thickness_job_t *job;     /* NULL: free */
    int finished, exists;
} helper_t;

static helper_t helpers[HELPERS];
static pthread_once_t helpers_once = PTHREAD_ONCE_INIT;

static void reset_helpers(void) {
    for (int i = 0; i < HELPERS; i++) {
        helper_t *h = &helpers[i];
        pthread_mutex_init(&h->lock, NULL);
        pthread_cond_init(&h->cond, NULL);
        h->job = NULL;
        h->finished = h->exists = 0;
    }
}

/* A child after fork() has none of its parent's threads: its helpers start again when first needed (the
 * parent's locks may have been held by one of them) */
static void init_helpers(void) {
    reset_helpers();
    pthread_atfork(NULL, NULL, reset_helpers);
}

static void *helper_loop(void *arg) {
    helper_t *h = arg;
    pthread_mutex_lock(&h->lock);
    for (;;) {
        while (!h->job || h->finished) pthread_cond_wait(&h->cond, &h->lock);
        thickness_job_t *job = h->job;
        pthread_mutex_unlock(&h->lock);
        fit_thickness(job);
        pthread_mutex_lock(&h->lock);
        h->finished = 1;
        pthread_cond_broadcast(&h->cond);
    }
    return NULL;
}

static int start_helper(helper_t *h) {
    pthread_t thread;
    if (pthread_create(&thread, NULL, helper_loop, h)) return 0;
    pthread_detach(thread);
    return 1;
}

/* The job handed to a free helper (started on its first use): that helper, or NULL where none is free */
static helper_t *hand_over(thickness_job_t *job) {
    pthread_once(&helpers_once, init_helpers);
    for (int i = 0; i < HELPERS; i++) {
        helper_t *h = &helpers[i];
        pthread_mutex_lock(&h->lock);
        int taken = !h->job && (h->exists || (h->exists = start_helper(h)));
        if (taken) {
            h->job = job;
            h->finished = 0;
            pthread_cond_broadcast(&h->cond);
        }
        pthread_mutex_unlock(&h->lock);
        if (taken) return h;
    }
    return NULL;
}

/* Waits for the helper's job and frees it */
static void collect(helper_t *h) {
    pthread_mutex_lock(&h->lock);
    while (!h->finished) pthread_cond_wait(&h->cond, &h->lock);
    h->job = NULL;
    pthread_mutex_unlock(&h->lock);
}

/* Below this many bins a thickness is fitted in the calling thread: handing it over costs about what
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
    helper_t **given = malloc(k * sizeof *given);
    if (!jobs || !given) {
        free(jobs);
        free(given);
        return -2;
    }
    for (size_t j = 0; j < k; j++) {
        const size_t at = j * n;
        jobs[j] = (thickness_job_t){&grids[j], &tables[j], &options[j], n, I_b + at, I_w + at, I_c + at, rho_b + at,
                                    rho_w + at, sd_in ? sd_in + 3u * at : NULL, fits + j * (size_t)TM_ROW_COUNT * n,
                                    0};
    }
    /* thicknesses 1.. to helpers (up to threads - 1 of them, as many as are free) while this thread fits
     * thickness 0, then the rest here in turn; each bin's fit is its own, so the results are the same
     * for any threads */
    size_t wanted = threads > 1 && n >= THREAD_MIN_BINS ? (size_t)threads - 1 : 0, running = 0;
    while (running < wanted && running + 1 < k && (given[running] = hand_over(&jobs[running + 1])) != NULL)
        running++;
    for (size_t j = 0; j < k; j++)
        if (j == 0 || j > running) fit_thickness(&jobs[j]);
    for (size_t t = 0; t < running; t++) collect(given[t]);
    long long steps = 0;
    for (size_t j = 0; j < k && steps >= 0; j++) steps = jobs[j].steps < 0 ? jobs[j].steps : steps + jobs[j].steps;
    free(jobs);
    free(given);
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
