"""The fast map tracer: one path-traced batch per (σt, g) serves every α and every background ρ.

Why it works (paper Sec. 5.1, "reusing the Monte Carlo path space samples"): at fixed σt, g
and geometry, free-flight distances, Fresnel choices and scattering directions do not depend on α or
ρ. Everything is sampled proportionally (no weights besides a constant), so a path that reaches the
light after k scattering events and m background bounces contributes w·α^k·ρ^m. We trace adjoint
paths from the detector without α, record each path's final (k, m, reached-the-light), and histogram
them. Then for every α on the map's axis

    c_m(α) = w/N · Σ_k H[m, k] α^k,     A = c0(α),  B = c1(α)

and I(ρ) = A + Bρ/(1 − Cρ) needs C, the slab's reflectance seen from the (Lambertian) background.
In the ideal geometry, where the background forgets directions, C is exactly that: a detector path
stops at its 2nd background hit, and a second set of paths starts on the background,
cosine-distributed upward, and tallies by k those that come back to it, C(α) = Σ_k R[k] α^k / N_b.
The maps use that for the device too. But there light that came back returns less each time (it
spreads over the finite stack and background, and strays further from the panels' view), so a single
C measured from under the detector overstates a white background's I, most in clear samples (figures:
the git history of maps/README.md). The bounce series is the alternative: detector paths go on to
`background_orders` ≥ 3 bounces, I(ρ) = Σ_m c_m(α)ρ^m (the tail geometric), and C is the one return
coefficient that makes the model equal that series at a reference white (ColumnTally.abc): exact there,
and close to it over the whites an instrument uses. The paths are traced to their 2nd bounce as for
the maps, and those that reach it go on in passes of their own, bounce by bounce, each from where the
last pass cut it with its own random stream (so a path is what one unbroken trace would make it, and
the loop carries no per-bounce records). Past the 2nd bounce, Russian roulette with a constant
survival (a weight, not a power of α: the polynomial stays) spares the long diffusion of light that
comes back into a dense sample from below; a pilot sets the survival (continuation_share). It is not
the maps' default yet (its cost: maps/README.md, open points).

No Russian roulette on α (it would break the polynomial): a path is traced until it escapes, is lost
(sides, past the background), or has K scattering events, where α_max^K ≤ `truncation`. The
truncated remainder of a path is worth at most w·α^K per path, so the truncation error of I is
bounded by w·α^K·(fraction of paths truncated); the tally reports that bound.

In the ideal geometry (an unbounded slab over an unbounded Lambertian background) where and how a
detector path reaches the background says nothing about where it goes next, so B = UT1·UTU factorises
(the slab's transmittance for the detector's direction × its diffuse transmittance up to the light):
detector paths stop at their first background hit and tally UT1, the background paths tally UTU
(reached the light) beside C (came back). A detector path's value then carries UTU's expectation
instead of a second 0/1 outcome, which is most of the noise on a white background at α near 1 (the
nodes that set a column's paths). Factorised columns use none of the control variates below: they
replace 0/1 outcomes by their expectation with coefficient 1, which pays where that light dominates
(clear samples at low α) and adds variance where the rest of the light is comparable (α near 1,
the nodes that set a column's paths). The device's finite stack, background and panels do not
factorise: there, detector paths carry on after the bounce as described above (`Stack.factorises`).

Variance reduction, each unbiased: a next-event estimate at each background bounce; control
variates for light that does not depend on α, which dominates the noise of clear samples (a detector
path's straight first pass to the background with its next-event value, and background paths that
come straight back off the stack: exact expectations replace their 0/1 outcomes; in a bounce series, a
detector path's return from its first bounce by one Fresnel reflection: its expected next-event value
given where it bounced replaces the realised one, _returns_control_variate); and, where C comes
from background paths, only as many of them as C's share of the error needs (`below_share`). In the
device, whether a path that leaves the top face meets one of the two panels is the main noise of
every dense column and of light scattered in a clear sample: that 0/1 outcome is replaced by its
average over the path turned about the vertical through its start (`ROTATIONS` turns; exact wherever
the turned copies meet no side face or edge, see rotation_average in `trace`; its gain was measured in
the git history of maps/README.md).

The loop is a Dr.Jit symbolic loop (compiled once, material and seed are opaque inputs; all cores
via the LLVM backend), run in waves that drop finished paths (see `trace`). The
geometry is a layer stack with closed-form plane intersections, which is exact for both presets of
hardware/geometry.toml: `ideal` (one slab, background right under it, light from the whole upper
hemisphere) and `device` (cover slide | sample | cover slide, an air gap, a finite background, two
rectangular Lambertian LED panels, a 2 mm detector spot; reflectance factor normalised by the white
reference: I = π·L / E with E the panels' irradiance at the background plane, as
trimeter.forward.scenes computes it; panels emit radiance 1 and reflect nothing).
The stack's side faces are dielectric (as in the direct-render scene): light trapped in the stack by
total internal reflection leaves through them. A ray leaving one upward counts if it reaches a panel;
one leaving downward goes on through the air to the background, whose rim outside the stack's
footprint is lit by the panels (on a white background, thin weakly scattering samples send much of
their light this way). Rays rising from that rim towards the stack meet its side faces like any other
interface (the stack shades the rim from the far panel), and a next-event estimate from the rim counts
only directions that pass the stack without entering it.
"""

from __future__ import annotations

import functools
import importlib
import math
import os
from dataclasses import dataclass

import numpy as np

from trimeter.errors import InputError
from trimeter.model.response import REFERENCE_RHOS, background_response

N_BACKGROUND_ORDERS = 2  # detector paths stop at their 2nd background hit: m = 0 → A, m = 1 → B


@dataclass(frozen=True)
class Panel:
    center: tuple[float, float, float]
    normal: tuple[float, float, float]      # facing the sample
    axis_u: tuple[float, float, float]
    axis_v: tuple[float, float, float]
    half_u: float
    half_v: float


@dataclass(frozen=True)
class Stack:
    """The layer stack and its surroundings in mm; z up, the sample's top face at z = ℓ (+ slide)."""

    layer_n: tuple[float, ...]              # refractive index of each layer, top → bottom
    plane_z: tuple[float, ...]              # z of the len(layer_n)+1 interfaces, top → bottom
    sample_layer: int
    background_z: float
    stack_half_width: float = math.inf      # lateral half-width of the stack (inf: slab)
    background_half_width: float = math.inf
    panels: tuple[Panel, ...] = ()          # empty: uniform sky of radiance 1 (ideal)
    detector_half_side: float = 0.0        # the detector's spot: a square of the spot's area
    scale: float = 1.0                      # observable per unit of radiance reaching the detector

    @property
    def factorises(self) -> bool:
        """Whether B = UT1·UTU holds exactly: a laterally unbounded stack over an unbounded Lambertian
        background under a uniform sky (the ideal geometry), where the background forgets where and
        from which direction a path arrived."""
        return (not self.panels and not math.isfinite(self.stack_half_width)
                and not math.isfinite(self.background_half_width))

    @classmethod
    def from_recipe(cls, geometry: str, geometry_params: dict, n: float, thickness_mm: float) -> "Stack":
        """The stack in the frame of trimeter.forward.scenes (the direct-render reference): z = 0 is
        the back face of the sample stack, +z points at the detector. Panels, their orientation and
        the white-reference normalisation come from that module, so both agree by construction."""
        if geometry == "ideal":
            gap = float(geometry_params.get("background_gap_mm", 0.0))
            return cls(layer_n=(n,), plane_z=(thickness_mm, 0.0), sample_layer=0, background_z=-gap)
        if geometry != "device":
            raise ValueError(f"unknown geometry {geometry!r}")
        from trimeter.forward.scenes import panel_corners, reflectance_scale
        from trimeter.geometry import cover_slide_n, cover_slide_thickness_mm

        p = geometry_params
        ng = cover_slide_n(p)
        layers: tuple[float, ...]
        planes: tuple[float, ...]
        if ng is not None:
            s = cover_slide_thickness_mm(p)
            layers, planes, sample = (ng, n, ng), (2 * s + thickness_mm, s + thickness_mm, s, 0.0), 1
        else:
            layers, planes, sample = (n,), (thickness_mm, 0.0), 0
        side = float(p["detector"]["spot_diameter_mm"]) * math.sqrt(math.pi) / 2  # square of the spot's area
        return cls(layer_n=layers, plane_z=planes, sample_layer=sample,
                   background_z=-float(p["background_gap_mm"]),
                   stack_half_width=float(p["sample_width_mm"]) / 2,
                   background_half_width=float(p["background_width_mm"]) / 2,
                   panels=tuple(_panel_from_corners(c) for c in panel_corners(p)),
                   detector_half_side=side / 2, scale=float(reflectance_scale(p)))


def _panel_margin(stack: Stack) -> float:
    """How far [mm] the panel's hit point can move when a ray leaves the top of the stack rather than
    going straight on from the background: the refracted ray's sideways offset (at most the stack's
    thickness × the steepest panel direction's tanθ), × 3 for the slant onto the panel, + 1 mm."""
    if not stack.panels:
        return 0.0
    steepest = 0.0
    w = stack.background_half_width if math.isfinite(stack.background_half_width) else 0.0
    for p in stack.panels:
        for su in (-1, 1):
            for sv in (-1, 1):
                corner = [p.center[j] + su * p.half_u * p.axis_u[j] + sv * p.half_v * p.axis_v[j] for j in range(3)]
                for bx in (-w, w):
                    for by in (-w, w):
                        rise = corner[2] - stack.background_z
                        run = math.hypot(corner[0] - bx, corner[1] - by)
                        steepest = max(steepest, run / rise if rise > 0 else math.inf)
    thickness = stack.plane_z[0] - stack.plane_z[-1]
    return 3 * thickness * min(steepest, 20.0) + 1.0


def _panel_from_corners(corners) -> Panel:
    corners = np.asarray(corners, dtype=float)
    centre = corners.mean(axis=0)
    eu, ev = corners[1] - corners[0], corners[3] - corners[0]
    normal = np.cross(eu, ev)
    normal /= np.linalg.norm(normal)
    if normal @ centre > 0:          # face the sample (the origin)
        normal = -normal
    def floats(v):  # plain floats: numpy scalars must not meet Dr.Jit arrays
        return tuple(float(c) for c in v)

    return Panel(floats(centre), floats(normal), floats(eu / np.linalg.norm(eu)), floats(ev / np.linalg.norm(ev)),
                 float(np.linalg.norm(eu)) / 2, float(np.linalg.norm(ev)) / 2)


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
        var_above = _detector_path_variance(self.above, alpha, q) / max(n - 1, 1)
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
        variance = _detector_path_variance(self.above, alpha, rho) / max(n - 1, 1)
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


def _detector_path_variance(tally: Tally, alpha, q):
    """Variance of one detector path's value Σ_m h_m·q^m, from its tally's first and second moments:
    towards I(ρ) = A + B·q (q = ρ/(1 − Cρ)) for the model's two rows, the bounce series with q = ρ."""
    f1, f2 = tally._moments(alpha)
    mean = sum(f1[m] * q**m for m in range(len(f1)))
    return np.maximum(sum(f2[p] * q**p for p in range(len(f2))) - mean * mean, 0.0)


# Paths per Dr.Jit launch: its path state costs ~140 bytes per path (a 128M-path launch held 19 GB),
# so larger requests are traced in chunks of this many and summed. The first chunk keeps the
# request's seed, so any trace of at most this many paths is what it was before chunking.
TRACE_CHUNK = 1 << 24


def trace_column(stack: Stack, sigma_t: float, g: float, n_paths: int, seed: int, k_max: int,
                 below_fraction: float | None = None, backend: str = "llvm",
                 control_variates: bool = True, factorise: bool | None = None,
                 background_orders: int = N_BACKGROUND_ORDERS, white_rho: float = REFERENCE_RHOS[1]) -> ColumnTally:
    """Detector paths for one (σt, g), and for C either (a fraction as many) background paths or the
    detector paths' own later background orders (ColumnTally); seeds derived from `seed`; in chunks of
    at most TRACE_CHUNK paths (memory), chunk i > 0 seeded with _mix64(seed + i).
    `background_orders`: at 2 (the maps'), C comes from background paths; at ≥ 3 (not factorised),
    detector paths go on to that many background bounces with a next-event estimate at each, no
    background paths are traced and C is matched to their bounce series at `white_rho` (A and B are,
    bit for bit, what a trace to 2 orders gives).
    `below_fraction` (background paths) None: as many as minimise the error of I(ρ = 0.9) for the
    work (below_share, from a pilot of 1/16); `control_variates` False: the plain estimator
    (comparisons; factorised columns never use them, see the module's docstring).
    `backend`: "llvm" or "cuda" (resolve_backend); the same seed gives the same paths on either, up to
    the backends' floating-point differences. `factorise` (B = UT1·UTU, see ColumnTally): None = where
    it is exact (Stack.factorises); True elsewhere is an InputError; False: detector paths carry on
    past the background (comparisons)."""
    n_paths = int(n_paths)
    if factorise is None:
        factorise = stack.factorises
    elif factorise and not stack.factorises:
        raise InputError("B = UT1·UTU factorises only for an unbounded slab over an unbounded background "
                         "(the ideal geometry)")
    if not 0 < white_rho <= 1:
        raise InputError(f"white_rho must be within (0, 1], got {white_rho!r}")
    if below_fraction is not None and background_orders > N_BACKGROUND_ORDERS:
        raise InputError("below_fraction sets the background paths, and a bounce series traces none")
    parts = []
    for i, start in enumerate(range(0, max(n_paths, 1), TRACE_CHUNK)):
        n = min(TRACE_CHUNK, n_paths - start)
        s = seed if i == 0 else _mix64(seed + i)
        above = trace(stack, sigma_t, g, n, s, k_max, backend=backend, control_variates=control_variates,
                      factorise=factorise, background_orders=background_orders)
        if background_orders > N_BACKGROUND_ORDERS:
            parts.append(ColumnTally(above, None, white_rho=white_rho))
            continue
        share = below_fraction if below_fraction is not None else 1 / BELOW_PILOT
        below = trace(stack, sigma_t, g, max(1024, int(n * share)), _mix64(s ^ 0xB0B0B0B0), k_max,
                      from_below=True, backend=backend, control_variates=control_variates, factorise=factorise)
        if below_fraction is None:
            more = int(n * below_share(above, below, factorised=factorise)) - below.n_paths
            if more > 0:
                below += trace(stack, sigma_t, g, max(1024, more), _mix64(s ^ 0xB0B0B0B1), k_max, from_below=True,
                               backend=backend, control_variates=control_variates, factorise=factorise)
        parts.append(ColumnTally(above, below, factorised=factorise, white_rho=white_rho))
    total = parts[0]  # the range above has at least one chunk
    for part in parts[1:]:
        total += part
    return total


# Background paths: a pilot of 1/BELOW_PILOT of the detector paths, then as many as below_share says.
BELOW_PILOT = 16


def below_share(above: Tally, below: Tally, rho: float = 0.9, factorised: bool = False) -> float:
    """Background paths per detector path that minimise the variance of I(ρ) for the work: with
    per-path variances s_a² (detector paths' value) and s_c² (C's, × (∂I/∂C)²) and loop iterations e_a,
    e_c per path, N_c/N_a = (s_c/s_a)·√(e_a/e_c) (the largest over α = 0.5 … 0.999), within
    [1/BELOW_PILOT, 1]. Iterations, not seconds, so the count does not depend on the machine's load.
    Clear samples' C is noisy and matters on white; a dense sample's C hardly matters."""
    tally = ColumnTally(above, below, factorised=factorised)
    alpha = np.array([0.5, 0.9, 0.99, 0.999])
    if factorised:
        var_a, var_c, _ = tally._factorised_path_variances(alpha, rho)
    else:
        A, B, C = tally.abc(alpha)
        q = rho / (1 - C * rho)
        var_a = _detector_path_variance(above, alpha, q)
        g1, g2 = below._moments(alpha)
        var_c = np.maximum(g2[0] - g1[0] ** 2, 0.0) * (B * q * q) ** 2
    cost = (above.path_events / max(above.n_paths, 1)) / max(below.path_events / max(below.n_paths, 1), 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(var_c / var_a * cost)
    ratio = float(np.max(np.where(np.isfinite(ratio), ratio, 1.0)))
    return min(max(ratio, 1 / BELOW_PILOT), 1.0)


def _add_padded(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    shape = tuple(max(x, y) for x, y in zip(a.shape, b.shape, strict=True))
    out = np.zeros(shape)
    out[: a.shape[0], : a.shape[1]] += a
    out[: b.shape[0], : b.shape[1]] += b
    return out


def _mix64(x: int) -> int:
    """SplitMix64's finaliser: neighbouring seeds → unrelated 64-bit values."""
    x = (x + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return x ^ (x >> 31)


def k_max_for(alpha_max: float, truncation: float) -> int:
    """Smallest K with α_max^K ≤ truncation."""
    if alpha_max <= 0:
        return 1
    return max(1, math.ceil(math.log(truncation) / math.log(alpha_max)))


# ------------------------------------------------------------------------------------ Dr.Jit part
BACKENDS = ("llvm", "cuda", "auto")


def resolve_backend(name: str = "auto") -> str:
    """The Dr.Jit backend a trace runs on: `llvm` (CPU, all cores), `cuda` (a GPU), or `auto` (CUDA
    when Dr.Jit finds a CUDA device, else LLVM). Asking for `cuda` without one is an InputError."""
    if name not in BACKENDS:
        raise InputError(f"--backend must be one of {', '.join(BACKENDS)}, got {name!r}")
    if name == "llvm":
        return name
    dr = _import_drjit()
    has_cuda = bool(dr.has_backend(dr.JitBackend.CUDA))
    if name == "cuda" and not has_cuda:
        raise InputError("--backend cuda: Dr.Jit finds no CUDA device (driver and GPU) on this machine; "
                         "use --backend llvm or auto")
    return "cuda" if has_cuda else "llvm"


def _import_drjit():
    llvm = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"
    if os.path.exists(llvm):  # the machine's default LLVM aborts at JIT time (docs/platform-notes.md)
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", llvm)
    _keep_freed_memory()
    import drjit as dr
    return dr


def _keep_freed_memory() -> None:
    """Make glibc keep the memory this process frees instead of handing it back to the OS, once per
    process. Why, twice over:
    - Speed: glibc maps every buffer over 32 MB afresh and unmaps it when freed, so each trace's
      per-path arrays (tens of MB) land on fresh pages, and on a virtual machine touching a fresh page
      can cost more than the copy into it (the git history of maps/README.md has the measurement).
    - A segfault inside Dr.Jit's compiled kernels (on its worker thread, in the background-path
      trace that follows a dense column's detector trace: σt = 50/mm, g = 0.9, 8M paths) in processes
      started with MALLOC_TRIM_THRESHOLD_ set, as Dask's nanny does (65536): every large buffer freed
      went back to the OS at once and a later read of it faulted. Our side was ruled out as far as
      tried (one Dr.Jit thread, each wave's gathers evaluated and synchronised before the next, every
      numpy↔Dr.Jit conversion an explicit copy); memory that is never unmapped cannot fault.
    The process keeps its peak footprint (a 16M-path chunk: ~2.5 GB) until it exits."""
    global _MEMORY_KEPT
    if _MEMORY_KEPT:
        return
    _MEMORY_KEPT = True
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc
        return
    m_trim_threshold, m_mmap_max = -1, -4           # glibc's mallopt parameters
    libc.mallopt(m_mmap_max, 0)                      # no mmap'ed chunks: large buffers come from the heap
    libc.mallopt(m_trim_threshold, 1 << 62)          # … and the heap's top is never trimmed


_MEMORY_KEPT = False


def _drjit(backend: str = "llvm"):
    """Dr.Jit and the array module of one backend (drjit.llvm or drjit.cuda), imported lazily: maps
    load and query without Dr.Jit. The only place the array types are chosen."""
    dr = _import_drjit()
    if backend not in ("llvm", "cuda"):
        raise InputError(f"backend must be 'llvm' or 'cuda' (resolve 'auto' first), got {backend!r}")
    return dr, importlib.import_module(f"drjit.{backend}")


def _fresnel(dr, cos_i, eta):
    """Unpolarised Fresnel reflectance for |cos_i| and relative index eta = n_t / n_i; also cos_t."""
    sin2_t = (1 - cos_i * cos_i) / (eta * eta)
    tir = sin2_t >= 1
    cos_t = dr.safe_sqrt(1 - sin2_t)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    F = dr.select(tir, 1.0, 0.5 * (rs * rs + rp * rp))
    return F, cos_t


def _side_entry(dr, half_width, z_bottom, z_top, px, py, pz, dx, dy, dz):
    """Where a ray in the air outside the stack's footprint (|x| or |y| > half_width), rising, meets
    one of the stack's side faces (between z_bottom and z_top): (meets an x face, meets a y face,
    distance). A convex box has one way in, so at most one is true; a ray from under the footprint
    meets the bottom face first, or passes outward. Dr.Jit arrays of one backend."""
    entries = []
    for pos, d, other_pos, other_d in ((px, dx, py, dy), (py, dy, px, dx)):
        face = dr.select(pos > 0, half_width, -half_width)
        t = (face - pos) / d
        zt, ot = pz + t * dz, other_pos + t * other_d
        entries.append(((dr.abs(pos) > half_width) & (pos * d < 0) & (zt >= z_bottom) & (zt <= z_top)
                        & (dr.abs(ot) <= half_width), t))
    (meets_x, t_x), (meets_y, t_y) = entries
    return meets_x, meets_y, dr.select(meets_x, t_x, t_y)


def trace(stack: Stack, sigma_t: float, g: float, n_paths: int, seed: int, k_max: int, wave: int = 48,
          from_below: bool = False, backend: str = "llvm", control_variates: bool = True,
          factorise: bool = False, next_event: bool = True,
          background_orders: int = N_BACKGROUND_ORDERS) -> Tally:
    """Trace `n_paths` adjoint paths from the detector at extinction σt [1/mm] and HG anisotropy g;
    or, `from_below`, paths leaving the background (under the detector spot) cosine-distributed
    upward, tallying those that come back to the background (row 0) — the C coefficient.
    `factorise` (ColumnTally): detector paths stop at the background and tally it in row 1 (UT1);
    background paths also tally those that reach the light, in row 1 (UTU); no control variates.
    `next_event` False (comparisons only): detector paths count their own straight way out instead
    of a next-event estimate at the first bounce (no control variates either, they build on it).
    `background_orders`: detector paths stop at that background bounce (rows m < it; not factorised);
    beyond 2 (a bounce series, with next-event estimates), past their 2nd bounce in passes, with
    roulette (see the module's docstring)."""
    import time

    if background_orders < N_BACKGROUND_ORDERS or (factorise and background_orders != N_BACKGROUND_ORDERS):
        raise InputError(f"background_orders must be ≥ {N_BACKGROUND_ORDERS} (and {N_BACKGROUND_ORDERS} for a "
                         f"factorised column), got {background_orders}")

    dr, B = _drjit(backend)
    Float, UInt32, Bool = B.Float, B.UInt32, B.Bool
    t0 = time.perf_counter()
    control_variates = control_variates and not factorise and next_event
    L = len(stack.layer_n)
    planes = [float(z) for z in stack.plane_z]
    layer_n = [float(v) for v in stack.layer_n]
    sample = stack.sample_layer
    W, WB = stack.stack_half_width, stack.background_half_width
    finite = math.isfinite(W)
    # Opaque: the material is a kernel *input*, so one compiled kernel serves every (σt, g) column
    # (literals would be baked in and force a fresh LLVM compile per column).
    g_is_zero = abs(float(g)) < 1e-4
    sigma_t_value = float(sigma_t)
    sigma_t, g = dr.opaque(Float, float(sigma_t)), dr.opaque(Float, float(g) if not g_is_zero else 0.5)
    max_iter = 8 * k_max + 20000  # TIR bounces between scatterings count too; a safety net only

    def per_layer(li, values):
        out = Float(values[-1])
        for i in range(len(values) - 2, -1, -1):
            out = dr.select(li == i, values[i], out)
        return out

    def sees_panel(p, px, py, pz, dx, dy, dz):
        nx, ny, nz = p.normal
        denom = dx * nx + dy * ny + dz * nz
        t = ((p.center[0] - px) * nx + (p.center[1] - py) * ny + (p.center[2] - pz) * nz) / denom
        hx, hy, hz = px + t * dx - p.center[0], py + t * dy - p.center[1], pz + t * dz - p.center[2]
        u = hx * p.axis_u[0] + hy * p.axis_u[1] + hz * p.axis_u[2]
        v = hx * p.axis_v[0] + hy * p.axis_v[1] + hz * p.axis_v[2]
        return (denom < 0) & (t > 0) & (dr.abs(u) <= p.half_u) & (dr.abs(v) <= p.half_v)

    def light(px, py, pz, dx, dy, dz):
        """Radiance-1 light seen by a ray leaving upward: the sky (ideal) or the panels (device)."""
        if not stack.panels:
            return dz > 0
        seen = Bool(False)
        for p in stack.panels:
            seen |= sees_panel(p, px, py, pz, dx, dy, dz)
        return seen

    def side_entry(px, py, pz, dx, dy, dz):
        return _side_entry(dr, W, planes[-1], planes[0], px, py, pz, dx, dy, dz)

    nee = next_event and not from_below
    margin = _panel_margin(stack)

    def straight_through(px, py, u_a, u_b):
        """Next-event estimate at a background bounce (px, py): the light that leaves the bounce
        upward and reaches the light *straight*, i.e. through every interface of the stack (Fresnel
        transmission, no reflection), unscattered (Beer-Lambert through the sample) and past no side
        face. Device: a direction towards a point drawn uniformly on one panel (chosen by u_a)
        enlarged by `margin`, which holds every point the refracted ray can reach; ideal: a
        cosine-distributed direction. Value = (cos/π)/pdf · transmittance · reached the light."""
        if stack.panels:
            count = len(stack.panels)
            pick = dr.minimum(UInt32(u_a * count), count - 1)
            u_a = u_a * count - Float(pick)
            cx = cy = cz = ux = uy = uz = vx = vy = vz = hu = hv = Float(0.0)
            for i, p in enumerate(stack.panels):
                on = pick == i
                cx, cy, cz = (dr.select(on, p.center[j], c) for j, c in enumerate((cx, cy, cz)))
                ux, uy, uz = (dr.select(on, p.axis_u[j], c) for j, c in enumerate((ux, uy, uz)))
                vx, vy, vz = (dr.select(on, p.axis_v[j], c) for j, c in enumerate((vx, vy, vz)))
                hu, hv = dr.select(on, p.half_u + margin, hu), dr.select(on, p.half_v + margin, hv)
            a, b = (2 * u_a - 1) * hu, (2 * u_b - 1) * hv
            tx, ty, tz = cx + a * ux + b * vx - px, cy + a * uy + b * vy - py, cz + a * uz + b * vz - stack.background_z
            dist2 = tx * tx + ty * ty + tz * tz
            inv = dr.rsqrt(dist2)
            ex, ey, ez = tx * inv, ty * inv, tz * inv
            nx_, ny_, nz_ = (ux * 0, uy * 0, uz * 0)
            for i, p in enumerate(stack.panels):
                on = pick == i
                nx_, ny_, nz_ = (dr.select(on, p.normal[j], c) for j, c in enumerate((nx_, ny_, nz_)))
            cos_panel = dr.maximum(-(ex * nx_ + ey * ny_ + ez * nz_), 1e-6)
            # (cos/π) / pdf_ω, pdf_ω = dist² / (area · cos_panel) / count
            value = ez / math.pi * (4 * hu * hv) * cos_panel / dist2 * count
        else:
            r, phi = dr.sqrt(u_a), 2 * math.pi * u_b
            ex, ey, ez = r * dr.cos(phi), r * dr.sin(phi), dr.safe_sqrt(1 - u_a)
            value = Float(1.0)
        # Through the gap to the stack's bottom face; a ray missing the stack goes straight on.
        to_stack = (planes[-1] - stack.background_z) / ez
        qx, qy = px + to_stack * ex, py + to_stack * ey
        hits_stack = (dr.abs(qx) <= W) & (dr.abs(qy) <= W) if finite else Bool(True)
        sin2 = ex * ex + ey * ey                    # n·sinθ is the same in every layer
        transmit = Float(1.0)
        inside = Bool(True)
        n_before = 1.0
        for layer in range(L - 1, -1, -1):          # bottom layer first
            n_l = layer_n[layer]
            cos_before = dr.safe_sqrt(1 - sin2 / (n_before * n_before))
            F, cos_l = _fresnel(dr, cos_before, n_l / n_before)
            transmit *= 1 - F
            depth = planes[layer] - planes[layer + 1]
            shift = depth / (n_l * cos_l)           # horizontal step per unit of the air direction's (x, y)
            qx, qy = qx + shift * ex, qy + shift * ey
            if layer == sample:
                transmit *= dr.exp(-sigma_t * depth / cos_l)
            if finite:
                inside &= (dr.abs(qx) <= W) & (dr.abs(qy) <= W)
            n_before = n_l
        F, _ = _fresnel(dr, dr.safe_sqrt(1 - sin2 / (n_before * n_before)), 1.0 / n_before)
        transmit *= 1 - F
        qz = dr.select(hits_stack, planes[0], stack.background_z)
        qx, qy = dr.select(hits_stack, qx, px), dr.select(hits_stack, qy, py)
        transmit = dr.select(hits_stack, transmit, 1.0)
        if finite:  # from the rim outside the footprint: a ray into a side face is not straight
            meets_x, meets_y, _ = side_entry(px, py, Float(stack.background_z), ex, ey, ez)
            passes = hits_stack | ~(meets_x | meets_y)
        else:
            passes = Bool(True)
        if stack.panels:
            seen = Bool(False)
            for i, p in enumerate(stack.panels):
                seen |= (pick == i) & sees_panel(p, qx, qy, qz, ex, ey, ez)
        else:
            seen = ez > 0
        return dr.select(seen & (inside | ~hits_stack) & passes & (ez > 0), value * transmit, 0.0)

    # PCG32 streams whose (state, increment) seeds are close are correlated, and the constructor
    # adds the lane index to both: so both seeds are scrambled (SplitMix64) from `seed`.
    rng = B.PCG32(n_paths, initstate=dr.opaque(B.UInt64, _mix64(seed)),
                  initseq=dr.opaque(B.UInt64, _mix64(_mix64(seed) ^ 0x5EED)))
    # Start: just inside the top layer, straight down (the first interface is done in closed form).
    if stack.detector_half_side > 0:
        x = stack.detector_half_side * (2 * rng.next_float32() - 1)
        y = stack.detector_half_side * (2 * rng.next_float32() - 1)
    else:
        x, y = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths)
    k = dr.zeros(UInt32, n_paths)
    if from_below:
        z = dr.full(Float, stack.background_z, n_paths)
        u1, u2 = rng.next_float32(), rng.next_float32()
        r_l, phi0 = dr.sqrt(u1), 2 * math.pi * u2
        dx, dy, dz = r_l * dr.cos(phi0), r_l * dr.sin(phi0), dr.safe_sqrt(1 - u1)
        start_cos = np.asarray(dz, dtype=np.float64) if control_variates else None
        li = dr.full(UInt32, L, n_paths)
        m = dr.full(UInt32, 1, n_paths)          # has left the background once
        orders = 2                                # … and stops when it comes back
    else:
        z = dr.full(Float, planes[0], n_paths)
        dx, dy, dz = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths), dr.full(Float, -1.0, n_paths)
        li = dr.zeros(UInt32, n_paths)
        m = dr.zeros(UInt32, n_paths)
        orders = 1 if factorise else int(background_orders)
    it = dr.zeros(UInt32, n_paths)
    alive = dr.full(Bool, True, n_paths)
    hit = dr.full(Bool, False, n_paths)
    # The first background bounce: scatterings before it, where, two unused random numbers (for its
    # next-event estimate, computed once per path after the loop), and whether the path has gone
    # straight on since (nothing but refraction).
    nee_k = dr.zeros(UInt32, n_paths)
    # A bounce series traces on past the 2nd bounce in passes (go_on, below): its loop state is
    # the 2-order trace's, plus, in the first pass, for the returns' control variate (after the loop),
    # the reflections since the first bounce (NOT_PLAIN once anything but an interface crossing happened).
    series = orders > N_BACKGROUND_ORDERS and nee and not factorise
    returns_cv = control_variates and series
    cv_state = [dr.zeros(UInt32, n_paths)] if returns_cv else []
    bounce_x, bounce_y = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths)
    nee_u, nee_v = dr.zeros(Float, n_paths), dr.zeros(Float, n_paths)
    straight = dr.full(Bool, False, n_paths)
    clean = dr.full(Bool, False, n_paths)   # reached the first bounce straight from the detector
    # For the rotation average of a path's own way to the light (see rotation_average): where it
    # started, how far from there it has been (squared), and whether it left through the top face
    # towards where a light could be (a way out that counts).
    x0, y0 = Float(x), Float(y)
    reach2 = dr.zeros(Float, n_paths)
    escape = dr.full(Bool, False, n_paths)

    # A pass stops its paths at this background bounce (an opaque input: one kernel serves every pass).
    cut_at = [dr.opaque(UInt32, min(orders, N_BACKGROUND_ORDERS) if series else orders)]

    def body(x, y, z, dx, dy, dz, li, k, m, it, alive, hit, nee_k, bounce_x, bounce_y, nee_u, nee_v, straight, clean,
             x0, y0, reach2, escape, *rest):
        cv, rng = list(rest[:-1]), rest[-1]
        it = it + 1
        in_stack = li < L
        in_gap = li == L
        going_down = dz < 0
        # --- inside a layer: next event is a scattering (sample only) or an interface
        z_top = per_layer(li, planes[:-1] + [planes[-1]])
        z_bot = per_layer(li, planes[1:] + [stack.background_z])
        z_plane = dr.select(going_down, z_bot, z_top)
        dist_plane = dr.select(dz != 0, (z_plane - z) / dz, dr.inf)
        u_free = rng.next_float32()
        dist_scatter = dr.select(in_stack & (li == sample), -dr.log(1 - u_free) / sigma_t, dr.inf)
        if finite:
            to_wall_x = dr.select(dx > 0, (W - x) / dx, dr.select(dx < 0, (-W - x) / dx, dr.inf))
            to_wall_y = dr.select(dy > 0, (W - y) / dy, dr.select(dy < 0, (-W - y) / dy, dr.inf))
            dist_wall = dr.minimum(to_wall_x, to_wall_y)
            wall_is_x = to_wall_x <= to_wall_y
        else:
            dist_wall = Float(dr.inf)
            wall_is_x = Bool(True)
        scatter = in_stack & (dist_scatter < dist_plane) & (dist_scatter < dist_wall)
        wall = in_stack & ~scatter & (dist_wall < dist_plane)
        cross = in_stack & ~scatter & ~wall
        step = dr.select(scatter, dist_scatter, dr.select(cross, dist_plane, dr.select(wall, dist_wall, 0.0)))
        x, y = x + step * dx, y + step * dy
        z = dr.select(cross, z_plane, z + step * dz)

        # --- scattering: Henyey-Greenstein in closed form, rotated about the current direction
        u1, u2 = rng.next_float32(), rng.next_float32()
        if g_is_zero:
            cos_t = 1 - 2 * u1
        else:
            sq = (1 - g * g) / (1 - g + 2 * g * u1)
            cos_t = (1 + g * g - sq * sq) / (2 * g)
        cos_t = dr.clip(cos_t, -1.0, 1.0)
        sin_t = dr.safe_sqrt(1 - cos_t * cos_t)
        phi = 2 * math.pi * u2
        sign = dr.select(dz >= 0, 1.0, -1.0)           # Duff et al. 2017 orthonormal basis
        a = -1 / (sign + dz)
        b = dx * dy * a
        s1 = (1 + sign * dx * dx * a, sign * b, -sign * dx)
        s2 = (b, sign + dy * dy * a, -dy)
        cp, sp = sin_t * dr.cos(phi), sin_t * dr.sin(phi)
        ndx = cp * s1[0] + sp * s2[0] + cos_t * dx
        ndy = cp * s1[1] + sp * s2[1] + cos_t * dy
        ndz = cp * s1[2] + sp * s2[2] + cos_t * dz
        k = dr.select(scatter, k + 1, k)

        # --- interface: Fresnel reflect or refract into the neighbour (air outside the stack)
        n_here = per_layer(li, layer_n + [1.0])
        # neighbour below layer li is layer li+1 (air under the last); above it li−1 (air over the
        # first); from the gap going up, the bottom layer
        n_next = dr.select(going_down, per_layer(li, layer_n[1:] + [1.0, 1.0]), per_layer(li, [1.0] + layer_n))
        u_f = rng.next_float32()
        F, cos_tr = _fresnel(dr, dr.abs(dz), n_next / n_here)
        ratio = n_here / n_next
        # --- the gap below the stack: background (going down) or the stack's bottom face (going up)
        dist_bg = dr.select(going_down, (stack.background_z - z) / dz, (planes[-1] - z) / dz)
        gx, gy = x + dist_bg * dx, y + dist_bg * dy
        gap_down = in_gap & going_down
        gap_up = in_gap & ~going_down
        on_bg = gap_down & (dr.abs(gx) <= WB) & (dr.abs(gy) <= WB)
        under_stack = gap_up & (dr.abs(gx) <= W) & (dr.abs(gy) <= W)
        enter_interface = cross | under_stack
        reflect = enter_interface & (u_f < F)
        refract = enter_interface & ~reflect
        if finite:
            # A ray rising from the background's rim (outside the footprint) towards the stack can
            # meet a side face, the more so the thicker the stack: Fresnel-reflected off it (it then
            # rises away, past the stack) or refracted into the layer there. Not straight (see nee).
            meets_x, meets_y, t_side = side_entry(x, y, z, dx, dy, dz)
            side = gap_up & ~under_stack & (meets_x | meets_y)
            sx, sy, sz = x + t_side * dx, y + t_side * dy, z + t_side * dz
            side_li = UInt32(0)
            for i in range(1, L):
                side_li = side_li + dr.select(sz < planes[i], UInt32(1), UInt32(0))
            n_side = per_layer(side_li, layer_n)
            F_s, cos_s = _fresnel(dr, dr.select(meets_x, dr.abs(dx), dr.abs(dy)), n_side)
            side_reflect = side & (u_f < F_s)
            side_in = side & ~side_reflect
            inward_x, inward_y = dr.select(dx > 0, cos_s, -cos_s), dr.select(dy > 0, cos_s, -cos_s)
            side_dx = dr.select(meets_x, dr.select(side_reflect, -dx, inward_x),
                                dr.select(side_reflect, dx, dx / n_side))
            side_dy = dr.select(meets_x, dr.select(side_reflect, dy, dy / n_side),
                                dr.select(side_reflect, -dy, inward_y))
            side_dz = dr.select(side_reflect, dz, dz / n_side)
        else:
            side = side_in = Bool(False)
            sx = sy = sz = side_dx = side_dy = side_dz = Float(0.0)
            side_li = UInt32(0)
        x, y = dr.select(side, sx, dr.select(in_gap, gx, x)), dr.select(side, sy, dr.select(in_gap, gy, y))
        z = dr.select(side, sz, dr.select(gap_down, stack.background_z, dr.select(gap_up, planes[-1], z)))

        # Lambertian background bounce: m += 1, cosine-sampled upward direction
        m = dr.select(on_bg, m + 1, m)
        r_l = dr.sqrt(u1)
        lx, ly, lz = r_l * dr.cos(phi), r_l * dr.sin(phi), dr.safe_sqrt(1 - u1)

        tx, ty = dx * ratio, dy * ratio
        tz = dr.select(going_down, -cos_tr, cos_tr)
        # Side faces of the stack (device): a dielectric layer|air; reflect back in, or leave into air.
        d_norm = dr.select(wall_is_x, dx, dy)
        F_w, cos_w = _fresnel(dr, dr.abs(d_norm), 1.0 / n_here)
        wall_reflect = wall & (u_f < F_w)
        wall_exit = wall & ~wall_reflect
        out_norm = dr.select(d_norm > 0, cos_w, -cos_w)
        wdx = dr.select(wall_reflect, dr.select(wall_is_x, -dx, dx),
                        dr.select(wall_is_x, out_norm, dx * n_here))
        wdy = dr.select(wall_reflect, dr.select(wall_is_x, dy, -dy),
                        dr.select(wall_is_x, dy * n_here, out_norm))
        wdz = dr.select(wall_reflect, dz, dz * n_here)
        new_dx = dr.select(scatter, ndx, dr.select(refract, tx, dr.select(on_bg, lx, dr.select(
            wall, wdx, dr.select(side, side_dx, dx)))))
        new_dy = dr.select(scatter, ndy, dr.select(refract, ty, dr.select(on_bg, ly, dr.select(
            wall, wdy, dr.select(side, side_dy, dy)))))
        new_dz = dr.select(scatter, ndz, dr.select(refract, tz, dr.select(reflect, -dz, dr.select(
            on_bg, lz, dr.select(wall, wdz, dr.select(side, side_dz, dz))))))
        # A ray leaving a side face downward goes on through the air below the stack (the gap's state
        # from wherever it is): it can land on the background's rim outside the stack's footprint.
        wall_down = wall_exit & (wdz < 0)
        new_li = dr.select(refract, dr.select(in_gap, L - 1, dr.select(going_down, li + 1, li - 1)),
                           dr.select(wall_down, L, dr.select(side_in, side_li, li)))

        # --- termination: left through the top (light?), past the stack's edge, lost, or truncated
        out_top = refract & in_stack & ~going_down & (li == 0)
        escaped_up = gap_up & ~under_stack & ~side_in
        reach_light = (out_top | escaped_up | wall_exit) & light(x, y, z, new_dx, new_dy, new_dz)
        cut = on_bg & (m >= cut_at[0])
        lost = (gap_down & ~on_bg) | cut
        done = out_top | escaped_up | (wall_exit & ~wall_down) | lost | (k >= k_max) | (it >= max_iter)
        if nee:
            # The first bounce estimates the straight way out (u_free, u_f are unused at a bounce);
            # the path goes on, and its own straight way out is not counted again.
            first_bounce = alive & on_bg & (m == 1)
            bounce_x, bounce_y = dr.select(first_bounce, x, bounce_x), dr.select(first_bounce, y, bounce_y)
            nee_u, nee_v = dr.select(first_bounce, u_free, nee_u), dr.select(first_bounce, u_f, nee_v)
            nee_k = dr.select(first_bounce, k, nee_k)
            if cv:  # the first pass of a bounce series: it ends at the 2nd bounce, with that count
                counted = dr.minimum(cv[0] + dr.select(reflect, UInt32(1), UInt32(0)), NOT_PLAIN)
                cv = [dr.select(first_bounce, UInt32(0), dr.select(scatter | wall | side, UInt32(NOT_PLAIN), counted))]
            # Every bounce estimates the straight way out: the path's own is counted after none.
            straight = dr.select(alive & on_bg, True, straight & ~(scatter | reflect | wall | side))
            # Straight down needs one iteration per interface and one through the gap; any scattering
            # or reflection on the way adds iterations (a vertical ray meets no side face).
            clean = dr.select(first_bounce, it == L + 1, clean)
            reach_light &= ~straight
            escape = escape | (alive & out_top & ~straight)
        hit = hit | (alive & (cut if from_below and not factorise else reach_light))
        alive = alive & ~done
        reach2 = dr.maximum(reach2, (x - x0) * (x - x0) + (y - y0) * (y - y0))
        return (x, y, z, new_dx, new_dy, new_dz, dr.select(out_top, li, new_li), k, m, it, alive, hit, nee_k,
                bounce_x, bounce_y, nee_u, nee_v, straight, clean, x0, y0, reach2, escape, *cv, rng)

    # Waves: a symbolic loop runs each SIMD packet until its *slowest* lane is done, and path lengths
    # are heavy-tailed; so run WAVE iterations at a time, then keep only the live paths (the kernel
    # is compiled once: the wave limit is an opaque input). A lane's random stream is its own, so
    # the result does not depend on the wave length.
    state = [x, y, z, dx, dy, dz, li, k, m, it, alive, hit, nee_k, bounce_x, bounce_y, nee_u, nee_v, straight, clean,
             x0, y0, reach2, escape, *cv_state, rng]
    slot = {name: i for i, name in enumerate(_LOOP_STATE)}     # then `cv_state`, the random stream
    slot["reflections"] = len(_LOOP_STATE)
    assert len(state) == len(_LOOP_STATE) + len(cv_state) + 1
    ALIVE, IT = slot["alive"], slot["it"]
    averaged = nee and bool(stack.panels) and ROTATIONS > 1 and control_variates   # not in the plain estimator
    safe_radius = min(W, WB)

    def rotation_average(s):
        """A detector path's own way to the light (h = 1 if it reached a panel), averaged over the
        path turned about the vertical through its start by 2πi/ROTATIONS, i = 0…ROTATIONS−1.
        Unbiased (Rao-Blackwell over a rotation group): inside a disc around the axis where the stack
        and background are unbounded for every turned copy (the path and its start within
        min(W, WB) of it), the layers, the Lambertian background and the straight-down start are
        symmetric about any vertical, so each turned copy is as likely as the path itself; only
        the panels break the symmetry, and they are what is averaged. Elsewhere h stays 0/1."""
        px, py, pz, ux, uy, uz = (s[slot[name]] for name in ("x", "y", "z", "dx", "dy", "dz"))
        sx, sy, reach, left = (s[slot[name]] for name in ("x0", "y0", "reach2", "escape"))
        inside = dr.sqrt(sx * sx + sy * sy) + dr.sqrt(reach) < safe_radius
        total = Float(0.0)
        for i in range(ROTATIONS):
            c, sn = math.cos(2 * math.pi * i / ROTATIONS), math.sin(2 * math.pi * i / ROTATIONS)
            rx, ry = sx + c * (px - sx) - sn * (py - sy), sy + sn * (px - sx) + c * (py - sy)
            total += dr.select(light(rx, ry, pz, c * ux - sn * uy, sn * ux + c * uy, uz), 1.0, 0.0)
        return dr.select(left & inside, total / ROTATIONS, dr.select(s[slot["hit"]], 1.0, 0.0))

    # Per lane, what a pass leaves: the path's outcome (and the first pass, its first bounce); a bounce
    # series' passes also leave, for the paths they cut at a bounce, all that a path needs to go on.
    outcome = [("k", np.uint32), ("m", np.uint32), ("it", np.uint32), ("hit", bool)]
    first_bounce_record = [("nee_k", np.uint32), ("bounce_x", np.float32), ("bounce_y", np.float32),
                           ("nee_u", np.float32), ("nee_v", np.float32), ("clean", bool)]
    carried = [(name, np.float32) for name in ("x", "y", "z", "dx", "dy", "dz", "x0", "y0", "reach2")] + [
        ("li", np.uint32)]

    def run(state, recorded, cut_bounce=None, wave_length=wave):
        """Runs the paths of `state` to their end, `wave_length` iterations at a time: each lane's final values
        of `recorded` (name, dtype); with `cut_bounce`, those of `carried` and the random stream too,
        for the lanes that ended cut at that bounce (the others' stay 0)."""
        n = dr.width(state[0])
        lane = dr.arange(UInt32, n)
        final = {name: np.zeros(n, dtype=dtype) for name, dtype in recorded}   # the kernel's own types: no casts
        if averaged:
            final["light"] = np.zeros(n, dtype=np.float32)
        cut_record = {}
        if cut_bounce is not None:
            cut_record = {name: np.zeros(n, dtype=dtype) for name, dtype in carried}
            cut_record.update(rng_state=np.zeros(n, dtype=np.uint64), rng_inc=np.zeros(n, dtype=np.uint64))
        limit = 0
        while True:
            limit += wave_length
            wave_limit = dr.opaque(UInt32, limit)
            state = list(dr.while_loop(tuple(state), lambda *s, bound=wave_limit: s[ALIVE] & (s[IT] < bound), body))
            dr.eval(state)
            alive_now = np.asarray(state[slot["alive"]], dtype=bool)
            # Every lane's values, live or not: a live path's are overwritten in the wave where it ends.
            # (Selecting the finished ones first was as slow as the first wave's kernel on large traces.)
            ids = slice(None) if limit == wave_length else np.asarray(lane, dtype=np.int64)
            for name in final:
                if name in slot:
                    final[name][ids] = np.asarray(state[slot[name]])
            if averaged:
                light_seen = rotation_average(state)
                dr.eval(light_seen)
                final["light"][ids] = np.asarray(light_seen)
            if cut_bounce is not None:   # few lanes, gathered before leaving Dr.Jit
                ended = np.flatnonzero(~alive_now & (final["m"][ids] == cut_bounce))
                if len(ended):
                    lanes = np.arange(n) if isinstance(ids, slice) else ids
                    at = UInt32(ended.astype(np.uint32))
                    sources = [state[slot[name]] for name, _ in carried] + [state[-1].state, state[-1].inc]
                    gathered = [dr.gather(type(v), v, at) for v in sources]
                    dr.eval(gathered)           # one kernel for all
                    for name, values in zip([name for name, _ in carried] + ["rng_state", "rng_inc"], gathered,
                                            strict=True):
                        cut_record[name][lanes[ended]] = np.asarray(values)
            if not alive_now.any():
                return final, cut_record
            keep = UInt32(np.flatnonzero(alive_now).astype(np.uint32))
            rng_old = state[-1]
            rng_new = B.PCG32(rng_old)
            rng_new.state = dr.gather(B.UInt64, rng_old.state, keep)
            rng_new.inc = dr.gather(B.UInt64, rng_old.inc, keep)
            state = [dr.gather(type(v), v, keep) for v in state[:-1]] + [rng_new]
            lane = dr.gather(UInt32, lane, keep)

    final, cut_record = run(state, outcome + first_bounce_record + ([("reflections", np.uint32)] if returns_cv else []),
                            N_BACKGROUND_ORDERS if series else None)
    it_total, over_iter = final["it"].astype(np.int64), final["it"] >= max_iter

    def go_on(paths, record, k_at, m_at):
        """A bounce series: `paths`, cut at a bounce with `record` (their `carried` values and random
        streams) and (k, m), go on from there, pass by pass, each with its own random stream (so a
        path is what one unbroken trace would make it) to the next bounce, until `orders`. Their
        outcomes go into `final`, their iterations into it_total; returns, per bounce after the cut,
        the paths that reached it, where and k."""
        reached = []
        while len(paths):
            n, bounce = len(paths), int(m_at[0])
            rng = B.PCG32(n)
            rng.state, rng.inc = B.UInt64(record["rng_state"]), B.UInt64(record["rng_inc"])
            start = {name: (UInt32 if dtype == np.uint32 else Float)(record[name]) for name, dtype in carried}
            start.update(k=UInt32(k_at), m=UInt32(m_at), it=dr.zeros(UInt32, n), alive=dr.full(Bool, True, n),
                         hit=dr.full(Bool, False, n), straight=dr.full(Bool, True, n), clean=dr.full(Bool, False, n),
                         escape=dr.full(Bool, False, n), nee_k=dr.zeros(UInt32, n),   # the first bounce's: unused
                         **{name: dr.zeros(Float, n) for name in ("bounce_x", "bounce_y", "nee_u", "nee_v")})
            cut_at[0] = dr.opaque(UInt32, bounce + 1)
            # few paths: longer waves, fewer of each wave's fixed costs (tracing the loop, launching it)
            current, next_record = run([start[name] for name in _LOOP_STATE] + [rng], outcome,
                                       bounce + 1 if bounce + 1 < orders else None, LATER_WAVES * wave)
            for name in ("k", "m", "hit", "light"):
                if name in current:
                    final[name][paths] = current[name]
            it_total[paths] += current["it"]
            over_iter[paths] |= current["it"] >= max_iter
            if bounce + 1 >= orders:
                break
            cut = np.flatnonzero(current["m"] == bounce + 1)
            paths, k_at, m_at = paths[cut], current["k"][cut], current["m"][cut]
            record = {name: values[cut] for name, values in next_record.items()}
            reached.append((paths, record["x"], record["y"], k_at))
        return reached

    k_np, m_np, hit_np = final["k"], final["m"], final["hit"]
    if from_below:
        truncated = int(np.count_nonzero((k_np >= k_max) | over_iter))
        # factorised: `hit` is "reached the light", and a path came back iff it met the background again
        if factorise:
            counts, second = _background_sums(k_np, m_np >= 2, hit_np)
        else:
            counts, second = _background_sums(k_np, hit_np)
        if start_cos is not None:  # control variates on
            # The light the stack's interfaces send straight back (no scattering, few reflections):
            # its expectation is a 1-D integral, so those paths' 0/1 outcomes are replaced by it.
            min_cos, expected = _plain_return(stack, sigma_t_value)
            plain = hit_np & (k_np == 0) & (it_total <= PLAIN_RETURN_ITERATIONS) & (start_cos >= min_cos)
            counts, second = _background_sums(k_np, hit_np & ~plain)
            counts, second = _add_constant(counts, second, n_paths, expected, row=0)
        return Tally(counts=counts, n_paths=n_paths, weight=1.0, specular=0.0, truncated=truncated, k_max=k_max,
                     seconds=time.perf_counter() - t0, path_events=int(it_total.sum()), second=second)
    bounced = np.flatnonzero(m_np >= 1)
    nee_value = np.zeros(n_paths)
    if factorise:  # each path that reached the background adds 1 to UT1 at its scatterings so far
        truncated = int(np.count_nonzero((k_np >= k_max) | over_iter))
        every = np.arange(n_paths)
        counts, second = _detector_sums(n_paths, [(every, k_np, np.where(m_np < 1, hit_np, 0.0), m_np),
                                                  (every, final["nee_k"], np.where(m_np >= 1, 1.0, 0.0), 1)])
        r0 = ((layer_n[0] - 1.0) / (layer_n[0] + 1.0)) ** 2
        return Tally(counts=counts, n_paths=n_paths, weight=(1 - r0) * stack.scale, specular=r0 * stack.scale,
                     truncated=truncated, k_max=k_max, seconds=time.perf_counter() - t0,
                     path_events=int(it_total.sum()), second=second)
    if nee and len(bounced):
        value = straight_through(*(Float(final[name][bounced]) for name in ("bounce_x", "bounce_y", "nee_u", "nee_v")))
        nee_value[bounced] = np.asarray(value, dtype=np.float64)
    offset_variance = 0.0
    if control_variates:
        # Most detector paths of a clear sample go straight down to the background; whether one does
        # (a Fresnel or free-flight draw) and its next-event value are noise that does not depend on α.
        # Their estimates are replaced by the exact probability of that first pass × the mean
        # next-event value from fresh samples of the same estimator (control variate, unbiased).
        nee_value = np.where(final["clean"], 0.0, nee_value)
        clean_pass = _clean_pass_probability(stack, sigma_t_value)
        replicas = []
        for points in _nee_points(seed, n_paths):
            if stack.detector_half_side > 0:
                sx, sy = (Float(stack.detector_half_side * (2 * points[:, i] - 1)) for i in (0, 1))
            else:
                sx, sy = dr.zeros(Float, len(points)), dr.zeros(Float, len(points))
            value = straight_through(sx, sy, Float(points[:, 2]), Float(points[:, 3]))
            replicas.append(float(np.mean(np.asarray(value, dtype=np.float64))))
        fresh_mean = float(np.mean(replicas))
        offset_variance = (clean_pass * n_paths) ** 2 * float(np.var(replicas, ddof=1)) / len(replicas)
    every = np.arange(n_paths)
    terms = [(every, final["nee_k"], nee_value, 1)]

    def next_events(at, x, y, bounce):
        # Direction samples of their own (any independent uniforms will do), seeded from the trace's.
        if not len(at):
            return np.zeros(0)
        u, v = np.random.default_rng([seed, 0x4E45, bounce - 2]).random((2, len(at)), dtype=np.float32)
        return np.asarray(straight_through(Float(x), Float(y), Float(u), Float(v)), dtype=np.float64)

    own = final["light"] if averaged else hit_np
    if series:
        # The 2nd bounce: its next-event estimate (with the returns' control variate), for every path
        # that reached it.
        at = np.flatnonzero(m_np == N_BACKGROUND_ORDERS)
        value = next_events(at, cut_record["x"][at], cut_record["y"][at], N_BACKGROUND_ORDERS)
        if returns_cv:
            value, expected = _returns_control_variate(dr, B, stack, sigma_t_value, seed, straight_through, final,
                                                       cut_record, at, value)
            terms.append((every, final["nee_k"], expected, N_BACKGROUND_ORDERS))
        terms.append((at, k_np[at], value, N_BACKGROUND_ORDERS))
        first = [*terms, (every, k_np.copy(), np.where(m_np < N_BACKGROUND_ORDERS, own, 0.0), m_np.copy())]
        first_iterations = int(it_total.sum())
        # Past the 2nd bounce, Russian roulette (a constant weight, no α in it: the polynomial stays):
        # light that comes back into a dense sample from below diffuses for thousands of scatterings
        # and hardly changes I. A pilot, 1 in CONTINUATION_PILOT of the paths there, always goes on;
        # from its cost and spread (continuation_share) the others go on with a probability p and
        # weight 1/p. The pilot's outcomes decide only the others' p: unbiased.
        draw = np.random.default_rng([seed, 0x5255]).random(len(at))
        pilot = draw < 1 / CONTINUATION_PILOT
        weight = np.ones(n_paths)

        def go_on_from_the_second(chosen):
            return go_on(chosen, {name: values[chosen] for name, values in cut_record.items()}, k_np[chosen],
                         m_np[chosen])

        reached = [go_on_from_the_second(at[pilot])]      # per group, per bounce 3 …: (paths, x, y, k)
        later_terms = [(at[pilot], k_np[at[pilot]], own[at[pilot]], m_np[at[pilot]])]
        for j, (p_j, x_j, y_j, k_j) in enumerate(reached[0]):
            later_terms.append((p_j, k_j, next_events(p_j, x_j, y_j, N_BACKGROUND_ORDERS + 1 + j),
                                N_BACKGROUND_ORDERS + 1 + j))
        share = continuation_share(n_paths, first, first_iterations, later_terms,
                                   int(it_total.sum()) - first_iterations, orders)
        others = at[~pilot & (draw < share)]
        if len(others):
            weight[others] = (1 - 1 / CONTINUATION_PILOT) / (share - 1 / CONTINUATION_PILOT)
        reached.append(go_on_from_the_second(others))
        own = np.where(m_np >= N_BACKGROUND_ORDERS, own * weight, own)   # the paths that went on (others': 0)
        for j in range(orders - N_BACKGROUND_ORDERS - 1):     # bounces 3 … orders − 1, both groups, in path order
            parts = [group[j] for group in reached if len(group) > j]
            p_j, x_j, y_j, k_j = (np.concatenate([part[i] for part in parts]) for i in range(4))
            order = np.argsort(p_j, kind="stable")
            p_j, x_j, y_j, k_j = p_j[order], x_j[order], y_j[order], k_j[order]
            terms.append((p_j, k_j, next_events(p_j, x_j, y_j, N_BACKGROUND_ORDERS + 1 + j) * weight[p_j],
                          N_BACKGROUND_ORDERS + 1 + j))
    terms.append((every, k_np, np.where(m_np < orders, own, 0.0), m_np))
    truncated = int(np.count_nonzero((k_np >= k_max) | over_iter))
    counts, second = _detector_sums(n_paths, terms, orders)
    if control_variates:
        counts, second = _add_constant(counts, second, n_paths, clean_pass * fresh_mean, row=1)

    # First interface (air → top layer) at normal incidence, in closed form.
    r0 = ((layer_n[0] - 1.0) / (layer_n[0] + 1.0)) ** 2
    specular = r0 * stack.scale if not stack.panels else 0.0  # the device's detector sees no panel specularly
    return Tally(counts=counts, n_paths=n_paths, weight=(1 - r0) * stack.scale, specular=specular,
                 truncated=truncated, k_max=k_max, seconds=time.perf_counter() - t0,
                 path_events=int(it_total.sum()), second=second, offset_variance=offset_variance)


# A bounce series' count of reflections since the last bounce once it stopped being plain.
NOT_PLAIN = 255

# The symbolic loop's state, in `body`'s argument order (then, in a bounce series' first pass, its
# count of reflections since the first bounce; then the random stream).
_LOOP_STATE = ("x", "y", "z", "dx", "dy", "dz", "li", "k", "m", "it", "alive", "hit", "nee_k", "bounce_x", "bounce_y",
               "nee_u", "nee_v", "straight", "clean", "x0", "y0", "reach2", "escape")

# A path's own way to the light is averaged over this many turns of the path (see rotation_average
# in trace); 1: not averaged.
ROTATIONS = 32

# Independent randomisations of the quasi-random points that estimate the mean next-event value of
# the straight first pass (their spread gives that estimate's variance).
NEE_REPLICAS = 8


def _nee_points(seed: int, n_paths: int) -> list[np.ndarray]:
    """NEE_REPLICAS sets of 4-D points (detector x, y; light u, v) in [0, 1): scrambled Sobol, each
    set a power of two of about n_paths / 64 points (≥ 4096), seeded from `seed`. float32 values, < 1."""
    from scipy.stats import qmc

    size = max(12, min(20, round(math.log2(max(n_paths, 1) / 64))))
    below_one = np.float32(1 - 2**-24)
    return [np.minimum(qmc.Sobol(4, scramble=True, seed=np.random.default_rng([seed, 0xC1EA2, r]))
                       .random_base2(size).astype(np.float32), below_one) for r in range(NEE_REPLICAS)]


def _background_sums(k, returned, escaped=None):
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


def _add_constant(counts, second, n_paths, value, row):
    """The tallies with `value`·q^row added to every path's value (a control variate's expectation):
    Σ(X + c·q^r) and Σ(X + c·q^r)² = ΣX² + 2c·q^r·ΣX + n·c²·q^2r, as polynomials in α and q."""
    counts, second = counts.copy(), second.copy()
    rows, width = counts.shape
    second[row: row + rows, :width] += 2 * value * counts
    second[2 * row, 0] += n_paths * value * value
    counts[row, 0] += n_paths * value
    return counts, second


def _clean_pass_probability(stack: Stack, sigma_t: float) -> float:
    """Probability that a detector path, past the top face, crosses every interface straight down
    without a Fresnel reflection and the sample without scattering (normal incidence)."""
    indices = [float(n) for n in stack.layer_n] + [1.0]
    p = 1.0
    for above, below in zip(indices[:-1], indices[1:], strict=True):
        p *= 1 - ((above - below) / (above + below)) ** 2
    depth = stack.plane_z[stack.sample_layer] - stack.plane_z[stack.sample_layer + 1]
    return p * math.exp(-sigma_t * depth)


# A background path that returns unscattered within this many loop iterations (a few reflections
# inside the stack) is a "plain return", replaced by its expectation (see _plain_return).
PLAIN_RETURN_ITERATIONS = 24


def _plain_return(stack: Stack, sigma_t: float) -> tuple[float, float]:
    """(μ_min, E): background paths leaving at cosθ ≥ μ_min that return unscattered within
    PLAIN_RETURN_ITERATIONS iterations never meet a side face or the background's edge (their sideways
    travel is bounded), so the probability of that return is the same as for an infinite stack; E is
    its expectation over the cosine-distributed start, ∫ P(μ) 2μ dμ over [μ_min, 1], P from the
    layers' Fresnel reflectances and the sample's Beer-Lambert attenuation, iteration by iteration."""
    n_layers = len(stack.layer_n)
    layer_n = np.array(stack.layer_n, dtype=float)
    depth = -np.diff(np.asarray(stack.plane_z, dtype=float))
    gap = stack.plane_z[-1] - stack.background_z
    reach = min(stack.stack_half_width, stack.background_half_width) - stack.detector_half_side
    steps = PLAIN_RETURN_ITERATIONS

    def sideways(tan_air):  # an upper bound on the travel of such a path, the gap crossed twice
        sin_air = tan_air / math.sqrt(1 + tan_air * tan_air)
        sin_l = sin_air / layer_n
        return 2 * gap * tan_air + (steps - 2) * float(np.max(depth * sin_l / np.sqrt(1 - sin_l * sin_l)))

    if not math.isfinite(reach):
        min_cos = 0.0
    else:
        lo, hi = 0.0, 1e6
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if sideways(mid) <= reach else (lo, mid)
        min_cos = 1 / math.sqrt(1 + lo * lo)
    nodes, weights = _gauss_legendre()
    mu = min_cos + (1 - min_cos) * (nodes + 1) / 2
    weights = weights * (1 - min_cos) / 2
    sin2 = 1 - mu * mu
    cos_l = np.sqrt(1 - sin2[None, :] / layer_n[:, None] ** 2)        # (layer, μ)
    survive = np.ones_like(cos_l)
    survive[stack.sample_layer] = np.exp(-sigma_t * depth[stack.sample_layer] / cos_l[stack.sample_layer])
    media = np.concatenate([[1.0], layer_n, [1.0]])
    cos_media = np.vstack([mu, cos_l, mu])
    # interface i lies between medium i (above) and i + 1 (below); F is the same from either side
    fresnel = np.array([_fresnel_np(cos_media[i], media[i + 1] / media[i]) for i in range(n_layers + 1)])
    up, down = np.zeros((n_layers + 1, len(mu))), np.zeros((n_layers + 1, len(mu)))   # index n_layers: the gap
    up[n_layers] = 1.0
    returned = np.zeros(len(mu))
    for _ in range(steps):
        returned += down[n_layers]
        new_up, new_down = np.zeros_like(up), np.zeros_like(down)
        new_down[n_layers] += up[n_layers] * fresnel[n_layers]
        new_up[n_layers - 1] += up[n_layers] * (1 - fresnel[n_layers])
        for layer in range(n_layers):
            going_down, going_up = down[layer] * survive[layer], up[layer] * survive[layer]
            new_up[layer] += going_down * fresnel[layer + 1]
            new_down[layer + 1] += going_down * (1 - fresnel[layer + 1])
            new_down[layer] += going_up * fresnel[layer]
            if layer > 0:
                new_up[layer - 1] += going_up * (1 - fresnel[layer])
        up, down = new_up, new_down
    return min_cos, float(np.sum(weights * returned * 2 * mu))


@functools.cache
def _gauss_legendre() -> tuple[np.ndarray, np.ndarray]:
    """256-point Gauss-Legendre nodes and weights on [-1, 1], computed once per process (an
    eigenvalue problem that, with BLAS threads competing with Dr.Jit's, took longer than the trace)."""
    return np.polynomial.legendre.leggauss(256)


# A bounce series' passes past the 2nd bounce run this many times as many iterations per wave.
LATER_WAVES = 4

# Paths that go on past the 2nd background bounce first, as a pilot for the others: 1 in this many.
CONTINUATION_PILOT = 8
# Paths whose value up to the 2nd bounce gives the spread that continuation_share weighs the pilot against.
CONTINUATION_SAMPLE = 1 << 18


def continuation_share(n_paths: int, first_terms, first_iterations: int, later_terms, later_iterations: int,
                       orders: int, rho: float = REFERENCE_RHOS[1]) -> float:
    """The survival past the 2nd background bounce that minimises the variance of I(ρ) for the work,
    from a pilot of 1/CONTINUATION_PILOT of the paths there (`later_terms`, `later_iterations`): with
    V the per-path variance of a path's value up to that bounce (`first_terms`), M the mean square of
    its value after it (at survival 1) and c₁, c_L the iterations per path before and after,
    f = √(M·c₁ / (V·c_L)) (the largest over α = 0.9 … 0.999), within [1/CONTINUATION_PILOT, 1].
    Terms as _detector_sums takes them."""
    if later_iterations <= 0:
        return 1.0
    alpha = np.array([0.9, 0.99, 0.999])
    # V from the first CONTINUATION_SAMPLE paths (any will do: they are independent): the sums are
    # the costliest part of a trace's bookkeeping.
    sample = min(n_paths, CONTINUATION_SAMPLE)
    first_terms = [tuple(part[:np.searchsorted(term[0], sample)] if np.ndim(part) else part for part in term)
                   for term in first_terms]
    first, later = (Tally(counts=counts, second=second, n_paths=n, weight=1.0, specular=0.0, truncated=0, k_max=0)
                    for n, (counts, second) in ((sample, _detector_sums(sample, first_terms, orders)),
                                                (n_paths, _detector_sums(n_paths, later_terms, orders))))
    variance = _detector_path_variance(first, alpha, rho)
    _, later_second = later._moments(alpha)
    mean_square = sum(later_second[p] * rho**p for p in range(len(later_second))) * CONTINUATION_PILOT
    cost_ratio = first_iterations / (later_iterations * CONTINUATION_PILOT)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.sqrt(mean_square / variance * cost_ratio)
    share = float(np.max(np.where(np.isfinite(share), share, 1.0)))
    return min(max(share, 1 / CONTINUATION_PILOT), 1.0)


def _returns_control_variate(dr, B, stack: Stack, sigma_t: float, seed: int, straight_through, final: dict,
                             second_bounce: dict, at, value):
    """A bounce series' control variate for its noisiest outcome: whether a path comes back to the
    background after its first bounce (for a clear sample mostly a Fresnel reflection off the stack's
    back face). `at`: the paths that reached their 2nd bounce, `value` their next-event estimates
    there; a path that came back by exactly one reflection and nothing else (`final`'s reflections
    since its first bounce, `second_bounce`: where the paths landed) has its estimate replaced by the
    expectation of it given its first bounce's position (_expected_plain_returns, for every path that
    bounced). Returns the estimates without those paths', and the expectation per path (α^k at the
    first bounce's k, row 2)."""
    value = np.where(final["reflections"][at] == 1, 0.0, value)
    expected = np.zeros(len(final["m"]))
    bounced = np.flatnonzero(final["m"] >= 1)
    if len(bounced):
        expected[bounced] = _expected_plain_returns(dr, B, stack, sigma_t, seed, straight_through,
                                                    final["bounce_x"][bounced], final["bounce_y"][bounced])
    return value, expected


def _expected_plain_returns(dr, B, stack: Stack, sigma_t: float, seed: int, straight_through, x, y):
    """A bounce series' control variate for its noisiest outcome: whether a path comes back to the
    background after its first bounce (for a clear sample mostly a Fresnel reflection off the stack's
    back face). A path that came back by exactly one reflection and nothing else has its second
    bounce's next-event estimate replaced by the expectation of that estimate given the first
    bounce's position (x, y) (numpy): over the bounce's cosine-distributed direction, Σ_i P_i ·
    v(landing_i) (_single_reflection_returns), from RETURN_DIRECTIONS fresh directions per path, each
    with one interface drawn ∝ P_i and one next-event estimate from where it lands (unbiased). Fresh
    directions, not the path's own: the trace need not carry its first bounce's direction."""
    Float = B.Float
    xs, ys = Float(x), Float(y)
    total_value = np.zeros(len(x))
    state = _mix64(seed ^ 0x5245)
    rng = B.PCG32(len(x), initstate=dr.opaque(B.UInt64, state), initseq=dr.opaque(B.UInt64, _mix64(state ^ 0x5EED)))
    for _ in range(RETURN_DIRECTIONS):
        u1, u2, pick_u, u, v = (rng.next_float32() for _ in range(5))
        r, phi = dr.sqrt(u1), 2 * math.pi * u2
        P, landings = _single_reflection_returns(dr, stack, sigma_t, xs, ys, r * dr.cos(phi), r * dr.sin(phi),
                                                 dr.safe_sqrt(1 - u1))
        total = P[0]
        for p in P[1:]:
            total = total + p
        # the interface whose cumulative share first reaches pick_u (the last one if rounding leaves none)
        target, cumulative = pick_u * total, Float(0.0)
        land_x, land_y = landings[-1]
        chosen = dr.zeros(dr.mask_t(Float), len(x))
        for p, (lx, ly) in zip(P[:-1], landings[:-1], strict=True):
            cumulative = cumulative + p
            take = ~chosen & (cumulative >= target) & (p > 0)
            land_x, land_y = dr.select(take, lx, land_x), dr.select(take, ly, land_y)
            chosen |= take
        total_value += np.asarray(total * straight_through(land_x, land_y, u, v), dtype=np.float64)
    return total_value / RETURN_DIRECTIONS


# Fresh first-bounce directions per path for the bounce series' returns control variate.
RETURN_DIRECTIONS = 2


def _single_reflection_returns(dr, stack: Stack, sigma_t: float, x, y, dx, dy, dz):
    """For rays leaving the background at (x, y) upward in direction (dx, dy, dz) (Dr.Jit arrays of one
    backend): per interface i of the stack (0 = its bottom face … L = its top face), the probability
    P_i that the ray comes back to the background after one Fresnel reflection there and nothing else
    (refracted through the interfaces below it both ways, unscattered, past no side face, landing on
    the background), and where it lands: ([P_i], [(x_i, y_i)]). The ray's way up and down is
    symmetric, so P_i = F_i·(transmittance up to i)², and it stays over the footprint if its entry,
    the reflection and its exit do (each leg is monotonic sideways)."""
    n_layers = len(stack.layer_n)
    W, WB = stack.stack_half_width, stack.background_half_width
    sin2 = dr.maximum(1 - dz * dz, 0.0)
    gap = (stack.plane_z[-1] - stack.background_z) / dz     # sideways travel per unit of (dx, dy)
    step, transmit = gap, dr.ones(type(dz), dr.width(dz))
    cos_below, n_below = dz, 1.0

    def over(px, py, half):
        return (dr.abs(px) <= half) & (dr.abs(py) <= half)

    entry_ok = over(x + gap * dx, y + gap * dy, W)
    P, landings = [], []
    for i in range(n_layers + 1):
        layer = n_layers - i                     # the medium above interface i: layer − 1, or air at 0
        n_above = stack.layer_n[layer - 1] if layer >= 1 else 1.0
        F, _ = _fresnel(dr, cos_below, n_above / n_below)
        land_x, land_y = x + 2 * step * dx, y + 2 * step * dy
        ok = (entry_ok & over(x + step * dx, y + step * dy, W) & over(land_x - gap * dx, land_y - gap * dy, W)
              & over(land_x, land_y, WB))
        P.append(dr.select(ok, F * transmit * transmit, 0.0))
        landings.append((land_x, land_y))
        if layer >= 1:                           # on through layer − 1 to the next interface up
            li = layer - 1
            n_l = stack.layer_n[li]
            cos_l = dr.safe_sqrt(1 - sin2 / (n_l * n_l))
            depth = stack.plane_z[li] - stack.plane_z[li + 1]
            transmit = transmit * (1 - F)
            if li == stack.sample_layer:
                transmit = transmit * dr.exp(-sigma_t * depth / cos_l)
            step = step + depth / (n_l * cos_l)
            cos_below, n_below = cos_l, n_l
    return P, landings


def _fresnel_np(cos_i, eta):
    """_fresnel in numpy (float64)."""
    sin2_t = (1 - cos_i * cos_i) / (eta * eta)
    cos_t = np.sqrt(np.maximum(1 - sin2_t, 0.0))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(sin2_t >= 1, 1.0, 0.5 * (rs * rs + rp * rp))


def _detector_sums(n_paths, terms, orders: int = N_BACKGROUND_ORDERS):
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


# Paths per step of _detector_sums.
SUMS_CHUNK = 1 << 18


def _detector_sums_chunk(n_paths, terms, orders, width):
    """_detector_sums' flat counts and second moments for paths 0 … n_paths − 1 (a chunk)."""
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

