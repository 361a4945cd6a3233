/* The device table read in place: the v2 reader (every field checked before any array is used) and
 * what the fit evaluates from it at one point. Each function is the numpy reference's operation for
 * operation (trimeter.formats.device_table, trimeter.model.compact, TableInverter.initial_guess,
 * ForwardGrid.inscatter_log1p / model_variance), so that the host build agrees with it to rounding.
 *
 * The CRC-32 is not checked here: the firmware's storage checks it when a slot is written and when
 * it becomes active (map_table_check), and the core is called every few bins, where a pass over
 * 128 KiB would cost more than the fit; the host binding checks it once when it takes the table. */
#include "compact.h"

#include <string.h>

#define HEADER_SIZE 256u
#define DIRECTORY_OFFSET 156u
#define RESERVED_OFFSET 244u
#define ALIGN 8u
#define CODE_MAX R(65535.0)

static const uint8_t MAGIC[8] = {0x89, 'T', 'R', 'L', 'U', 'T', '\r', '\n'};

static uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | p[1] << 8); }
static uint32_t get_u32(const uint8_t *p) {
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}
static float get_f32(const uint8_t *p) {
    uint32_t u = get_u32(p);
    float f;
    __builtin_memcpy(&f, &u, sizeof f); /* a register move, not a freestanding build's byte loop */
    return f;
}

static size_t padded(size_t n) { return (n + ALIGN - 1) / ALIGN * ALIGN; }

/* (R_front, R_back, T) of a stack element; incoherent combination (collimated._combine) */
typedef struct { tr_real r, r_back, t; } stack_t_;

static stack_t_ combine(stack_t_ a, stack_t_ b) {
    tr_real denom = R(1.0) - a.r_back * b.r;
    stack_t_ c = {a.r + a.t * a.t * b.r / denom, b.r_back + b.t * b.t * a.r_back / denom, a.t * b.t / denom};
    return c;
}

static tr_real fresnel(tr_real n1, tr_real n2) {
    tr_real q = (n1 - n2) / (n1 + n2);
    return q * q;
}

/* collimated.stack_transmittance of [1, n, 1] or [1, n_c, n, n_c, 1] with sample transmittance x */
static tr_real stack_transmittance(tr_real n, tr_real cover_n, tr_real x) {
    tr_real idx[5] = {R(1.0), cover_n, n, cover_n, R(1.0)}, inner[3] = {R(1.0), x, R(1.0)};
    int k = cover_n > R(0.0) ? 5 : 3;
    if (k == 3) {
        idx[1] = n;
        idx[2] = R(1.0);
        inner[0] = x;
    }
    tr_real r = fresnel(idx[0], idx[1]);
    stack_t_ e = {r, r, R(1.0) - r};
    for (int i = 0; i < k - 2; i++) {
        stack_t_ layer = {R(0.0), R(0.0), inner[i]};
        e = combine(e, layer);
        r = fresnel(idx[i + 1], idx[i + 2]);
        stack_t_ face = {r, r, R(1.0) - r};
        e = combine(e, face);
    }
    return e.t;
}

static int finite_in(tr_real x, tr_real lo, tr_real hi) { return isfinite(x) && x >= lo && x <= hi; }

/* Finite and strictly increasing. Checked as: both ends finite, every step up (a NaN fails the
 * comparison), so nothing between the ends can be infinite: one comparison per node, which the
 * table check runs on every call. */
static int axis_ok(const float *x, int n) {
    if (!isfinite(x[0]) || !isfinite(x[n - 1])) return 0;
#pragma GCC unroll 4
    for (int i = 1; i < n; i++)
        if (!(x[i] > x[i - 1])) return 0;
    return 1;
}

/* Whether all n values are finite: x·0 is 0 for a finite x and NaN for ±∞ or NaN, and a NaN stays in
 * the sum (one multiply-add per value, no classification) */
static int all_finite(const float *x, size_t n) {
    float zero_if_finite = 0.0f;
#pragma GCC unroll 8
    for (size_t i = 0; i < n; i++) zero_if_finite += x[i] * 0.0f;
    return zero_if_finite == 0.0f;
}

int tr_table_open(const uint8_t *data, size_t len, tr_table *t) {
    const uint16_t one = 1;
    uint8_t first;
    memcpy(&first, &one, 1);
    /* the sections are read in place as float and uint16_t: little-endian, 4-byte aligned memory */
    if (!data || first != 1 || ((uintptr_t)data & 3u) || len < HEADER_SIZE + 4u) return -1;
    if (memcmp(data, MAGIC, sizeof MAGIC) || get_u16(data + 8) != 2 || get_u16(data + 10) != HEADER_SIZE ||
        get_u32(data + 12) != len)
        return -1;
    int counts[8];
    for (int i = 0; i < 8; i++) counts[i] = get_u16(data + 116 + 2 * i);
    static const int least[7] = {4, 4, 3, 2, 2, 2, 2};
    for (int i = 0; i < 7; i++)
        if (counts[i] < least[i]) return -1;
    if (counts[7]) return -1;
    for (size_t i = RESERVED_OFFSET; i < HEADER_SIZE; i++)
        if (data[i]) return -1;
    t->na = counts[0];
    t->ns = counts[1];
    t->ng = counts[2];
    t->n_inv = counts[3];
    t->nu = counts[4];
    t->nt = counts[5];
    t->nv = counts[6];
    /* 64-bit sizes: products of 16-bit counts overflow a 32-bit size_t (the MCU's) */
    const uint64_t na = (uint64_t)t->na, ns = (uint64_t)t->ns, ng = (uint64_t)t->ng, ni = (uint64_t)t->n_inv;
    const uint64_t sizes[TR_SEC_COUNT] = {
        4 * na, 4 * ns, 4 * ng, 4 * 2 * TR_SCALE_COUNT, 2 * ng * na * ns * 3, 2 * na * ns * ng * 2,
        2 * (uint64_t)t->nu * (uint64_t)t->nt * (uint64_t)t->nv, 4 * ns * 6, 2 * ns * ni * ni, 2 * ns * ni * ni,
        get_u32(data + DIRECTORY_OFFSET + 8 * TR_SEC_GEOMETRY + 4)};
    const uint8_t *at[TR_SEC_COUNT];
    uint64_t offset = HEADER_SIZE;
    for (int s = 0; s < TR_SEC_COUNT; s++) {
        if (sizes[s] > len || offset > len - sizes[s]) return -1;
        if (get_u32(data + DIRECTORY_OFFSET + 8 * s) != offset || get_u32(data + DIRECTORY_OFFSET + 8 * s + 4) != sizes[s])
            return -1;
        at[s] = data + offset;
        offset += padded((size_t)sizes[s]);
    }
    if (offset + 4u != len) return -1;
    t->alpha = (const float *)(const void *)at[TR_SEC_ALPHA];
    t->log_sigma_t = (const float *)(const void *)at[TR_SEC_LOG_SIGMA_T];
    t->g = (const float *)(const void *)at[TR_SEC_G];
    t->scales = (const float *)(const void *)at[TR_SEC_SCALES];
    t->spline = (const uint16_t *)(const void *)at[TR_SEC_SPLINE];
    t->model_std = (const uint16_t *)(const void *)at[TR_SEC_MODEL_STD];
    t->inscatter = (const uint16_t *)(const void *)at[TR_SEC_INSCATTER];
    t->inv_frame = (const float *)(const void *)at[TR_SEC_INV_FRAME];
    t->inv_alpha_q = (const uint16_t *)(const void *)at[TR_SEC_INV_ALPHA_Q];
    t->inv_g_q = (const uint16_t *)(const void *)at[TR_SEC_INV_G_Q];
    if (!axis_ok(t->alpha, t->na) || !axis_ok(t->log_sigma_t, t->ns) || !axis_ok(t->g, t->ng)) return -1;
    if (!(t->alpha[0] >= 0.0f && t->alpha[t->na - 1] <= 1.0f && t->g[0] > -1.0f && t->g[t->ng - 1] < 1.0f)) return -1;
    for (int i = 0; i < TR_SCALE_COUNT; i++)
        if (!isfinite(t->scales[2 * i]) || !isfinite(t->scales[2 * i + 1]) || !(t->scales[2 * i + 1] > 0.0f)) return -1;
    for (int i = TR_SCALE_STD_B; i < TR_SCALE_COUNT; i++)
        if (!(t->scales[2 * i] >= 0.0f)) return -1;
    if (!all_finite(t->inv_frame, (size_t)ns * 6)) return -1;
    t->n = R(get_f32(data + 80));
    t->thickness_mm = R(get_f32(data + 84));
    tr_real cover_n = R(get_f32(data + 88));
    t->rho_b_ref = R(get_f32(data + 92));
    t->rho_w_ref = R(get_f32(data + 96));
    t->mc_stderr = R(get_f32(data + 100));
    t->u_max = R(get_f32(data + 104));
    t->tau_max = R(get_f32(data + 108));
    t->v_max = R(get_f32(data + 112));
    if (!finite_in(t->n, R(1.0), R(3.0)) || !finite_in(t->thickness_mm, R(1e-6), R(100.0)) ||
        !finite_in(t->rho_b_ref, R(0.0), R(1.0)) || !finite_in(t->rho_w_ref, R(0.0), R(1.0)) ||
        !finite_in(t->mc_stderr, R(0.0), R(1.0)) || !finite_in(t->u_max, R(1e-6), R(50.0)) ||
        !finite_in(t->tau_max, R(1e-6), R(1e3)) || !finite_in(t->v_max, R(1e-6), R(50.0)) ||
        !(t->rho_b_ref < t->rho_w_ref) || !(cover_n == R(0.0) || finite_in(cover_n, R(1.0), R(3.0))))
        return -1;
    /* stack_constants: T at x = 1 and x = 1/2 (as exp(−ln 2), the reference's evaluation) */
    tr_real t1 = stack_transmittance(t->n, cover_n, R(1.0));
    tr_real th = stack_transmittance(t->n, cover_n, R_EXP(-R_LOG(R(2.0))));
    tr_real b = (R(2.0) * th - t1) / (th / R(2.0) - t1);
    t->stack_a = t1 * (R(1.0) - b);
    t->stack_b = b;
    t->t_max = t1;
    t->t_valid = t1 * (R(1.0) + R(1e-12));
    return 0;
}

/* ------------------------------------------------------------------------------ the forward model */

/* The last node ≤ x of an increasing axis, clipped to [0, n − 2] (searchsorted(side="right") − 1) */
static int last_at_or_below(const float *axis, int n, tr_real x) {
    int lo = 0, len = n;
    while (len > 1) {
        int half = len >> 1;
        if (R(axis[lo + half]) <= x) lo += half;
        len -= half;
    }
    return lo > n - 2 ? n - 2 : lo;
}

/* not-a-knot knot k of nodes x (n of them): x₀ four times, x₂ … x₋₃, x₋₁ four times */
static tr_real knot(const float *x, int n, int k) { return R(x[k <= 3 ? 0 : (k >= n ? n - 1 : k - 2)]); }

/* compact.bspline_basis at one point: the first of the 4 non-zero cubic basis functions, their values
 * N and derivatives dN (de Boor's recurrence) */
static int bspline_basis(const float *x, int n, tr_real xq, tr_real N[4], tr_real dN[4]) {
    xq = tr_clamp(xq, R(x[0]), R(x[n - 1]));
    /* the knot interval: t[k] ≤ x < t[k+1], k in [3, n − 1]; node j ≤ x < node j+1 is knot j + 2 */
    int j = last_at_or_below(x, n, xq);
    if (R(x[n - 1]) <= xq) j = n - 1;
    int i = j + 2 < 3 ? 3 : (j + 2 > n - 1 ? n - 1 : j + 2);
    tr_real kt[8]; /* knots i − 3 … i + 4: the only ones the recurrence and its derivative read */
#pragma GCC unroll 8
    for (int m = 0; m < 8; m++) kt[m] = knot(x, n, i - 3 + m);
#define T(k) kt[(k) - (i - 3)]
    tr_real cur[4] = {R(1.0)}, lower[5] = {R(0.0)};
    /* unrolled: every loop below has a fixed count, so the arrays stay in registers */
#pragma GCC unroll 3
    for (int d = 1; d <= 3; d++) {
        if (d == 3)
            for (int r = 0; r < 3; r++) lower[r + 1] = cur[r];
        tr_real saved = R(0.0), next[4];
#pragma GCC unroll 3
        for (int r = 0; r < d; r++) {
            tr_real right = T(i + r + 1) - xq, left = xq - T(i + r + 1 - d);
            tr_real temp = cur[r] / (right + left);
            next[r] = saved + right * temp;
            saved = left * temp;
        }
        next[d] = saved;
#pragma GCC unroll 4
        for (int r = 0; r <= d; r++) cur[r] = next[r];
    }
    /* dN_r = 3·(q_r − q_{r+1}), q_j = lower_j / (t_{i−3+j+3} − t_{i−3+j}): each quotient serves two
     * functions; lower_0 = lower_4 = 0 */
    tr_real q[5] = {R(0.0), R(0.0), R(0.0), R(0.0), R(0.0)};
#pragma GCC unroll 3
    for (int j = 1; j < 4; j++) {
        int m = i - 3 + j;
        tr_real d = T(m + 3) - T(m);
        q[j] = lower[j] / (d > R(0.0) ? d : R(1.0));
    }
#pragma GCC unroll 4
    for (int r = 0; r < 4; r++) {
        N[r] = cur[r];
        dN[r] = R(3.0) * (q[r] - q[r + 1]);
    }
#undef T
    return i - 3;
}

static int sgn(tr_real x) { return (x > R(0.0)) - (x < R(0.0)); }

/* compact._pchip_slopes on a window of w ≤ 4 g nodes for one component, at the two nodes `at` and
 * `at` + 1 only (the Hermite cubic's ends): slopes d of values y (node spacings 1/inv_h) and their
 * tangents dd (of the tangents dy, in α and ln σt). Divisions by reciprocals taken once: they are
 * most of an evaluation's cost otherwise. */
static inline __attribute__((always_inline)) void pchip_slopes(int w, int at, const tr_real *h, const tr_real *inv_h,
                                                               const tr_real *y, const tr_real dy[2][4], tr_real d[2],
                                                               tr_real dd[2][2]) {
    /* im: 1/m, shared by the two nodes around an interval (∞ at m = 0: unused); sm: sgn(m), likewise.
     * Inlined with w a constant, the loops unroll; the zeros only quieten the compiler's flow analysis. */
    tr_real m[3] = {R(0.0)}, dm[2][3] = {{R(0.0)}}, im[3] = {R(0.0)};
    int sm[3] = {0};
#pragma GCC unroll 3
    for (int i = 0; i < w - 1; i++) {
        m[i] = (y[i + 1] - y[i]) * inv_h[i];
        im[i] = R(1.0) / m[i];
        sm[i] = sgn(m[i]);
#pragma GCC unroll 2
        for (int k = 0; k < 2; k++) dm[k][i] = (dy[k][i + 1] - dy[k][i]) * inv_h[i];
    }
#pragma GCC unroll 2
    for (int out = 0; out < 2; out++) {
        int i = at + out;
        if (i > 0 && i < w - 1) {
            tr_real h0 = h[i - 1], h1 = h[i], w1 = R(2.0) * h1 + h0, w2 = h1 + R(2.0) * h0, m0 = m[i - 1], m1 = m[i];
            d[out] = dd[0][out] = dd[1][out] = R(0.0);
            if (sm[i - 1] == sm[i] && m0 != R(0.0) && m1 != R(0.0)) {
                tr_real im0 = im[i - 1], im1 = im[i], iden = R(1.0) / (w1 * im0 + w2 * im1);
                d[out] = (w1 + w2) * iden;
#pragma GCC unroll 2
                for (int k = 0; k < 2; k++)
                    dd[k][out] = (w1 + w2) * (w1 * dm[k][i - 1] * im0 * im0 + w2 * dm[k][i] * im1 * im1) * iden * iden;
            }
            continue;
        }
        /* one-sided three-point slope at an end of the axis, shape-preserving */
        int a = i ? w - 2 : 0, b = i ? w - 3 : 1;
        tr_real e0 = h[a], e1 = h[b], ma = m[a], mb = m[b], inv_e = R(1.0) / (e0 + e1);
        tr_real de = ((R(2.0) * e0 + e1) * ma - e0 * mb) * inv_e;
        int zero = sgn(de) != sm[a];
        int cap = !zero && sm[a] != sm[b] && R_FABS(de) > R(3.0) * R_FABS(ma);
        d[out] = zero ? R(0.0) : (cap ? R(3.0) * ma : de);
#pragma GCC unroll 2
        for (int k = 0; k < 2; k++) {
            tr_real dde = ((R(2.0) * e0 + e1) * dm[k][a] - e0 * dm[k][b]) * inv_e;
            dd[k][out] = zero ? R(0.0) : (cap ? R(3.0) * dm[k][a] : dde);
        }
    }
}

void tr_sigma_slice_init(const tr_table *t, tr_real log_sigma_t, tr_sigma_slice *slice) {
    slice->first = bspline_basis(t->log_sigma_t, t->ns, log_sigma_t, slice->N, slice->dN);
    slice->window_alpha = slice->window_g = -1;
}

/* One (g node, α row) of the window summed along ln σt with the slice's basis (the codes as they are) */
static inline void contract_row(const tr_table *t, int ia, int first, int w, int r, tr_sigma_slice *sl) {
    const tr_real *Ns = sl->N, *dNs = sl->dN;
    const uint16_t *q = t->spline + (((size_t)(first + w) * (size_t)t->na + (size_t)(ia + r)) * (size_t)t->ns +
                                     (size_t)sl->first) * 3u;
#pragma GCC unroll 3
    for (int c = 0; c < 3; c++) {
        tr_real along = R(0.0), along_d = R(0.0);
#pragma GCC unroll 4
        for (int s = 0; s < 4; s++) {
            tr_real code = R(q[3 * s + c]);
            along += code * Ns[s];
            along_d += code * dNs[s];
        }
        sl->sum[w][r][c] = along;
        sl->sum_d[w][r][c] = along_d;
    }
}

static inline void move_sums(tr_sigma_slice *sl, int w, int r, int from_w, int from_r) {
    for (int c = 0; c < 3; c++) {
        sl->sum[w][r][c] = sl->sum[from_w][from_r][c];
        sl->sum_d[w][r][c] = sl->sum_d[from_w][from_r][c];
    }
}

/* The window (α rows ia …, g nodes first …) summed along ln σt. A Newton step that moves the window
 * along one axis keeps the rows both windows share: those are moved, not summed again (the same sums,
 * so the results do not depend on it); only the new ones are summed. */
static void contract_sigma(const tr_table *t, int ia, int first, int width, tr_sigma_slice *sl) {
    const int da = ia - sl->window_alpha, dg = first - sl->window_g, had = sl->window_alpha >= 0;
    if (had && dg == 0 && da > -4 && da < 4) {
        /* rows r ← r + da, in the order that reads each before it is overwritten */
        for (int k = 0; k < 4; k++) {
            int r = da > 0 ? k : 3 - k, from = r + da;
            for (int w = 0; w < width; w++) {
                if (from >= 0 && from < 4) move_sums(sl, w, r, w, from);
                else contract_row(t, ia, first, w, r, sl);
            }
        }
    } else if (had && da == 0 && dg > -width && dg < width) {
        for (int k = 0; k < width; k++) {
            int w = dg > 0 ? k : width - 1 - k, from = w + dg;
            for (int r = 0; r < 4; r++) {
                if (from >= 0 && from < width) move_sums(sl, w, r, from, r);
                else contract_row(t, ia, first, w, r, sl);
            }
        }
    } else {
        for (int w = 0; w < width; w++)
            for (int r = 0; r < 4; r++) contract_row(t, ia, first, w, r, sl);
    }
    sl->window_alpha = ia;
    sl->window_g = first;
}

/* tr_compact_eval on a window of `width` g nodes: inlined with width a constant (3 or 4), so that its
 * loops unroll and their arrays stay in registers */
static inline __attribute__((always_inline)) void compact_eval(const tr_table *t, tr_real alpha,
                                                               tr_sigma_slice *sigma, tr_real g, tr_abc *out,
                                                               const int width) {
    tr_real Na[4], dNa[4];
    int ia = bspline_basis(t->alpha, t->na, alpha, Na, dNa);
    const int ng = t->ng;
    tr_real gq = tr_clamp(g, R(t->g[0]), R(t->g[ng - 1]));
    int k = last_at_or_below(t->g, ng, gq);
    int first = k - 1 < 0 ? 0 : (k - 1 > ng - width ? ng - width : k - 1);
    if (sigma->window_alpha != ia || sigma->window_g != first) contract_sigma(t, ia, first, width, sigma);
    /* per window node: value and tangents in α and ln σt of A, B, C from the 4 α rows. The codes are
     * summed as they are and decoded once (value = offset + step·code): the basis sums to one and its
     * derivatives to zero, so the offset enters the value alone. */
    tr_real y[3][4], dy[3][2][4], h[3];
#pragma GCC unroll 4
    for (int w = 0; w < width; w++) {
        tr_real v[3] = {R(0.0)}, va[3] = {R(0.0)}, vs[3] = {R(0.0)};
#pragma GCC unroll 4
        for (int r = 0; r < 4; r++)
#pragma GCC unroll 3
            for (int c = 0; c < 3; c++) {
                const tr_real along = sigma->sum[w][r][c], along_d = sigma->sum_d[w][r][c];
                v[c] += Na[r] * along;
                va[c] += dNa[r] * along;
                vs[c] += Na[r] * along_d;
            }
#pragma GCC unroll 3
        for (int c = 0; c < 3; c++) {
            const tr_real off = R(t->scales[2 * c]), step = R(t->scales[2 * c + 1]);
            y[c][w] = off + step * v[c];
            dy[c][0][w] = step * va[c];
            dy[c][1][w] = step * vs[c];
        }
        if (w + 1 < width) h[w] = R(t->g[first + w + 1]) - R(t->g[first + w]);
    }
    tr_real hk = R(t->g[k + 1]) - R(t->g[k]);
    tr_real s = (gq - R(t->g[k])) / hk, s2 = s * s, s3 = s2 * s;
    tr_real h00 = R(2.0) * s3 - R(3.0) * s2 + R(1.0), h10 = s3 - R(2.0) * s2 + s, h01 = R(-2.0) * s3 + R(3.0) * s2,
            h11 = s3 - s2;
    tr_real e00 = (R(6.0) * s2 - R(6.0) * s) / hk, e10 = R(3.0) * s2 - R(4.0) * s + R(1.0),
            e01 = -e00, e11 = R(3.0) * s2 - R(2.0) * s;
    int at = k - first;
    tr_real inv_h[3] = {R(1.0), R(1.0), R(1.0)}; /* width − 1 of them set below; the ones quieten flow analysis */
#pragma GCC unroll 3
    for (int i = 0; i < width - 1; i++) inv_h[i] = R(1.0) / h[i];
#pragma GCC unroll 3
    for (int c = 0; c < 3; c++) {
        tr_real d[2], dd[2][2];
        pchip_slopes(width, at, h, inv_h, y[c], dy[c], d, dd);
        tr_real y0 = y[c][at], y1 = y[c][at + 1];
        out->v[c] = h00 * y0 + h10 * hk * d[0] + h01 * y1 + h11 * hk * d[1];
        out->da[c] = h00 * dy[c][0][at] + h10 * hk * dd[0][0] + h01 * dy[c][0][at + 1] + h11 * hk * dd[0][1];
        out->ds[c] = h00 * dy[c][1][at] + h10 * hk * dd[1][0] + h01 * dy[c][1][at + 1] + h11 * hk * dd[1][1];
        out->dg[c] = e00 * y0 + e10 * d[0] + e01 * y1 + e11 * d[1];
    }
    /* C is a reflectance, and 1 − Cρ must stay positive (compact.C_CLIP) */
    if (out->v[2] < R(0.0) || out->v[2] > R(0.999)) {
        out->v[2] = tr_clamp(out->v[2], R(0.0), R(0.999));
        out->da[2] = out->ds[2] = out->dg[2] = R(0.0);
    }
}

void tr_compact_eval(const tr_table *t, tr_real alpha, tr_sigma_slice *sigma, tr_real g, tr_abc *out) {
    if (t->ng >= 4) compact_eval(t, alpha, sigma, g, out, 4);
    else compact_eval(t, alpha, sigma, g, out, t->ng); /* 3: the reader takes no fewer */
}

/* ------------------------------------------------------------------------------- the other tables */

/* x clamped to [0, hi] for an index, NaN to 0: a table whose numbers overflow gives NaN values, never
 * an index outside it */
static tr_real index_clamp(tr_real x, tr_real hi) { return !(x >= R(0.0)) ? R(0.0) : (x > hi ? hi : x); }

/* ForwardGrid._cell on a float axis: the cell and weight of x, clamped */
static int axis_cell(const float *axis, int n, tr_real x, tr_real *w) {
    int i = last_at_or_below(axis, n, x);
    *w = tr_clamp((x - R(axis[i])) * (R(1.0) / (R(axis[i + 1]) - R(axis[i]))), R(0.0), R(1.0));
    return i;
}

void tr_inverse_guess(const tr_table *t, tr_real log_sigma_t, tr_real I_b, tr_real I_w, tr_real *alpha, tr_real *g) {
    const int ns = t->ns, nx = t->n_inv, ny = t->n_inv;
    tr_real ls = tr_clamp(isnan(log_sigma_t) ? R(t->log_sigma_t[0]) : log_sigma_t, R(t->log_sigma_t[0]),
                          R(t->log_sigma_t[ns - 1]));
    tr_real ws;
    int is = axis_cell(t->log_sigma_t, ns, ls, &ws);
    /* a NaN intensity counts as 0 here (it would index outside the table); the polish then returns NaN */
    tr_real x = R_SQRT(I_b > R(0.0) ? (I_b < R(1.0) ? I_b : R(1.0)) : R(0.0));
    tr_real yq = R_SQRT(I_w > R(0.0) ? (I_w < R(1.0) ? I_w : R(1.0)) : R(0.0));
    tr_real a0 = R(t->alpha[0]), a_span = R(t->alpha[t->na - 1]) - a0;
    tr_real g0 = R(t->g[0]), g_span = R(t->g[t->ng - 1]) - g0;
    tr_real out_a = R(0.0), out_g = R(0.0);
    for (int dk = 0; dk < 2; dk++) {
        int k = is + dk;
        tr_real wk = dk ? ws : R(1.0) - ws;
        const float *fr = t->inv_frame + (size_t)k * 6u;
        tr_real dx = x - R(fr[0]), dyy = yq - R(fr[1]);
        tr_real u = index_clamp(R(fr[2]) * R(nx - 1) * dx + R(fr[3]) * R(nx - 1) * dyy, R(nx - 1));
        tr_real v = index_clamp(R(fr[4]) * R(ny - 1) * dx + R(fr[5]) * R(ny - 1) * dyy, R(ny - 1));
        int iu = (int)u, iv = (int)v;
        if (iu > nx - 2) iu = nx - 2;
        if (iv > ny - 2) iv = ny - 2;
        tr_real fu = u - R(iu), fv = v - R(iv);
        const size_t row = ((size_t)k * (size_t)ny + (size_t)iv) * (size_t)nx + (size_t)iu;
        for (int which = 0; which < 2; which++) {
            const uint16_t *q = which ? t->inv_g_q : t->inv_alpha_q;
            tr_real base = which ? g0 : a0, span = which ? g_span : a_span;
            tr_real v00 = base + span * R(q[row]) / CODE_MAX, v01 = base + span * R(q[row + 1]) / CODE_MAX;
            tr_real v10 = base + span * R(q[row + (size_t)nx]) / CODE_MAX;
            tr_real v11 = base + span * R(q[row + (size_t)nx + 1]) / CODE_MAX;
            tr_real q1 = v01 - v00, q2 = v10 - v00, q3 = v11 - v10 - v01 + v00;
            tr_real value = (v00 + q1 * fu + (q2 + q3 * fu) * fv) * wk;
            if (which) out_g += value;
            else out_a += value;
        }
    }
    *alpha = out_a;
    *g = out_g;
}

static tr_real lerp(tr_real a, tr_real b, tr_real w) { return a + (b - a) * w; }

/* model.cells.regular_cell: cell and weight at p = (x − x0)/step on n evenly spaced nodes. The cell is
 * index_clamp(floor(p), n − 2), taken without floor (a library call on the MCU): NaN and p < 0 give 0,
 * p ≥ n − 2 gives n − 2, and in between the conversion to int truncates, which is floor for p ≥ 0. */
static int regular_cell(tr_real p, int n, tr_real *w) {
    tr_real hi = R(n - 2);
    tr_real f = !(p >= R(0.0)) ? R(0.0) : (p >= hi ? hi : (tr_real)(int)p);
    *w = tr_clamp(p - f, R(0.0), R(1.0));
    return (int)f;
}

/* InscatterTable.log1p_ratio's cells: u = −ln(1 − α) (α ≤ 0.999), τ = σt·ℓ, v = −ln(1 − g) (0 ≤ g ≤ 0.9) */
static int u_cell(const tr_table *t, tr_real alpha, tr_real *w) {
    return regular_cell(-R_LOG1P(-tr_clamp(alpha, R(0.0), R(0.999))) * (R(t->nu - 1) / t->u_max), t->nu, w);
}
static int tau_cell(const tr_table *t, tr_real sigma_t, tr_real *w) {
    return regular_cell(tr_clamp(sigma_t * t->thickness_mm, R(0.0), t->tau_max) * (R(t->nt - 1) / t->tau_max), t->nt, w);
}
static int v_cell(const tr_table *t, tr_real g, tr_real *w) {
    return regular_cell(-R_LOG1P(-tr_clamp(g, R(0.0), R(0.9))) * (R(t->nv - 1) / t->v_max), t->nv, w);
}

/* InscatterTable.log1p_ratio at one material from its cells: trilinear in (u, τ, v), along v first */
static tr_real inscatter_table(const tr_table *t, int iu, tr_real wu, int it, tr_real wt, int iv, tr_real wv) {
    const size_t nt = (size_t)t->nt, nv = (size_t)t->nv;
    const tr_real off = R(t->scales[2 * TR_SCALE_L]), step = R(t->scales[2 * TR_SCALE_L + 1]);
#define L_AT(i, j, k) (off + step * R(t->inscatter[((size_t)(i) * nt + (size_t)(j)) * nv + (size_t)(k)]))
#define ALONG_V(i, j) lerp(L_AT(i, j, iv), L_AT(i, j, iv + 1), wv)
    tr_real value = lerp(lerp(ALONG_V(iu, it), ALONG_V(iu, it + 1), wt), lerp(ALONG_V(iu + 1, it), ALONG_V(iu + 1, it + 1), wt),
                         wu);
#undef ALONG_V
#undef L_AT
    return value;
}

/* The cell of x on an axis refined ×2 (model.cells.refine_axis: the midpoint inserted into every
 * interval, as ForwardGrid.between_nodes refines α and g) and that cell's two nodes */
static tr_real refined_cell(const float *axis, int n, tr_real x, tr_real node[2]) {
    int k = last_at_or_below(axis, n, x);
    tr_real lo = R(axis[k]), hi = R(axis[k + 1]), mid = lo + (hi - lo) * R(0.5);
    if (x >= mid) node[0] = mid, node[1] = hi;
    else node[0] = lo, node[1] = mid;
    return tr_clamp((x - node[0]) * (R(1.0) / (node[1] - node[0])), R(0.0), R(1.0));
}

/* the host resamples the table onto its grid's α and g nodes at the table's own optical depths and
 * interpolates there: the same, on the fly, from the 8 nodes around the point */
void tr_inscatter_cells_init(const tr_table *t, tr_real alpha, tr_real g, tr_inscatter_cells *c) {
    tr_real an[2], gn[2];
    c->wa = refined_cell(t->alpha, t->na, alpha, an);
    c->wg = refined_cell(t->g, t->ng, g, gn);
    for (int k = 0; k < 2; k++) {
        c->iu[k] = u_cell(t, an[k], &c->wu[k]);
        c->iv[k] = v_cell(t, gn[k], &c->wv[k]);
    }
}

tr_real tr_inscatter_log1p_at(const tr_table *t, const tr_inscatter_cells *c, tr_real sigma_t) {
    const int nt = t->nt;
    tr_real tau = sigma_t * t->thickness_mm, wt;
    tau = isfinite(tau) ? tau : R(0.0);
    int it = regular_cell(tr_clamp(tau, R(0.0), t->tau_max) * (R(nt - 1) / t->tau_max), nt, &wt);
    tr_real dt = t->tau_max / R(nt - 1); /* numpy.linspace's step */
    int jt[2];
    tr_real wjt[2];
    for (int k = 0; k < 2; k++) {
        int j = it + k;
        jt[k] = tau_cell(t, (j == nt - 1 ? t->tau_max : R(j) * dt) / t->thickness_mm, &wjt[k]);
    }
    tr_real along_t[2][2];
    for (int da = 0; da < 2; da++)
        for (int k = 0; k < 2; k++)
            along_t[da][k] = lerp(inscatter_table(t, c->iu[da], c->wu[da], jt[k], wjt[k], c->iv[0], c->wv[0]),
                                  inscatter_table(t, c->iu[da], c->wu[da], jt[k], wjt[k], c->iv[1], c->wv[1]), c->wg);
    return lerp(lerp(along_t[0][0], along_t[0][1], wt), lerp(along_t[1][0], along_t[1][1], wt), c->wa);
}

void tr_model_variance(const tr_table *t, tr_real alpha, tr_real log_sigma_t, tr_real g, tr_real *var_b,
                       tr_real *var_w) {
    tr_real wa, ws, wg;
    int ia = axis_cell(t->alpha, t->na, alpha, &wa);
    int is = axis_cell(t->log_sigma_t, t->ns, log_sigma_t, &ws);
    int ig = axis_cell(t->g, t->ng, g, &wg);
    tr_real out[2];
    for (int c = 0; c < 2; c++) {
        const tr_real off = R(t->scales[2 * (TR_SCALE_STD_B + c)]), step = R(t->scales[2 * (TR_SCALE_STD_B + c) + 1]);
        tr_real along_s[2];
        for (int da = 0; da < 2; da++) {
            tr_real along_g[2];
            for (int ds = 0; ds < 2; ds++) {
                const uint16_t *q = t->model_std + (((size_t)(ia + da) * (size_t)t->ns + (size_t)(is + ds)) *
                                                    (size_t)t->ng + (size_t)ig) * 2u + (size_t)c;
                tr_real s0 = off + step * R(q[0]), s1 = off + step * R(q[2]);
                along_g[ds] = lerp(s0 * s0, s1 * s1, wg);
            }
            along_s[da] = lerp(along_g[0], along_g[1], ws);
        }
        out[c] = lerp(along_s[0], along_s[1], wa);
    }
    *var_b = out[0];
    *var_w = out[1];
}
