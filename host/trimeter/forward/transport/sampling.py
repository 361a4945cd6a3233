"""Random numbers of the tracer: seeds scrambled into independent streams, the quasi-random points of the
next-event control variate, and the two direction samplings of a path (Henyey-Greenstein scattering about
the current direction; cosine-distributed directions off a Lambertian surface)."""

from __future__ import annotations

import math

import numpy as np

def mix64(x: int) -> int:
    """SplitMix64's finaliser: neighbouring seeds → unrelated 64-bit values."""
    x = (x + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return x ^ (x >> 31)


# Independent randomisations of the quasi-random points that estimate the mean next-event value of
# the straight first pass (their spread gives that estimate's variance).
NEE_REPLICAS = 8


def nee_points(seed: int, n_paths: int) -> list[np.ndarray]:
    """NEE_REPLICAS sets of 4-D points (detector x, y; light u, v) in [0, 1): scrambled Sobol, each
    set a power of two of about n_paths / 64 points (≥ 4096), seeded from `seed`. float32 values, < 1."""
    from scipy.stats import qmc

    size = max(12, min(20, round(math.log2(max(n_paths, 1) / 64))))
    below_one = np.float32(1 - 2**-24)
    return [np.minimum(qmc.Sobol(4, scramble=True, seed=np.random.default_rng([seed, 0xC1EA2, r]))
                       .random_base2(size).astype(np.float32), below_one) for r in range(NEE_REPLICAS)]


def pcg_streams(dr, B, n_paths: int, seed: int):
    """One PCG32 stream per path. Streams whose (state, increment) seeds are close are correlated, and
    the constructor adds the lane index to both: so both seeds are scrambled (SplitMix64) from `seed`."""
    return B.PCG32(n_paths, initstate=dr.opaque(B.UInt64, mix64(seed)),
                   initseq=dr.opaque(B.UInt64, mix64(mix64(seed) ^ 0x5EED)))


def henyey_greenstein(dr, g, g_is_zero: bool, u1, u2, dx, dy, dz):
    """A direction scattered from (dx, dy, dz) by the Henyey-Greenstein phase function of anisotropy g,
    in closed form from the uniforms u1 (polar) and u2 (azimuth), rotated about the current direction."""
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
    return (cp * s1[0] + sp * s2[0] + cos_t * dx, cp * s1[1] + sp * s2[1] + cos_t * dy,
            cp * s1[2] + sp * s2[2] + cos_t * dz)


def cosine_direction(dr, u1, u2):
    """A cosine-distributed upward direction from two uniforms (a Lambertian surface's)."""
    r, phi = dr.sqrt(u1), 2 * math.pi * u2
    return r * dr.cos(phi), r * dr.sin(phi), dr.safe_sqrt(1 - u1)
