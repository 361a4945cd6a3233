"""The forward model: what a sample set-up and a material (α, σt, g) make the instrument read.

Below both `maps` (which reads and writes the model's files) and `inversion` (which solves it): the
sample set-up (SampleSetup: n, ℓ, cover slides — the one source of ℓ), the analytic collimated beam
(collimated), the background response I(ρ) = A + Bρ/(1 − Cρ) (response), the map's interpolant
(grid.ForwardGrid) with its cell helpers (cells), and the in-scattering table lookup (inscatter).
Imports only the foundation modules and numpy/scipy.
"""
