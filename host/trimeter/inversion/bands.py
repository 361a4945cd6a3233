"""Band-aware fitting: readings of a multichannel sensor, each an integral over a band, → smooth α(λ), σt(λ), g(λ).

A channel of a filter sensor (the AS7341: 25-55 nm wide) reads the band integral of the per-wavelength
observables under its effective weight: its spectral response times the lamp's emission (the diffuse
panels for I_b and I_w, the collimated LED for I_c). The map is not linear, so the band average of the
intensities is not the intensity of the band-averaged parameters: fitting each channel as if it were
monochromatic (the per-channel fit) is biased wherever the spectrum changes within a band.

The model here: α, σt, g as smooth spectra, each a natural cubic spline in λ through one knot per
channel (at the centroid of the channel's diffuse weight) in a transformed coordinate that keeps them
inside the map (logit α, ln σt, a scaled atanh of g). Per wavelength of the weights' grid the map's
forward model (ForwardGrid.intensities: I_b, I_w and I_c with the in-scattering correction, exactly what
the per-channel fit inverts) gives the observables; each channel's reading is their weighted sum. The
knots are found by Levenberg-Marquardt on the noise-normalised residuals of every channel's three
readings plus a small penalty on the knots' second differences (it only decides what the data cannot:
with one knot per channel the readings pin the knots, the penalty keeps a badly conditioned channel
from swinging), started from the per-channel fit.

The stds: first-order propagation through the band model (the readings' stds — given, else the fit's
noise model — and the map's own error at the solution, through the Jacobian of the penalised least
squares at the solution). A channel is BAND_UNRESOLVED where the spectra within its band are not pinned
by the readings: where the same readings fitted with a not-a-knot cubic spline (another interpolation,
as smooth and equally consistent with the readings; it differs from the natural spline where the
channels are sparse and near the ends) give a value at the centre off by more than the UNRESOLVED_*
tolerances. Backgrounds are per channel, each taken as constant across its own band (they vary slowly:
they are surfaces of the instrument).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from trimeter.domain.parameters import FitResult
from trimeter.errors import InputError
from trimeter.inversion.flags import UNUSABLE, FitFlag
from trimeter.model.grid import ForwardGrid

if TYPE_CHECKING:
    from trimeter.inversion.api import FitModel
    from trimeter.inversion.kernel import Kernel

# Weights below this fraction of a channel's peak are outside its band (left out of its integral).
BAND_EDGE = 1e-3
# A channel's band must lie inside the weights' grid up to this fraction of its integral: a weight
# still at BAND_COVERAGE_EDGE of its peak at the grid's edge is cut off.
BAND_COVERAGE_EDGE = 0.02
# The second-difference penalty on the knots (transformed coordinates, per unit of the readings'
# normalised residual). With one knot per channel the readings determine the knots; the penalty only
# keeps a channel the readings hardly constrain from swinging (`trimeter bench sensor` shows it moves
# no resolved channel).
SMOOTHNESS = 0.03
# BAND_UNRESOLVED where the natural and the not-a-knot spline's centre values differ by more than
# these (α absolute, σt relative, g absolute): the band-aware fit's targets
UNRESOLVED_ALPHA, UNRESOLVED_SIGMA_T_REL, UNRESOLVED_G = 0.01, 0.02, 0.03
UNRESOLVED_BASIS = "not-a-knot"
# NOT_CONVERGED where a channel's readings stay this many stds off the fitted spectra's
MISFIT_SIGMAS = 5.0
# OUTSIDE_MAP where a value ran onto the map's range edge (in the squashed coordinate: tanh of the knot value)
EDGE_TANH = 1 - 1e-6
ALPHA_MIN_G = 0.02  # the per-wavelength fit's default: g undefined below
BASES = ("cubic", "not-a-knot", "linear")


@dataclass(frozen=True)
class BandWeights:
    """Per channel its effective weight on a wavelength grid under the diffuse lamps and under the
    collimated LED (each normalised to sum 1 over the grid), and the centroid of the diffuse weight."""
    wavelength_nm: np.ndarray   # (N,) increasing
    channels: tuple[str, ...]
    diffuse: np.ndarray         # (C, N)
    collimated: np.ndarray      # (C, N)
    centre_nm: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_nm", self.diffuse @ self.wavelength_nm)

    def densities(self) -> tuple[np.ndarray, np.ndarray]:
        """(diffuse, collimated) per nm: what band_weights takes to give these weights back."""
        step = np.gradient(self.wavelength_nm)
        return self.diffuse / step, self.collimated / step

    def select(self, names: list[str] | tuple[str, ...], where: str = "CHANNELS") -> BandWeights:
        """The weights of these channels, in this order (an unknown name: InputError)."""
        missing = [n for n in names if n not in self.channels]
        if missing:
            raise InputError(f"{where}: channel(s) {', '.join(missing)} have no weights (the weights have "
                             f"{', '.join(self.channels)})")
        idx = [self.channels.index(n) for n in names]
        return BandWeights(self.wavelength_nm, tuple(names), self.diffuse[idx], self.collimated[idx])


def band_weights(wavelength_nm: ArrayLike, channels: list[str] | tuple[str, ...], diffuse: ArrayLike,
                 collimated: ArrayLike, where: str = "weights") -> BandWeights:
    """Validated, normalised BandWeights; each problem is an InputError naming the channel."""
    lam = np.asarray(wavelength_nm, dtype=float)
    d, c = np.atleast_2d(np.asarray(diffuse, dtype=float)), np.atleast_2d(np.asarray(collimated, dtype=float))
    names = tuple(channels)
    if lam.ndim != 1 or len(lam) < 3:
        raise InputError(f"{where}: need at least 3 wavelengths, got {lam.size}")
    if not np.all(np.isfinite(lam)) or np.any(np.diff(lam) <= 0):
        raise InputError(f"{where}: wavelength_nm must be finite and strictly increasing")
    if len(set(names)) != len(names):
        raise InputError(f"{where}: a channel appears more than once")
    if d.shape != (len(names), len(lam)) or c.shape != d.shape:
        raise InputError(f"{where}: weights must be (channels, wavelengths) = ({len(names)}, {len(lam)})")
    step = np.gradient(lam)  # the weights are densities: integrate them on an uneven grid too
    out = []
    for kind, w in (("diffuse", d), ("collimated", c)):
        for name, row in zip(names, w, strict=True):
            column = f"{name}_{kind}"
            if not np.all(np.isfinite(row)):
                raise InputError(f"{where}: {column} has an empty or non-finite value")
            if np.any(row < 0):
                raise InputError(f"{where}: {column} has a negative weight ({row.min():.3g} at "
                                 f"{lam[np.argmin(row)]:g} nm)")
            if not np.any(row > 0):
                raise InputError(f"{where}: {column} is zero everywhere")
            edge = BAND_COVERAGE_EDGE * row.max()
            if row[0] > edge or row[-1] > edge:
                side = f"{lam[0]:g}" if row[0] > edge else f"{lam[-1]:g}"
                raise InputError(f"{where}: {column} does not fall to zero at {side} nm: the grid "
                                 f"{lam[0]:g}-{lam[-1]:g} nm does not cover the channel's band")
        area = w * step
        out.append(area / area.sum(axis=1, keepdims=True))
    return BandWeights(lam, names, out[0], out[1])


# ------------------------------------------------------------------------------------ coordinates
class _Coordinates:
    """Knot values ↔ parameters: logit α, ln σt and a scaled atanh of g, inside the map's ranges."""

    def __init__(self, grid: ForwardGrid) -> None:
        a0, a1 = grid.alpha_range
        self.alpha = (max(a0, 1e-6), min(a1, 1 - 1e-6))
        self.sigma = tuple(np.log(grid.sigma_t_range))
        self.g = grid.g_range

    @staticmethod
    def _squash(u: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
        t = np.tanh(u)
        return lo + 0.5 * (hi - lo) * (t + 1.0), 0.5 * (hi - lo) * (1.0 - t * t)

    @staticmethod
    def _unsquash(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
        t = np.clip(2.0 * (x - lo) / (hi - lo) - 1.0, -0.999, 0.999)
        return np.arctanh(t)

    def to_params(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(3, …) transformed → (3, …) α, σt, g and d(param)/du."""
        a, da = self._squash(u[0], *self.alpha)
        ls, dls = self._squash(u[1], *self.sigma)
        g, dg = self._squash(u[2], *self.g)
        s = np.exp(ls)
        return np.stack([a, s, g]), np.stack([da, s * dls, dg])

    def from_params(self, alpha: np.ndarray, sigma_t: np.ndarray, g: np.ndarray) -> np.ndarray:
        return np.stack([self._unsquash(alpha, *self.alpha), self._unsquash(np.log(sigma_t), *self.sigma),
                         self._unsquash(g, *self.g)])


def _basis(knots: np.ndarray, lam: np.ndarray, kind: str) -> np.ndarray:
    """(len(lam), K): the interpolant through the knots is basis @ values (linear in the values)."""
    from scipy.interpolate import CubicSpline

    K = len(knots)
    eye = np.eye(K)
    if kind == "linear":
        order = np.argsort(knots)
        return np.stack([np.interp(lam, knots[order], eye[k][order]) for k in range(K)], axis=1)
    if kind not in ("cubic", "not-a-knot"):
        raise InputError(f"basis must be one of {', '.join(BASES)}, got {kind!r}")
    if K == 2 or (kind == "not-a-knot" and K < 4):
        return np.stack([1.0 - (lam - knots[0]) / (knots[1] - knots[0]), (lam - knots[0]) / (knots[1] - knots[0])], 1)
    order = np.argsort(knots)
    spline = CubicSpline(knots[order], eye[order], bc_type="natural" if kind == "cubic" else "not-a-knot",
                         extrapolate=True)
    knots = knots[order]
    inside = spline(np.clip(lam, knots[0], knots[-1]))
    # beyond the outer knots: straight on with the end slope (a cubic's extrapolation runs away)
    slope = spline(knots[[0, -1]], 1)
    below, above = lam < knots[0], lam > knots[-1]
    inside[below] += (lam[below] - knots[0])[:, None] * slope[0]
    inside[above] += (lam[above] - knots[-1])[:, None] * slope[1]
    return inside


def _second_differences(knots: np.ndarray) -> np.ndarray:
    """(K−2, K): the knots' second differences per (knot spacing)², scaled by the mean spacing² so
    that the penalty is dimensionless."""
    K = len(knots)
    D = np.zeros((max(K - 2, 0), K))
    h = np.diff(knots)
    for i in range(K - 2):
        D[i, i], D[i, i + 1], D[i, i + 2] = 1 / h[i], -(1 / h[i] + 1 / h[i + 1]), 1 / h[i + 1]
        D[i] *= 2.0 / (h[i] + h[i + 1])
    return D * np.mean(h) ** 2 if K > 2 else D


# ------------------------------------------------------------------------------------------ the fit
@dataclass
class BandFit:
    """The band-aware fit: at the channels' centres (input order) and, if asked, on a wavelength grid."""
    centre_nm: np.ndarray
    at_centres: FitResult
    per_channel: FitResult          # the per-channel fit it started from (the readings taken as monochromatic)
    grid_nm: np.ndarray | None = None
    on_grid: FitResult | None = None
    basis: str = "cubic"
    evaluations: int = 0  # of the readings, by the solver


class _BandModel:
    """The readings of every channel for knot values u (3, K), and their Jacobian. Evaluated on the
    (channel, wavelength) pairs inside each channel's band, so that each channel's backgrounds hold
    across its own band."""

    def __init__(self, grid: ForwardGrid, weights: BandWeights, rho_b: np.ndarray, rho_w: np.ndarray,
                 basis: str) -> None:
        self.grid = grid
        inside = np.maximum(weights.diffuse, weights.collimated) > BAND_EDGE * np.maximum(
            weights.diffuse, weights.collimated).max(axis=1, keepdims=True)
        self.channel, where = np.nonzero(inside)                                   # the pairs
        self.C = len(weights.channels)
        wd, wc = weights.diffuse[self.channel, where], weights.collimated[self.channel, where]
        self.wd = wd / np.bincount(self.channel, wd, self.C)[self.channel]
        self.wc = wc / np.bincount(self.channel, wc, self.C)[self.channel]
        self.lam = weights.wavelength_nm[where]
        self.knots = weights.centre_nm
        self.B = _basis(self.knots, self.lam, basis)                               # (pairs, K)
        self.rho_b, self.rho_w = rho_b[self.channel], rho_w[self.channel]
        self.coords = _Coordinates(grid)
        # per channel its weights over the pairs: a band integral is one matrix product
        self.Sd, self.Sc = np.zeros((self.C, len(self.lam))), np.zeros((self.C, len(self.lam)))
        self.Sd[self.channel, np.arange(len(self.lam))] = self.wd
        self.Sc[self.channel, np.arange(len(self.lam))] = self.wc

    def spectra(self, u: np.ndarray, B: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(α, σt, g) (3, pairs) for knot values u (3, K), and d(param)/du."""
        return self.coords.to_params(u @ (self.B if B is None else B).T)

    def readings(self, u: np.ndarray) -> np.ndarray:
        """(3, C): the channels' I_b, I_w, I_c."""
        p = self.spectra(u)[0]
        obs = self.grid.intensities(p[0], p[1], p[2], self.rho_b, self.rho_w)
        return np.stack([self.Sd @ obs[0], self.Sd @ obs[1], self.Sc @ obs[2]])

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        """(3, C, 3, K): ∂ reading / ∂ knot value. I_b, I_w analytic on the map; I_c (with the
        in-scattering correction) by forward differences."""
        p, dp = self.spectra(u)
        J = self.grid.jacobian(p[0], p[1], p[2], self.rho_b, self.rho_w)          # (pairs, 3 obs, 3 par)
        base = self.grid.collimated_measured(*p)
        for j in range(3):  # forward differences: the model is smooth, and LM needs no more
            step = np.zeros_like(p)
            step[j] = 1e-5 * (p[1] if j == 1 else 1.0)
            J[:, 2, j] = (self.grid.collimated_measured(*(p + step)) - base) / step[j]
        Ju = J * dp.T[:, None, :]                                                   # ∂obs/∂u per pair
        # ∂ reading[o, c] / ∂ u[j, k] = Σ_pairs of c  w · Ju[pair, o, j] · B[pair, k]
        K = len(self.knots)
        terms = (Ju[:, :, :, None] * self.B[:, None, None, :]).reshape(len(self.lam), 3, 3 * K)
        return np.stack([(S @ terms[:, o]).reshape(self.C, 3, K)
                         for o, S in ((0, self.Sd), (1, self.Sd), (2, self.Sc))])


def fit_bands(model: FitModel, weights: BandWeights, I_b: ArrayLike, I_w: ArrayLike, I_c: ArrayLike,
              rho_b: ArrayLike | None = None, rho_w: ArrayLike | None = None, *, I_b_std: ArrayLike | None = None,
              I_w_std: ArrayLike | None = None, I_c_std: ArrayLike | None = None, grid_nm: ArrayLike | None = None,
              basis: str = "cubic", smoothness: float = SMOOTHNESS, noise_rel: float = 0.005,
              noise_abs: float = 2e-4, check_resolved: bool = True, kernel: Kernel | None = None) -> BandFit:
    """Fit the channels' band readings (arrays over weights.channels, in that order) of one sample.

    model: a loaded map (trimeter.maps.artifacts.load_artifacts: its forward grid, as the per-channel
    fit's); rho_b, rho_w: per-channel backgrounds (default: the map's reference backgrounds);
    *_std: the readings' stds (default: the fit's noise model σ = noise_rel·I + noise_abs);
    grid_nm: wavelengths to report the spectra on as well; basis: "cubic" (natural spline through the
    knots) or "linear"; smoothness: the second-difference penalty's weight.
    """
    from scipy.optimize import least_squares

    from trimeter.inversion.api import UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD
    from trimeter.inversion.api import fit as fit_per_channel

    C = len(weights.channels)
    if C < 2:
        raise InputError(f"a band-aware fit needs at least 2 channels (it fits spectra across them), got {C}")
    r_b, r_w, r_c = (np.asarray(v, dtype=float).reshape(-1) for v in (I_b, I_w, I_c))
    readings = [r_b, r_w, r_c]
    if any(len(r) != C for r in readings):
        raise InputError(f"I_b, I_w, I_c must have one value per channel ({C})")
    ref_b, ref_w = model.reference_rhos
    rb = np.full(C, ref_b) if rho_b is None else np.asarray(rho_b, dtype=float).reshape(C)
    rw = np.full(C, ref_w) if rho_w is None else np.asarray(rho_w, dtype=float).reshape(C)
    stds_given = (I_b_std, I_w_std, I_c_std)
    start = fit_per_channel(model, r_b, r_w, r_c, rb, rw, I_b_std=I_b_std, I_w_std=I_w_std, I_c_std=I_c_std,
                            noise_rel=noise_rel, noise_abs=noise_abs, kernel=kernel)
    input_flags = start.flags & int(UNUSABLE | FitFlag.BLACK_NOT_BELOW_WHITE | FitFlag.IC_BELOW_FLOOR)
    usable = ((start.flags & int(UNUSABLE)) == 0) & np.isfinite(rb) & np.isfinite(rw)
    if usable.sum() < 2:
        raise InputError(f"a band-aware fit needs at least 2 usable channels, got {int(usable.sum())}")
    grid = model.grid
    band = _BandModel(grid, weights, np.where(np.isfinite(rb), rb, ref_b), np.where(np.isfinite(rw), rw, ref_w),
                      basis)
    meas = np.stack(readings)                                                       # (3, C)
    sigma = _reading_stds(meas, stds_given, noise_rel, noise_abs)
    sigma = np.sqrt(sigma ** 2 + _model_variance(band, start))
    u0 = _start_values(band, start, usable)
    D = _second_differences(band.knots[np.argsort(band.knots)])
    order = np.argsort(band.knots)
    penalty = np.sqrt(smoothness) * D[:, np.argsort(order)] if len(D) else D        # knots in input order
    mask = usable[None, :] & np.isfinite(meas)

    def residuals(x: np.ndarray) -> np.ndarray:
        u = x.reshape(3, C)
        r = (band.readings(u) - meas) / sigma
        return np.concatenate([r[mask], (penalty @ u.T).T.ravel()])

    def jac(x: np.ndarray) -> np.ndarray:
        u = x.reshape(3, C)
        J = band.jacobian(u) / sigma[:, :, None, None]                              # (3, C, 3, K)
        rows = J[mask].reshape(-1, 3 * C)
        reg = np.kron(np.eye(3), penalty)
        return np.vstack([rows, reg])

    solution = least_squares(residuals, u0.ravel(), jac=jac, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=200)
    u = solution.x.reshape(3, C)
    J = jac(solution.x)
    cov = _covariance(J, mask.sum())
    result = _evaluate(band, u, cov, _basis(band.knots, band.knots, basis), grid,
                       UNDERDETERMINED_ALPHA_STD, UNDERDETERMINED_G_STD)
    misfit = np.max(np.abs(np.where(mask, (band.readings(u) - meas) / sigma, 0.0)), axis=0)
    flags = result.flags | input_flags | np.where(misfit > MISFIT_SIGMAS, int(FitFlag.NOT_CONVERGED), 0)
    if check_resolved and basis == "cubic":
        other = fit_bands(model, weights, r_b, r_w, r_c, rb, rw, I_b_std=I_b_std, I_w_std=I_w_std, I_c_std=I_c_std,
                          basis=UNRESOLVED_BASIS, smoothness=smoothness, noise_rel=noise_rel, noise_abs=noise_abs,
                          check_resolved=False, kernel=kernel).at_centres
        flags |= np.where(_unresolved(result, other), int(FitFlag.BAND_UNRESOLVED), 0)
    result.flags = np.where(usable, flags, start.flags)
    _blank(result, ~usable)
    out = BandFit(weights.centre_nm.copy(), result, start, basis=basis, evaluations=int(solution.nfev))
    if grid_nm is not None:
        lam = np.asarray(grid_nm, dtype=float)
        on_grid = _evaluate(band, u, cov, _basis(band.knots, lam, basis), grid, UNDERDETERMINED_ALPHA_STD,
                            UNDERDETERMINED_G_STD)
        lo, hi = weights.centre_nm.min(), weights.centre_nm.max()
        outside = (lam < lo) | (lam > hi)
        # beyond the outermost centres the spectra are extrapolated: say so
        on_grid.flags = on_grid.flags | np.where(outside, int(FitFlag.BAND_UNRESOLVED), 0)
        out.grid_nm, out.on_grid = lam, on_grid
    return out


def _reading_stds(meas: np.ndarray, given: tuple, noise_rel: float, noise_abs: float) -> np.ndarray:
    model = noise_rel * np.abs(meas) + noise_abs
    out = model.copy()
    for i, s in enumerate(given):
        if s is not None:
            s = np.broadcast_to(np.asarray(s, dtype=float), meas[i].shape)
            out[i] = np.where(np.isfinite(s) & (s > 0), s, model[i])
    return out


def _model_variance(band: _BandModel, start: FitResult) -> np.ndarray:
    """(3, C) the map's own error in each reading, taken fully correlated within a band (the map's
    error is smooth in the parameters), at the per-channel start; I_c's in-scattering error as the
    per-channel fit takes it."""
    from trimeter.inversion.api import INSCATTER_REL_STD

    grid = band.grid
    p = np.stack([np.nan_to_num(v, nan=fill)[band.channel]
                  for v, fill in ((start.alpha, 0.5), (start.sigma_t, 1.0), (start.g, 0.5))])
    a, s, g = np.clip(p[0], *grid.alpha_range), grid.clamp_sigma_t(p[1]), np.clip(p[2], *grid.g_range)
    out = np.zeros((3, band.C))
    if grid.model_var is not None:
        var = grid.model_variance(a, grid.sigma_cell(s), g)
        out[0] = np.bincount(band.channel, band.wd * np.sqrt(var[0]), band.C) ** 2
        out[1] = np.bincount(band.channel, band.wd * np.sqrt(var[1]), band.C) ** 2
    if grid.inscatter_grid is not None:
        ic = grid.collimated_measured(a, s, g)
        L = grid.inscatter_log1p(a, s, g)
        out[2] = np.bincount(band.channel, band.wc * INSCATTER_REL_STD * np.abs(L) * ic, band.C) ** 2
    return out


def _start_values(band: _BandModel, start: FitResult, usable: np.ndarray) -> np.ndarray:
    """The knots at the per-channel fit (inside the map's ranges; an unusable or NaN channel: its
    usable neighbours' interpolation)."""
    ok = usable & np.isfinite(start.alpha) & np.isfinite(start.sigma_t)
    knots = band.knots
    values = []
    for v, fill in ((start.alpha, 0.5), (start.sigma_t, 1.0), (start.g, 0.5)):
        good = ok & np.isfinite(v)
        if good.any():
            order = np.argsort(knots[good])
            v = np.interp(knots, knots[good][order], v[good][order])
        else:
            v = np.full(len(knots), fill)
        values.append(v)
    a, s, g = values
    c = band.coords
    return c.from_params(np.clip(a, *c.alpha), np.clip(s, *np.exp(c.sigma)), np.clip(g, *c.g))


def _covariance(J: np.ndarray, n_data: int) -> np.ndarray:
    """The knots' covariance: (JᵀJ)⁻¹ JdᵀJd (JᵀJ)⁻¹ with J the whole (data + penalty) Jacobian and
    Jd its data rows: the penalty narrows nothing it does not also bias."""
    H = J.T @ J
    Jd = J[:n_data]
    Hinv = np.linalg.pinv(H)
    return Hinv @ (Jd.T @ Jd) @ Hinv


def _evaluate(band: _BandModel, u: np.ndarray, cov: np.ndarray, B: np.ndarray, grid: ForwardGrid, under_a: float,
              under_g: float) -> FitResult:
    """α, σt, g and their stds at the wavelengths of basis B (M, K)."""
    M, K = B.shape
    values = u @ B.T                                                              # (3, M)
    p, dp = band.coords.to_params(values)
    at_edge = np.any(np.abs(np.tanh(values)) > EDGE_TANH, axis=0)
    stds = np.empty((3, M))
    for j in range(3):
        block = cov[j * K:(j + 1) * K, j * K:(j + 1) * K]
        stds[j] = np.abs(dp[j]) * np.sqrt(np.maximum(np.einsum("mk,kl,ml->m", B, block, B), 0.0))
    flags = (np.where((stds[0] > under_a) | (stds[2] > under_g), int(FitFlag.UNDERDETERMINED), 0)
             | np.where(at_edge, int(FitFlag.OUTSIDE_MAP), 0)).astype(np.int64)
    beer = grid.setup.beer_lambert_sigma_t(grid.collimated_measured(p[0], p[1], p[2]))
    # as the per-wavelength fit: nothing scatters, the phase function is unobservable
    g_undefined = p[0] < ALPHA_MIN_G
    flags |= np.where(g_undefined, int(FitFlag.G_UNDEFINED), 0)
    p[2] = np.where(g_undefined, np.nan, p[2])
    stds[2] = np.where(g_undefined, np.nan, stds[2])
    return FitResult(p[0], p[1], p[2], stds[0], stds[1], stds[2], flags, beer, method="bands")


def _unresolved(a: FitResult, b: FitResult) -> np.ndarray:
    return ((np.abs(a.alpha - b.alpha) > UNRESOLVED_ALPHA)
            | (np.abs(a.sigma_t - b.sigma_t) > UNRESOLVED_SIGMA_T_REL * a.sigma_t)
            | (np.abs(a.g - b.g) > UNRESOLVED_G))


def _blank(result: FitResult, rows: np.ndarray) -> None:
    for name in ("alpha", "sigma_t", "g", "alpha_std", "sigma_t_std", "g_std", "sigma_t_beer"):
        getattr(result, name)[rows] = np.nan
