/* The host library's extras around the kernel (not linked into the firmware): the entry points
 * that allocate their scratch, the threads that share out a fit's bins, and the hash of the sources the
 * library was built from. */
#define _POSIX_C_SOURCE 200809L /* clock_gettime under -std=c11 */
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <time.h>

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

/* The bins of a part: a thickness's bins are fitted in parts of at most this many, so that threads share
 * the work evenly however late one of them starts (a helper whose CPU had gone idle starts a tenth of a
 * two-thickness fit late) */
#define PART_BINS 128
#define HELPERS 7

/* The work of one tm_fit_thicknesses: k thicknesses of n bins, each in `per_thickness` parts, the parts
 * numbered thickness by thickness and dealt out in one run of consecutive parts per thread. A thread
 * takes the parts of its own run first (mostly one thickness: its map stays in that core's cache), then
 * those left in the others' runs. */
typedef struct {
    const tm_forward_grid *grids;
    const tm_inverse_table *tables;
    const tm_fit_options *options;
    size_t k, n, per_thickness, runs;
    const double *I_b, *I_w, *I_c, *rho_b, *rho_w, *sd_in;
    double *fits;
    struct {
        atomic_size_t next; /* the run's next part to take: past `end`, none is left */
        size_t end;
    } run[HELPERS + 1];
    atomic_llong steps; /* the Newton steps of the parts fitted, or the first error */
} work_t;

/* One part: tm_fit's two halves straight into its place in its thickness's block */
static long long fit_part(const work_t *w, size_t p, void *scratch) {
    const size_t j = p / w->per_thickness, first = p % w->per_thickness * PART_BINS;
    const size_t m = w->n - first < PART_BINS ? w->n - first : PART_BINS, at = j * w->n + first;
    double *block = w->fits + j * (size_t)TM_ROW_COUNT * w->n + first;
    tmi_fit_prepare(&w->grids[j], &w->options[j], m, w->I_b + at, w->I_w + at, w->I_c + at, w->rho_b + at,
                    w->rho_w + at, w->sd_in ? w->sd_in + 3u * at : NULL, scratch, block, w->n, 0.0, 0.0, NULL);
    return tmi_fit_solve(&w->grids[j], &w->tables[j], &w->options[j], m, NULL, NULL, scratch, block, w->n);
}

/* Parts fitted until none is left, run `own`'s first; scratch: tm_fit_scratch_size(PART_BINS) bytes */
static void take_parts(work_t *w, size_t own, void *scratch) {
    long long steps = 0;
    for (size_t r = 0; r < w->runs; r++) {
        const size_t run = (own + r) % w->runs;
        for (size_t p; (p = atomic_fetch_add(&w->run[run].next, 1)) < w->run[run].end;) {
            long long s = fit_part(w, p, scratch);
            if (s < 0) {
                atomic_store(&w->steps, s);
                return;
            }
            steps += s;
        }
    }
    long long seen = atomic_load(&w->steps);
    while (seen >= 0 && !atomic_compare_exchange_weak(&w->steps, &seen, seen + steps)) {
    }
}

/* Threads kept between calls to take parts beside the caller: starting a thread each call costs about
 * a tenth of a two-thickness fit where its CPU had gone idle. A helper is started on its first work and
 * then waits for the next; one given to no caller is free. */
typedef struct {
    pthread_mutex_t lock;
    pthread_cond_t cond;      /* work handed over (the helper waits for it), or finished (the caller does) */
    work_t *work;             /* NULL: free */
    size_t own;               /* the work's run this helper takes first */
    int started, finished, exists;
    int expect;               /* woken ahead of work (tm_expect_fit): wait for it awake */
    atomic_int handed;        /* work is handed over: what a helper waiting awake watches */
} helper_t;

static helper_t helpers[HELPERS];
static pthread_once_t helpers_once = PTHREAD_ONCE_INIT;

static void reset_helpers(void) {
    for (int i = 0; i < HELPERS; i++) {
        helper_t *h = &helpers[i];
        pthread_mutex_init(&h->lock, NULL);
        pthread_cond_init(&h->cond, NULL);
        h->work = NULL;
        h->started = h->finished = h->exists = h->expect = 0;
        atomic_init(&h->handed, 0);
    }
}

/* A child after fork() has none of its parent's threads: its helpers start again when first needed (the
 * parent's locks may have been held by one of them) */
static void init_helpers(void) {
    reset_helpers();
    pthread_atfork(NULL, NULL, reset_helpers);
}

/* How long a helper woken ahead of a fit waits for its work awake before it sleeps again */
#define EXPECT_NS 1000000L

static long long elapsed_ns(const struct timespec *since) {
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (now.tv_sec - since->tv_sec) * 1000000000LL + (now.tv_nsec - since->tv_nsec);
}

/* Waiting awake: yielding, so that the CPU serves any other thread that wants it meanwhile */
static void wait_awake(helper_t *h) {
    struct timespec since;
    clock_gettime(CLOCK_MONOTONIC, &since);
    while (!atomic_load_explicit(&h->handed, memory_order_acquire) && elapsed_ns(&since) < EXPECT_NS) sched_yield();
}

static void *helper_loop(void *arg) {
    helper_t *h = arg;
    void *scratch = malloc(tm_fit_scratch_size(PART_BINS)); /* for its life; without it, it takes no parts */
    pthread_mutex_lock(&h->lock);
    for (;;) {
        while (!h->work || h->started) {
            if (h->expect) {
                h->expect = 0;
                pthread_mutex_unlock(&h->lock);
                wait_awake(h);
                pthread_mutex_lock(&h->lock);
            } else {
                pthread_cond_wait(&h->cond, &h->lock);
            }
        }
        work_t *work = h->work;
        h->started = 1;
        pthread_mutex_unlock(&h->lock);
        if (scratch) take_parts(work, h->own, scratch);
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

/* The work handed to a free helper (started on its first use), to take run `own` first: that helper, or
 * NULL where none is free */
static helper_t *hand_over(work_t *work, size_t own) {
    pthread_once(&helpers_once, init_helpers);
    for (int i = 0; i < HELPERS; i++) {
        helper_t *h = &helpers[i];
        pthread_mutex_lock(&h->lock);
        int taken = !h->work && (h->exists || (h->exists = start_helper(h)));
        if (taken) {
            h->work = work;
            h->own = own;
            h->started = h->finished = 0;
            atomic_store_explicit(&h->handed, 1, memory_order_release);
            pthread_cond_broadcast(&h->cond);
        }
        pthread_mutex_unlock(&h->lock);
        if (taken) return h;
    }
    return NULL;
}

/* Frees the helper once it is done with the work; one that has not started yet never will (every part is
 * taken by now), so it is not waited for */
static void collect(helper_t *h) {
    pthread_mutex_lock(&h->lock);
    if (h->started)
        while (!h->finished) pthread_cond_wait(&h->cond, &h->lock);
    h->work = NULL;
    h->started = 0;
    atomic_store_explicit(&h->handed, 0, memory_order_relaxed);
    pthread_mutex_unlock(&h->lock);
}

/* Below this many bins over all thicknesses the caller fits them alone: too few to be worth waking a
 * helper for */
#define THREAD_MIN_BINS 256

/* The helpers a fit of k thicknesses of n bins in `threads` threads hands parts to */
static size_t helpers_for(size_t k, size_t n, int threads) {
    const size_t parts = k * ((n + PART_BINS - 1) / PART_BINS);
    size_t wanted = threads > 1 && parts > 1 && k * n >= THREAD_MIN_BINS ? (size_t)threads - 1 : 0;
    if (wanted > HELPERS) wanted = HELPERS;
    return wanted > parts - 1 ? parts - 1 : wanted;
}

void tm_expect_fit(size_t k, size_t n, int threads) {
    size_t wanted = helpers_for(k, n, threads);
    if (!wanted) return;
    pthread_once(&helpers_once, init_helpers);
    for (int i = 0; i < HELPERS && wanted; i++) {
        helper_t *h = &helpers[i];
        pthread_mutex_lock(&h->lock);
        if (!h->work && (h->exists || (h->exists = start_helper(h)))) {
            h->expect = 1;
            pthread_cond_broadcast(&h->cond);
            wanted--;
        }
        pthread_mutex_unlock(&h->lock);
    }
}

long long tm_fit_thicknesses(size_t k, const tm_forward_grid *grids, const tm_inverse_table *tables,
                             const tm_fit_options *options, size_t n, const double *I_b, const double *I_w,
                             const double *I_c, const double *rho_b, const double *rho_w, const double *sd_in,
                             double underdetermined_alpha_std, double underdetermined_g_std, double disagree_sigmas,
                             double *fits, double *outputs, int threads) {
    if (!k || !tables || n > UINT32_MAX) return -1;
    for (size_t j = 0; j < k; j++)
        if (!grid_ok(&grids[j], &tables[j])) return -1;
    void *scratch = malloc(tm_fit_scratch_size(PART_BINS));
    if (!scratch) return -2;
    const size_t per_thickness = (n + PART_BINS - 1) / PART_BINS, parts = k * per_thickness;
    /* up to threads - 1 helpers beside this thread, a run of parts each; each bin's fit is its own, so the
     * results are the same whoever fits which part */
    const size_t helpers_wanted = helpers_for(k, n, threads);
    work_t w = {.grids = grids, .tables = tables, .options = options, .k = k, .n = n, .per_thickness = per_thickness,
                .runs = helpers_wanted + 1, .I_b = I_b, .I_w = I_w, .I_c = I_c, .rho_b = rho_b, .rho_w = rho_w,
                .sd_in = sd_in, .fits = fits};
    for (size_t r = 0; r < w.runs; r++) {
        atomic_init(&w.run[r].next, r * parts / w.runs);
        w.run[r].end = (r + 1) * parts / w.runs;
    }
    atomic_init(&w.steps, 0);
    helper_t *given[HELPERS];
    size_t running = 0;
    while (running < helpers_wanted && (given[running] = hand_over(&w, running + 1)) != NULL) running++;
    take_parts(&w, 0, scratch);
    for (size_t t = 0; t < running; t++) collect(given[t]);
    free(scratch);
    long long steps = atomic_load(&w.steps);
    if (steps >= 0 && outputs)
        tm_combine(k, n, fits, underdetermined_alpha_std, underdetermined_g_std, disagree_sigmas, outputs);
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
