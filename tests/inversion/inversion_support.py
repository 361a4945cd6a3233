"""What the inversion tests share, in a uniquely named module: `from conftest import …` is
ambiguous when pytest collects several test folders, each with its own conftest.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parent / "data"


def well_conditioned(amap, n, rng, alpha=(0.3, 0.995), tau=(0.2, 4.0), g=(0.0, 0.8)):
    """Random off-grid materials where all three parameters are observable: scattering enough for g,
    optically thick enough for α and thin enough for I_c."""
    a = rng.uniform(*alpha, n)
    s = np.exp(rng.uniform(np.log(tau[0]), np.log(tau[1]), n)) / amap.thickness_mm
    return a, s, rng.uniform(*g, n)


def forward(amap, alpha, sigma_t, g, rho_b, rho_w):
    """(I_b, I_w, I_c) by the forward model every method polishes and propagates with (the map
    table's: the map resampled onto refined axes), so round trips test the inversion alone."""
    from trimeter.inversion.artifacts import load_artifacts

    n = len(np.atleast_1d(alpha))
    b = lambda v: np.broadcast_to(np.asarray(v, float), (n,)).copy()  # noqa: E731
    return load_artifacts(amap).grid.intensities(b(alpha), b(sigma_t), b(g), b(rho_b), b(rho_w))
