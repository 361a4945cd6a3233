/* The map's tables read at a point: the inverse table's initial guess, the in-scattering table, the
 * map's error variances, and the forward cells prefetched before the polish. The forward cell lookups
 * and trilinear coefficients themselves are inline in invert_internal.h (every stage uses them). */
#include "invert_internal.h"

/* Where the table's guess at ln σt (already clamped to the forward grid, whose range is the table's) reads:
 * the cells of the two slices bracketing it, and the weights there (TableInverter.initial_guess). */
typedef struct {
    const double *q[2];
    double fu[2], fv[2], w[2];
} guess_cells_t;

static inline guess_cells_t locate_guess(const tm_inverse_table *t, double log_sigma_t, double I_b, double I_w) {
    guess_cells_t c;
    double ws;
    int is = find_cell_on(t->log_sigma_t, t->inv_ds, t->ns, t->uniform_ds, log_sigma_t, &ws);
    /* a NaN intensity counts as 0 here (it would index outside the table); the polish then returns NaN */
    double x = sqrt(I_b > 0.0 ? (I_b < 1.0 ? I_b : 1.0) : 0.0), y = sqrt(I_w > 0.0 ? (I_w < 1.0 ? I_w : 1.0) : 0.0);
    for (int dk = 0; dk < 2; dk++) {
        int k = is + dk;
        c.w[dk] = dk ? ws : 1.0 - ws;
        const double *fr = t->frame + (size_t)k * 6u;
        double dx = x - fr[0], dy = y - fr[1];
        double u = clampd(fr[2] * dx + fr[3] * dy, 0.0, t->nx - 1.0);
        double v = clampd(fr[4] * dx + fr[5] * dy, 0.0, t->ny - 1.0);
        int iu = (int)u, iv = (int)v;
        if (iu > t->nx - 2) iu = t->nx - 2;
        if (iv > t->ny - 2) iv = t->ny - 2;
        c.fu[dk] = u - iu;
        c.fv[dk] = v - iv;
        c.q[dk] = t->cells + (((size_t)k * (size_t)(t->ny - 1) + (size_t)iv) * (size_t)(t->nx - 1) + (size_t)iu) * 8u;
    }
    return c;
}

/* The guess from its cells: bilinear in each slice, blended linearly in ln σt */
static inline void eval_guess(const guess_cells_t *c, double *alpha, double *g) {
    v2d out = {0.0, 0.0}; /* (α, g): the cells hold both side by side, so each step serves both */
    for (int dk = 0; dk < 2; dk++) {
        const double *q = c->q[dk];
        v2d fu = splat2(c->fu[dk]), fv = splat2(c->fv[dk]);
        out += (load2(q) + load2(q + 2) * fu + (load2(q + 4) + load2(q + 6) * fu) * fv) * splat2(c->w[dk]);
    }
    *alpha = out[0];
    *g = out[1];
}

void tmi_initial_guess(const tm_inverse_table *t, double log_sigma_t, double I_b, double I_w,
                          double *alpha, double *g) {
    guess_cells_t c = locate_guess(t, log_sigma_t, I_b, I_w);
    eval_guess(&c, alpha, g);
}

/* Bins per block of tmi_initial_guesses: each block's cells are found and prefetched in one pass before
 * they are read (a bin's cells are random 64 B in a table of a few MB; a pass without dependent loads
 * keeps many misses in flight); its array takes ~1 KB of stack. */
#define GUESS_BLOCK 16

/* tmi_initial_guess for n bins (their cells' ln σt), a block at a time: the same values */
void tmi_initial_guesses(const tm_inverse_table *t, size_t n, const sigma_cell_t *cells, const double *I_b,
                         const double *I_w, double *alpha, double *g) {
    for (size_t j0 = 0; j0 < n; j0 += GUESS_BLOCK) {
        guess_cells_t c[GUESS_BLOCK];
        size_t m = n - j0 < GUESS_BLOCK ? n - j0 : GUESS_BLOCK;
        for (size_t j = 0; j < m; j++) {
            c[j] = locate_guess(t, cells[j0 + j].log_sigma_t, I_b[j0 + j], I_w[j0 + j]);
            __builtin_prefetch(c[j].q[0]);
            __builtin_prefetch(c[j].q[1]);
        }
        for (size_t j = 0; j < m; j++) eval_guess(&c[j], &alpha[j0 + j], &g[j0 + j]);
    }
}

/* Every bin's first forward cell, found (kept as walk_alpha's and walk_g's hints) and prefetched in one pass before
 * the polish: a bin's cell is a random 192 B in a ~22 MB grid, so in a cold cache each first visit
 * is a memory round trip that the polish would otherwise wait on bin by bin. (Prefetching each bin's
 * next cell after every step did not pay.) */
void tmi_prefetch_cells(const tm_forward_grid *f, size_t n, sigma_cell_t *cells, const double *alpha,
                           const double *g) {
    for (size_t i = 0; i < n; i++) {
        double w;
        int ia = alpha_cell(f, alpha[i], &w);
        int ig = g_cell(f, g[i], &w);
        cells[i].ia = ia;
        cells[i].ig = ig;
        const double *P = poly_row(f, ia, cells[i].is, ig);
        __builtin_prefetch(P);
        __builtin_prefetch(P + 8);
        __builtin_prefetch(P + 16);
    }
}

/* The in-scattering table's optical-depth cell for σt (τ clamped to [0, in_tau_max]) and the weight in it */
static inline int inscatter_depth_cell(const tm_forward_grid *f, double sigma_t, double *wt) {
    double p = clampd(sigma_t * f->thickness_mm, 0.0, f->in_tau_max) * f->in_inv_dt;
    double fi = floor(p);
    fi = fi > f->in_nt - 2 ? f->in_nt - 2 : fi;
    *wt = clampd(p - fi, 0.0, 1.0);
    return (int)fi;
}

/* L at node (ia, it) and g node ig; the next g node follows it */
static inline const double *inscatter_at(const tm_forward_grid *f, int ia, int it, int ig) {
    return f->inscatter_L + ((size_t)ia * (size_t)f->in_nt + (size_t)it) * (size_t)f->ng + (size_t)ig;
}

/* (var_b, var_w) at node (ia, is, ig); the next g node's follow them */
static inline const double *model_var_at(const tm_forward_grid *f, int ia, int is, int ig) {
    return f->model_var + (((size_t)ia * (size_t)f->ns + (size_t)is) * (size_t)f->ng + (size_t)ig) * 2u;
}

/* The in-scattering and model-error table cells that tm_fit_solve's per-bin pass will read for a bin (at
 * its polish's last cells and its σt before the correction), prefetched a few bins ahead: like the
 * forward cells, they are random reads in tables of up to a few MB, which a cold cache would otherwise
 * serve bin by bin. The cells may still move by the pass's walk; a missed prefetch costs nothing but
 * its slot. */
void tmi_prefetch_finish(const tm_forward_grid *f, const sigma_cell_t *c, double sigma_t) {
    if (c->ia < 0 || c->ig < 0) return;
    if (f->model_var)
        for (int da = 0; da < 2; da++)
            for (int ds = 0; ds < 2; ds++) __builtin_prefetch(model_var_at(f, c->ia + da, c->is + ds, c->ig));
    if (f->inscatter_L && sigma_t > 0.0) {
        double wt;
        int it = inscatter_depth_cell(f, sigma_t, &wt);
        for (int da = 0; da < 2; da++)
            for (int dt = 0; dt < 2; dt++) __builtin_prefetch(inscatter_at(f, c->ia + da, it + dt, c->ig));
    }
}

/* L = ln(1 + r) of the in-scattered light at (α cell ia/wa, σt, g cell ig/wg):
 * ForwardGrid.inscatter_log1p, operation for operation. Trilinear; τ clamped to [0, in_tau_max]. */
double tmi_inscatter_log1p(const tm_forward_grid *f, int ia, double wa, double sigma_t, int ig, double wg) {
    double wt;
    int it = inscatter_depth_cell(f, sigma_t, &wt);
#define ALONG_G(i, j) lerp(inscatter_at(f, i, j, ig)[0], inscatter_at(f, i, j, ig)[1], wg)
    double value = lerp(lerp(ALONG_G(ia, it), ALONG_G(ia, it + 1), wt),
                        lerp(ALONG_G(ia + 1, it), ALONG_G(ia + 1, it + 1), wt), wa);
#undef ALONG_G
    return value;
}


/* The map's error variances of I_b, I_w at (α, the bin's σt cell, g): trilinear on model_var's nodes,
 * along g, then σt, then α (ForwardGrid.model_variance). */
void tmi_model_variance(const tm_forward_grid *f, const sigma_cell_t *c, double alpha, double g, double *var_b,
                           double *var_w) {
    double wa, wg, ws = c->ws;
    /* from the last evaluation's cells (the solution is at most a step away): find_cell's result for any
     * non-NaN (α, g), without its search */
    int ia = alpha_near(f, alpha, c->ia, &wa), ig = g_near(f, g, c->ig, &wg);
    int is = c->is;
    /* (var_b, var_w) side by side on every node: both interpolated at once */
    v2d along_s[2], Wg = splat2(wg), Ws = splat2(ws);
    for (int da = 0; da < 2; da++) {
        v2d along_g[2];
        for (int ds = 0; ds < 2; ds++) {
            const double *v = model_var_at(f, ia + da, is + ds, ig);
            v2d v0 = load2(v), v1 = load2(v + 2);
            along_g[ds] = v0 + (v1 - v0) * Wg;
        }
        along_s[da] = along_g[0] + (along_g[1] - along_g[0]) * Ws;
    }
    v2d out = along_s[0] + (along_s[1] - along_s[0]) * splat2(wa);
    *var_b = out[0];
    *var_w = out[1];
}

