"""The map's forward model evaluated on the fly from a few kilobytes, as the device's table carries it:
per g node, tensor-product cubic B-spline coefficients in (α, ln σt) of A, B, C; along g, PCHIP
through the g nodes' values at the point.

This is the continuous form of what ForwardGrid.between_nodes samples (not-a-knot cubic splines in
α and ln σt, then PCHIP in g, C clipped to [0, 0.999]) before its trilinear cells: no refined grid is
stored, so a bounded-memory kernel (the MCU's) evaluates one point from a 4 (α) × 4 (ln σt) × 4 (g)
window of coefficients. B-spline coefficients rather than node values: the basis is local and sums
to one, so a coefficient's quantization error moves a value by at most that error.

Imports numpy alone (scipy only to fit the coefficients).
"""

from __future__ import annotations

import numpy as np

DEGREE = 3
C_CLIP = (0.0, 0.999)  # C is a reflectance, and 1 − Cρ must stay positive (as ForwardGrid.refined clips it)


def not_a_knot_knots(x: np.ndarray) -> np.ndarray:
    """The knots of the not-a-knot cubic interpolating spline through nodes x (scipy's default)."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) < DEGREE + 1:
        raise ValueError(f"a cubic spline needs at least {DEGREE + 1} nodes, got {len(x)}")
    return np.r_[(x[0],) * (DEGREE + 1), x[2:-2], (x[-1],) * (DEGREE + 1)]


def spline_coefficients(alpha, log_sigma_t, values: np.ndarray) -> np.ndarray:
    """(ng, na, ns, 3) B-spline coefficients of the not-a-knot spline through `values` (na, ns, ng, 3)
    along α and ln σt."""
    from scipy.interpolate import make_interp_spline

    v = np.asarray(values, dtype=np.float64)
    c = make_interp_spline(np.array(alpha, dtype=np.float64), v, k=DEGREE, axis=0).c
    c = make_interp_spline(np.array(log_sigma_t, dtype=np.float64), c, k=DEGREE, axis=1).c  # (ns, na, ng, 3)
    return np.ascontiguousarray(np.transpose(c, (2, 1, 0, 3)))


def bspline_basis(knots: np.ndarray, n_coef: int, x: np.ndarray):
    """For points x (clamped to the spline's range): the index of the first of the 4 non-zero cubic
    basis functions (N,), their values (4, N) and derivatives (4, N) — de Boor's recurrence."""
    t = knots
    x = np.minimum(np.maximum(np.asarray(x, dtype=np.float64), t[DEGREE]), t[n_coef])
    i = np.clip(np.searchsorted(t, x, side="right") - 1, DEGREE, n_coef - 1)
    N = [np.ones_like(x)]
    for j in range(1, DEGREE + 1):
        if j == DEGREE:
            lower = N  # degree-2 basis, for the derivative
        saved = np.zeros_like(x)
        new = []
        for r in range(j):
            right, left = t[i + r + 1] - x, x - t[i + r + 1 - j]
            temp = N[r] / (right + left)
            new.append(saved + right * temp)
            saved = left * temp
        N = new + [saved]
    # d/dx N_{m,3} = 3 (N_{m,2} / (t_{m+3} − t_m) − N_{m+1,2} / (t_{m+4} − t_{m+1})), m = i − 3 + r
    lower = [np.zeros_like(x)] + lower + [np.zeros_like(x)]
    dN = []
    for r in range(DEGREE + 1):
        m = i - DEGREE + r
        a = lower[r] / np.where(t[m + 3] > t[m], t[m + 3] - t[m], 1.0)
        b = lower[r + 1] / np.where(t[m + 4] > t[m + 1], t[m + 4] - t[m + 1], 1.0)
        dN.append(DEGREE * (a - b))
    return i - DEGREE, np.stack(N), np.stack(dN)


def _pchip_slopes(h: np.ndarray, y: np.ndarray, dy: np.ndarray):
    """scipy's PchipInterpolator node slopes (and their tangents) along axis 0 of y (W, ...), node
    spacings h (W − 1, ...) broadcasting against y's differences; dy (T, W, ...) are tangents of y
    that the slopes' tangents follow. The first and last node take the one-sided three-point slope:
    right at the ends of the g axis, and at a window's ends not needed (see CompactForward.evaluate)."""
    m, dm = np.diff(y, axis=0) / h, np.diff(dy, axis=1) / h
    d, dd = np.zeros_like(y), np.zeros_like(dy)
    h0, h1 = h[:-1], h[1:]
    w1, w2 = 2 * h1 + h0, h1 + 2 * h0
    m0, m1 = m[:-1], m[1:]
    same = (np.sign(m0) == np.sign(m1)) & (m0 != 0) & (m1 != 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = w1 / m0 + w2 / m1
        d[1:-1] = np.where(same, (w1 + w2) / den, 0.0)
        dd[:, 1:-1] = np.where(same, (w1 + w2) * (w1 * dm[:, :-1] / m0 ** 2 + w2 * dm[:, 1:] / m1 ** 2) / den ** 2,
                               0.0)
    for end, (a, b) in ((0, (0, 1)), (-1, (-1, -2))):  # one-sided three-point slopes, shape-preserving
        e0, e1 = h[a], h[b]
        ma, mb, dma, dmb = m[a], m[b], dm[:, a], dm[:, b]
        de = ((2 * e0 + e1) * ma - e0 * mb) / (e0 + e1)
        dde = ((2 * e0 + e1) * dma - e0 * dmb) / (e0 + e1)
        zero = np.sign(de) != np.sign(ma)
        cap = ~zero & (np.sign(ma) != np.sign(mb)) & (np.abs(de) > 3 * np.abs(ma))
        d[end] = np.where(zero, 0.0, np.where(cap, 3 * ma, de))
        dd[:, end] = np.where(zero, 0.0, np.where(cap, 3 * dma, dde))
    return d, dd


class CompactForward:
    """A, B, C of a map at any (α, ln σt, g) from its spline coefficients (see the module docstring)."""

    def __init__(self, alpha, log_sigma_t, g, coefficients):
        self.alpha = np.asarray(alpha, dtype=np.float64)
        self.log_sigma_t = np.asarray(log_sigma_t, dtype=np.float64)
        self.g = np.asarray(g, dtype=np.float64)
        self.coefficients = np.asarray(coefficients, dtype=np.float64)  # (ng, na, ns, 3)
        if self.coefficients.shape != (len(self.g), len(self.alpha), len(self.log_sigma_t), 3):
            raise ValueError(f"coefficients of shape {self.coefficients.shape} do not match the axes "
                             f"({len(self.g)}, {len(self.alpha)}, {len(self.log_sigma_t)}, 3)")
        if len(self.g) < 3:
            raise ValueError("PCHIP along g needs at least 3 g nodes")
        self.knots_alpha = not_a_knot_knots(self.alpha)
        self.knots_sigma = not_a_knot_knots(self.log_sigma_t)

    @classmethod
    def from_nodes(cls, alpha, log_sigma_t, g, values) -> CompactForward:
        """From A, B, C at the map's nodes, (na, ns, ng, 3)."""
        return cls(alpha, log_sigma_t, g, spline_coefficients(alpha, log_sigma_t, values))

    def _at_g_window(self, alpha, log_sigma_t, first, width):
        """(3, width, 3, N): A, B, C at g nodes first … first + width − 1 (per point) and the point's
        (α, ln σt) — value, ∂/∂α, ∂/∂ln σt — from 4 × 4 coefficients per node."""
        ia, Na, dNa = bspline_basis(self.knots_alpha, len(self.alpha), alpha)
        js, Ns, dNs = bspline_basis(self.knots_sigma, len(self.log_sigma_t), log_sigma_t)
        nodes = first + np.arange(width)[:, None]  # (width, N)
        out = np.zeros((3, width, 3, len(ia)))
        for r in range(DEGREE + 1):
            for s in range(DEGREE + 1):
                c = self.coefficients[nodes, ia + r, js + s].transpose(0, 2, 1)  # (width, 3, N)
                out[0] += c * (Na[r] * Ns[s])
                out[1] += c * (dNa[r] * Ns[s])
                out[2] += c * (Na[r] * dNs[s])
        return out

    def evaluate(self, alpha, log_sigma_t, g):
        """A, B, C stacked (3, N) and their derivatives in α, ln σt and g, each (3, N); the point is
        clamped to the map's box. In g cell k the Hermite cubic needs the PCHIP slopes at k and k + 1,
        i.e. the nodes k − 1 … k + 2 (three-point at the axis' ends): a window of 4 g nodes, placed so
        that its own end formulas are used only where they are the axis' ends."""
        alpha, log_sigma_t, g = (np.atleast_1d(np.asarray(x, dtype=np.float64)) for x in (alpha, log_sigma_t, g))
        alpha, log_sigma_t, g = np.broadcast_arrays(alpha, log_sigma_t, g)
        ng = len(self.g)
        gq = np.minimum(np.maximum(g.ravel(), self.g[0]), self.g[-1])
        k = np.clip(np.searchsorted(self.g, gq, side="right") - 1, 0, ng - 2)
        width = min(4, ng)
        first = np.clip(k - 1, 0, ng - width)
        at = self._at_g_window(alpha.ravel(), log_sigma_t.ravel(), first, width)
        y, dy = at[0], at[1:]
        nodes = first + np.arange(width)[:, None]
        h = (self.g[nodes[1:]] - self.g[nodes[:-1]])[:, None, :]  # (width − 1, 1, N)
        slope, dslope = _pchip_slopes(h, y, dy)
        hk = self.g[k + 1] - self.g[k]
        s = (gq - self.g[k]) / hk
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        e00, e10, e01, e11 = (6 * s**2 - 6 * s) / hk, 3 * s**2 - 4 * s + 1, (-6 * s**2 + 6 * s) / hk, 3 * s**2 - 2 * s
        at_k = k - first

        def pick(a):  # (..., width, 3, N) → (..., 3, N) at node k and at node k + 1 per point
            index = at_k.reshape((1,) * (a.ndim - 3) + (1, 1, -1))
            return (np.take_along_axis(a, index, axis=-3)[..., 0, :, :],
                    np.take_along_axis(a, index + 1, axis=-3)[..., 0, :, :])

        y0, y1 = pick(y)
        d0, d1 = pick(slope)
        t0, t1 = pick(dy)
        dt0, dt1 = pick(dslope)
        value = h00 * y0 + h10 * hk * d0 + h01 * y1 + h11 * hk * d1
        tangents = h00 * t0 + h10 * hk * dt0 + h01 * t1 + h11 * hk * dt1  # (2, 3, N): ∂/∂α, ∂/∂ln σt
        d_g = e00 * y0 + e10 * d0 + e01 * y1 + e11 * d1
        clipped = (value[2] < C_CLIP[0]) | (value[2] > C_CLIP[1])
        value[2] = np.clip(value[2], *C_CLIP)
        tangents[:, 2] = np.where(clipped, 0.0, tangents[:, 2])
        d_g[2] = np.where(clipped, 0.0, d_g[2])
        return value, tangents[0], tangents[1], d_g

    def nodes(self) -> np.ndarray:
        """A, B, C at the map's own nodes, (na, ns, ng, 3) (C unclipped: the spline's node values)."""
        ia, Na, _ = bspline_basis(self.knots_alpha, len(self.alpha), self.alpha)
        js, Ns, _ = bspline_basis(self.knots_sigma, len(self.log_sigma_t), self.log_sigma_t)
        out = np.zeros((len(self.alpha), len(self.log_sigma_t), len(self.g), 3))
        for r in range(DEGREE + 1):
            for s in range(DEGREE + 1):
                c = self.coefficients[:, ia + r][:, :, js + s]  # (ng, na, ns, 3)
                out += np.moveaxis(c, 0, 2) * (Na[r][:, None, None, None] * Ns[s][None, :, None, None])
        return out
