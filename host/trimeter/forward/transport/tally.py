"""Tallies of the map tracer and their statistics: sums over paths as polynomials in α and the
background's q, the column's A, B, C from them, their Monte Carlo standard errors, and the sums that
turn each path's terms into those polynomials."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trimeter.model.response import REFERENCE_RHOS, background_response

N_BACKGROUND_ORDERS = 2  # detector paths stop at their 2nd background hit: m = 0 → A, m = 1 → B


@dataclass
class Tally:
    """Sums over paths, as polynomials in α and q (q = ρ/(1 − Cρ) for detector paths): `counts[m, k]`
    holds Σ of the values a path adds to the α^k q^m term (1 for a path that reaches the light; the
    next-event estimate for one that reaches the background), `second[p, s]` Σ of its squared value's
    α^s q^p terms, so that mean and variance of a path's value follow at any (α, ρ). None: every path
    adds at most one term of value 1 (the background paths), so `second` follows from `counts`."""

    counts: np.ndarray                  # (rows, K+1)
    n_paths: int
    weight: float                       # contribution of one path at α = ρ = 1
    specular: float                     # deterministic first-surface reflection (k = m = 0)
    truncated: int                      # paths stopped at K scatterings
    k_max: int
    seconds: float = 0.0
    path_events: int = 0                # loop iterations over all paths (work measure)
    second: np.ndarray | None = None    # (2·rows − 1, 2K+1)
    # Σ over traces of n²·Var(c): the variance of the constant c added to every path's value at
    # α⁰q¹ (a control variate's expectation, estimated from its own samples), as a sum of n²·variances.
    offset_variance: float = 0.0

    def __post_init__(self):
        if self.second is None:
            rows, width = self.counts.shape
            self.second = np.zeros((2 * rows - 1, 2 * width - 1))
            self.second[0::2, 0::2] = self.counts

    def __iadd__(self, other: "Tally") -> "Tally":
        assert self.second is not None and other.second is not None  # filled by __post_init__
        self.counts = _add_padded(self.counts, other.counts)
        self.second = _add_padded(self.second, other.second)
        self.n_paths += other.n_paths
        self.truncated += other.truncated
        self.seconds += other.seconds
        self.path_events += other.path_events
        self.offset_variance += other.offset_variance
        return self

    def _moments(self, alpha):
        """First moments per row m (shape (rows, nα)) and second moments per power p of q (shape
        (2·rows − 1, nα)) of one path's value."""
        assert self.second is not None  # filled by __post_init__
        alpha = np.atleast_1d(np.asarray(alpha, dtype=float))
        with np.errstate(under="ignore"):
            powers = alpha[None, :] ** np.arange(self.second.shape[1])[:, None]   # 0**0 = 1
            first = self.counts @ powers[: self.counts.shape[1]] / self.n_paths * self.weight
            second = self.second @ powers / self.n_paths * self.weight**2
        return first, second

    def orders(self, alpha):
        """Per-row first moments (rows: m = 0, 1 from above; 'returned' from below), the specular
        reflection added to row 0."""
        first, _ = self._moments(alpha)
        first[0] += self.specular
        return first

    def truncation_bound(self, alpha_max: float) -> float:
        """Upper bound on the truncation error of any I (ρ ≤ 1, α ≤ α_max)."""
        return self.weight * alpha_max**self.k_max * self.truncated / self.n_paths


@dataclass
class ColumnTally:
    """One (σt, g) column: paths from the detector (`above`: rows m = 0, 1, …) and, where C has paths
    of its own, paths leaving the background upward (`below`: row 0 = came back to the background).

        A = c0(α),  B = c1(α)  (above),   C = the slab's reflectance seen from the background

    Two ways to C:
    - `below` (the maps' default): C from its own paths. For the ideal geometry that is URU exactly;
      for the device, the stack's response around the optical axis, which overstates every return
      after the first (see the module's docstring).
    - `below` None (a bounce series, device only): the detector paths' own bounce series to `above`'s rows,
      I(ρ) = Σ_m c_m ρ^m (bounce_series), and C the return coefficient that makes A + Bρ/(1 − Cρ)
      equal it at `white_rho`. Where few detector paths reach the background (thick slabs) that C
      is noisy, but there B is small and I hardly depends on C.

    `factorised` (ideal geometry, see the module's docstring): `above` row 1 is UT1 (detector paths that
    reached the background, stopped there), `below` row 1 UTU (background paths that reached the
    light), and B = UT1·UTU."""

    above: Tally
    below: Tally | None
    factorised: bool = False
    white_rho: float = REFERENCE_RHOS[1]

    def __post_init__(self):
        if self.below is None and (self.factorised or self.above.counts.shape[0] < 3):
            raise ValueError("a column without background paths needs detector paths traced to ≥ 3 background "
                             "orders (and is never factorised)")

    def __iadd__(self, other: "ColumnTally") -> "ColumnTally":
        if self.factorised != other.factorised or (self.below is None) != (other.below is None):
            raise ValueError("cannot add column tallies of different kinds (factorised, or C from background "
                             "paths or from the bounce series)")
        if self.white_rho != other.white_rho:
            raise ValueError(f"cannot add column tallies matched at different whites ({self.white_rho} and "
                             f"{other.white_rho})")
        self.above += other.above
        if self.below is not None and other.below is not None:
            self.below += other.below
        return self

    @property
    def parts(self) -> list[Tally]:
        return [self.above] if self.below is None else [self.above, self.below]

    @property
    def n_paths(self) -> int:
        return self.above.n_paths

    @property
    def seconds(self) -> float:
        return sum(t.seconds for t in self.parts)

    @property
    def path_events(self) -> int:
        return sum(t.path_events for t in self.parts)

    @property
    def truncated(self) -> int:
        return sum(t.truncated for t in self.parts)

    def abc(self, alpha) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = self.above.orders(alpha)
        if self.below is None:
            # A + Bρ/(1 − Cρ) = S at ρ = white: Bρ/(1 − Cρ) = S − A, and S − A ≥ Bρ (the later orders are
            # ≥ 0), so C ≥ 0 up to noise; clipped as the measured C is.
            rho = self.white_rho
            excess = self.bounce_series(alpha, rho)[0] - c[0]
            with np.errstate(divide="ignore", invalid="ignore"):
                C = np.where((excess > 0) & (c[1] > 0), (1 - c[1] * rho / excess) / rho, 0.0)
            return c[0], c[1], np.clip(C, 0.0, 0.999)
        below = self.below.orders(alpha)
        C = np.clip(below[0], 0.0, 0.999)
        if self.factorised:
            return c[0], c[1] * below[1], C
        return c[0], c[1], C

    def _factorised_path_variances(self, alpha, rho):
        """Factorised columns: the variance of one detector path's and one background path's value
        towards I(ρ) = A + UT1·UTU·q (q = ρ/(1 − Cρ)). A detector path adds its A term + q·UTU × its UT1
        term; a background path moves I through C (∂I/∂C = B·q²) and UTU (∂I/∂UTU = UT1·q): its value
        is B·q²·(came back) + UT1·q·(reached the light), from `below`'s moments in the formal variable y
        = UT1·q / (B·q²) — spelled out term by term so that neither coefficient may be zero."""
        assert self.below is not None  # a factorised column has background paths (__post_init__)
        A, B, C = self.abc(alpha)
        q = rho / (1 - C * rho)
        ut1, utu = self.above.orders(alpha)[1], self.below.orders(alpha)[1]
        y = q * utu
        f1, f2 = self.above._moments(alpha)
        mean = f1[0] + y * f1[1]
        mean_sq = sum(f2[p] * y**p for p in range(len(f2)))
        var_above = np.maximum(mean_sq - mean * mean, 0.0)
        a, b = B * q * q, ut1 * q
        g1, g2 = self.below._moments(alpha)
        second = a * a * g2[0] + a * b * g2[1] + b * b * g2[2]     # g2[1] = 2·E[came back · reached light]
        var_below = np.maximum(second - (a * g1[0] + b * g1[1]) ** 2, 0.0)
        return var_above, var_below, y

    def stderr(self, alpha, rho):
        """MC standard error of I(ρ) = A + Bρ/(1 − Cρ): the spread of one detector path's value (its
        terms towards A and, × q = ρ/(1 − Cρ), towards B, from `Tally.second`), plus C's own error
        propagated through ∂I/∂C = Bρ²/(1 − Cρ)²."""
        n = self.above.n_paths
        if self.factorised:
            assert self.below is not None  # a factorised column has background paths (__post_init__)
            var_above, var_below, y = self._factorised_path_variances(alpha, rho)
            var_above = var_above / max(n - 1, 1) + (y * self.above.weight) ** 2 * self.above.offset_variance / n**2
            return np.sqrt(var_above + var_below / max(self.below.n_paths - 1, 1))
        if self.below is None:  # the bounce series' error, which the model equals at the white
            return self.bounce_series(alpha, rho)[1]
        A, B, C = self.abc(alpha)
        q = rho / (1 - C * rho)
        var_above = detector_path_variance(self.above, alpha, q) / max(n - 1, 1)
        var_above = var_above + (q * self.above.weight) ** 2 * self.above.offset_variance / n**2
        g1, g2 = self.below._moments(alpha)
        nb = self.below.n_paths
        var_c = np.maximum(g2[0] - g1[0] ** 2, 0.0) / max(nb - 1, 1)
        return np.sqrt(var_above + (B * q * q) ** 2 * var_c)

    def bounce_series(self, alpha, rho) -> tuple[np.ndarray, np.ndarray]:
        """I(ρ) from the detector paths' own background orders: Σ_m c_m(α)ρ^m over the traced orders
        (trace_column(..., background_orders ≥ 3)), continued as a geometric series at the ratio of
        the last two; and its MC std-error from each path's value Σ_m h_m·ρ^m and the control
        variates' own error (at ρ¹; the continuation's factor left out: it is small)."""
        if self.factorised or self.above.counts.shape[0] < 3:
            raise ValueError("bounce_series needs a device column traced to ≥ 3 background orders")
        alpha = np.atleast_1d(np.asarray(alpha, dtype=float))
        c = self.above.orders(alpha)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.clip(np.where(c[-2] > 0, c[-1] / c[-2], 0.0), 0.0, 0.999)
        powers = rho ** np.arange(len(c))[:, None]
        value = (c * powers).sum(axis=0) + c[-1] * powers[-1] * ratio * rho / (1 - ratio * rho)
        n = self.above.n_paths
        variance = detector_path_variance(self.above, alpha, rho) / max(n - 1, 1)
        variance = variance + (rho * self.above.weight) ** 2 * self.above.offset_variance / n**2
        return value, np.sqrt(variance)

    def alpha_stderr(self, alpha, rho_b, rho_w):
        """MC standard error of α read from I(ρ_b), I(ρ_w) at this column's σt and g (g held: the
        column alone has no g derivative): 1/√(Σ_ρ (∂I_ρ/∂α / stderr_ρ)²), ∂/∂α by a central
        difference of the α-polynomials. inf where I does not change with α."""
        alpha = np.asarray(alpha, dtype=np.float64)
        h = 1e-4
        lo, hi = np.maximum(alpha - h, 0.0), np.minimum(alpha + h, float(np.max(alpha)))
        abc_lo, abc_hi = self.abc(lo), self.abc(hi)
        info = 0.0
        for rho in (rho_b, rho_w):
            slope = (background_response(*abc_hi, rho) - background_response(*abc_lo, rho)) / (hi - lo)
            info = info + (slope / np.maximum(self.stderr(alpha, rho), 1e-300)) ** 2
        with np.errstate(divide="ignore"):
            return 1.0 / np.sqrt(info)

    def truncation_bound(self, alpha_max: float) -> float:
        """Bound on the truncation error of I (ρ ≤ 0.99, α ≤ α_max): A and B directly, C amplified."""
        amplify = 1 / (1 - 0.999 * 0.99) ** 2
        below = self.below.truncation_bound(alpha_max) if self.below is not None else 0.0
        return self.above.truncation_bound(alpha_max) * 101 + below * amplify


def detector_path_variance(tally: Tally, alpha, q):
    """Variance of one detector path's value Σ_m h_m·q^m, from its tally's first and second moments:
    towards I(ρ) = A + B·q (q = ρ/(1 − Cρ)) for the model's two rows, the bounce series with q = ρ."""
    f1, f2 = tally._moments(alpha)
    mean = sum(f1[m] * q**m for m in range(len(f1)))
    return np.maximum(sum(f2[p] * q**p for p in range(len(f2))) - mean * mean, 0.0)


# Paths per Dr.Jit launch: its path state costs ~140 bytes per path (a 128M-path launch held 19 GB),


def _add_padded(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    shape = tuple(max(x, y) for x, y in zip(a.shape, b.shape, strict=True))
    out = np.zeros(shape)
    out[: a.shape[0], : a.shape[1]] += a
    out[: b.shape[0], : b.shape[1]] += b
    return out


def background_sums(k, returned, escaped=None):
    """Tally.counts and Tally.second of background paths: each adds α^k to row 0 if it came back and,
    with `escaped` given (factorised columns), to row 1 if it reached the light — never both, so the
    square of a path's value has no cross term."""
    if escaped is None:
        counts = np.bincount(k[returned], minlength=1)[None, :].astype(float)
        second = np.zeros((1, 2 * counts.shape[1] - 1))
        second[0, 0::2] = counts[0]
        return counts, second
    width = int(max(k[returned].max(initial=0), k[escaped].max(initial=0))) + 1
    counts = np.stack([np.bincount(k[flags], minlength=width)[:width] for flags in (returned, escaped)]).astype(float)
    second = np.zeros((3, 2 * width - 1))
    second[0::2, 0::2] = counts
    return counts, second


def add_constant(counts, second, n_paths, value, row):
    """The tallies with `value`·q^row added to every path's value (a control variate's expectation):
    Σ(X + c·q^r) and Σ(X + c·q^r)² = ΣX² + 2c·q^r·ΣX + n·c²·q^2r, as polynomials in α and q."""
    counts, second = counts.copy(), second.copy()
    rows, width = counts.shape
    second[row: row + rows, :width] += 2 * value * counts
    second[2 * row, 0] += n_paths * value * value
    counts[row, 0] += n_paths * value
    return counts, second


def detector_sums(n_paths, terms, orders: int = N_BACKGROUND_ORDERS):
    """Tally.counts and Tally.second of `n_paths` detector paths. A path's value is Σ_j v_j·α^k_j·q^r_j
    over the `terms` it has: (paths, k, v, r) each, the paths (sorted indices) with that term, their
    k, value and row r < `orders` (its own way to the light, and its next-event estimates at its
    bounces); its square is the sum over every pair of its terms (× 2 for two different ones).
    Summed SUMS_CHUNK paths at a time: the temporaries stay small and reuse the same memory (fresh
    pages cost more than the arithmetic on this machine's VMs)."""
    terms = [(np.asarray(paths), np.asarray(k_j), np.asarray(v_j), r_j) for paths, k_j, v_j, r_j in terms]
    width = max(int(k_j[v_j > 0].max(initial=0)) for _, k_j, v_j, _ in terms) + 1
    rows2, width2 = 2 * orders - 1, 2 * width - 1
    counts = np.zeros(orders * width)
    second = np.zeros(rows2 * width2)
    for start in range(0, max(n_paths, 1), SUMS_CHUNK):
        stop = min(start + SUMS_CHUNK, n_paths)
        chunk = []
        for paths, k_j, v_j, r_j in terms:
            lo, hi = np.searchsorted(paths, (start, stop))
            chunk.append((paths[lo:hi] - start, k_j[lo:hi], v_j[lo:hi], r_j[lo:hi] if np.ndim(r_j) else r_j))
        chunk_counts, chunk_second = _detector_sums_chunk(stop - start, chunk, orders, width)
        counts += chunk_counts
        second += chunk_second
    return counts.reshape(orders, width), second.reshape(rows2, width2)


# Paths per step of detector_sums.
SUMS_CHUNK = 1 << 18


def _detector_sums_chunk(n_paths, terms, orders, width):
    """detector_sums' flat counts and second moments for paths 0 … n_paths − 1 (a chunk)."""
    dense, sparse = [], []   # a term over most paths: as arrays over every path; else its nonzero entries
    for paths, k_j, v_j, r_j in terms:
        v_j = np.asarray(v_j, dtype=np.float64)
        k_j, r_j = k_j.astype(np.int64), np.broadcast_to(r_j, v_j.shape).astype(np.int64)
        on = v_j > 0
        if len(v_j) == n_paths and 4 * np.count_nonzero(on) > n_paths:
            # absent entries (value 0) add nothing, wherever their index points
            dense.append((np.where(on, v_j, 0.0), np.where(on, k_j, 0), np.where(on, r_j, 0)))
        else:
            sparse.append((paths[on], k_j[on], v_j[on], r_j[on]))
    rows2, width2 = 2 * orders - 1, 2 * width - 1
    # By np.bincount on flat indices: many times faster than np.add.at, and as exact for 0/1 values.
    counts = np.zeros(orders * width)
    second = np.zeros(rows2 * width2)

    def add(r_a, k_a, v_a, r_b, k_b, v_b, factor):
        nonlocal second
        second += np.bincount((r_a + r_b) * width2 + k_a + k_b, weights=factor * v_a * v_b, minlength=rows2 * width2)

    for i, (v_i, k_i, r_i) in enumerate(dense):
        counts += np.bincount(r_i * width + k_i, weights=v_i, minlength=orders * width)
        for j, (v_j, k_j, r_j) in enumerate(dense[i:]):
            add(r_i, k_i, v_i, r_j, k_j, v_j, 1.0 if j == 0 else 2.0)
    for i, (p_i, k_i, v_i, r_i) in enumerate(sparse):
        counts += np.bincount(r_i * width + k_i, weights=v_i, minlength=orders * width)
        for v_d, k_d, r_d in dense:
            add(r_i, k_i, v_i, r_d[p_i], k_d[p_i], v_d[p_i], 2.0)
        add(r_i, k_i, v_i, r_i, k_i, v_i, 1.0)
        for p_j, k_j, v_j, r_j in sparse[i + 1:]:
            _, a, b = np.intersect1d(p_i, p_j, assume_unique=True, return_indices=True)
            add(r_i[a], k_i[a], v_i[a], r_j[b], k_j[b], v_j[b], 2.0)
    return counts, second

