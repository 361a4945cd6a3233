"""`mlp`: a small network (trained by tools/train_mlp.py, shipped as maps/<map-name>.onnx) gives the
initial (α, g); the forward-map Newton polish (trimeter.inversion.newton) refines it at the bins'
true backgrounds (`polish=0`: the network's answer alone). Inference through onnxruntime only (no
scikit-learn at run time).

The fit prepares FEATURES per bin (numpy here, C in tm_fit_prepare); the network reads INPUTS made
from them with the forward model (network_inputs): each background's intensity placed between what
the map predicts at that σt and ρ for the least and the most scattering material (α at the map's
ends, g = 0), as a logit. That takes out what the network would otherwise have to learn first: the
background seen through the slab, which dominates I_b and I_w of thin samples, and the steep response
near α = 1; a small network then reaches the accuracy a larger one on the raw intensities does not.

Model contract (checked on load; a mismatch is a MapFileError, never a silent wrong answer):
- metadata `trimeter.kind` = "mlp-inverse", `trimeter.map_sha256` = the SHA-256 of the map it was
  trained on, `trimeter.features` = INPUTS (comma-separated), `trimeter.format` = MODEL_FORMAT;
- one float32 input (N, 5) in the order INPUTS, one float32 output (N, 2) = (α, g).
σt is not a network output: it comes exactly from I_c (see trimeter.inversion.api).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trimeter.errors import MapFileError
from trimeter.inversion.strategy import Method
from trimeter.validation import shown

if TYPE_CHECKING:
    from trimeter.model.grid import ForwardGrid

MODEL_KIND = "mlp-inverse"
MODEL_FORMAT = "2"
FEATURES = ("sqrt_I_b", "sqrt_I_w", "ln_sigma_t", "rho_b", "rho_w")
INPUTS = ("logit_scatter_b", "logit_scatter_w", "ln_sigma_t", "rho_b", "rho_w")
_LOGIT_CLIP = 1e-4  # keeps the logit finite for intensities at or beyond the map's ends (noise, other ρ)


def features(I_b: np.ndarray, I_w: np.ndarray, sigma_t: np.ndarray, rho_b: np.ndarray, rho_w: np.ndarray,
             log_sigma_range: tuple[float, float]) -> np.ndarray:
    """The fit's per-bin features (N, 5) float32 (FEATURES; tm_fit_prepare writes the same); ln σt clamped
    to the map's range. network_inputs makes the network's input from them."""
    ls = np.log(np.maximum(np.asarray(sigma_t, float), 1e-30))
    ls = np.minimum(np.maximum(ls, log_sigma_range[0]), log_sigma_range[1])
    x = np.empty((len(ls), 5), dtype=np.float32)
    x[:, 0] = np.sqrt(np.minimum(np.maximum(I_b, 0.0), 1.0))
    x[:, 1] = np.sqrt(np.minimum(np.maximum(I_w, 0.0), 1.0))
    x[:, 2] = ls
    x[:, 3] = rho_b
    x[:, 4] = rho_w
    return x


class ScatterRange:
    """What the forward model `grid` predicts at each σt for the least and the most scattering material
    (α at the map's ends, g = 0 where the map has it): the ends network_inputs places I_b and I_w between.
    The grid is trilinear, so at fixed α and g nodes its A, B, C are piecewise linear in ln σt between
    its σt nodes: these (ns, 3) rows interpolated give exactly grid.intensities there, for a few
    lookups per bin instead of two forward evaluations."""

    def __init__(self, grid: ForwardGrid) -> None:
        nodes = grid.coefficients_grid  # (na, ns, ng, 3)
        g0 = min(max(0.0, grid.g_range[0]), grid.g_range[1])
        j = int(np.clip(np.searchsorted(grid.g, g0, side="right") - 1, 0, len(grid.g) - 2))
        w = (g0 - grid.g[j]) / (grid.g[j + 1] - grid.g[j])
        at_g0 = nodes[:, :, j] * (1.0 - w) + nodes[:, :, j + 1] * w  # linear in g within a cell
        self.log_sigma_t = np.asarray(grid.log_sigma_t, dtype=np.float64)
        rows = np.concatenate([at_g0[0], at_g0[-1]], axis=1)  # (ns, 6): least A, B, C, most A, B, C
        self._rows, self._slopes = rows[:-1], np.diff(rows, axis=0) / np.diff(self.log_sigma_t)[:, None]

    def coefficients(self, log_sigma_t: np.ndarray) -> np.ndarray:
        """(6, N): A, B, C of the least, then of the most scattering material at ln σt (clamped)."""
        ls = np.clip(log_sigma_t, self.log_sigma_t[0], self.log_sigma_t[-1])
        k = np.clip(np.searchsorted(self.log_sigma_t, ls, side="right") - 1, 0, len(self._rows) - 1)
        return (self._rows[k] + self._slopes[k] * (ls - self.log_sigma_t[k])[:, None]).T

    def ends(self, log_sigma_t: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """I(ρ) of the least and the most scattering material at ln σt (clamped to the grid)."""
        return self._ends(self.coefficients(log_sigma_t), rho)

    @staticmethod
    def _ends(coef: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f_least, f_most = rho / (1.0 - coef[2] * rho), rho / (1.0 - coef[5] * rho)
        return coef[0] + coef[1] * f_least, coef[3] + coef[4] * f_most


def network_inputs(x: np.ndarray, scatter_range: ScatterRange) -> np.ndarray:
    """The network's input (N, 5) float32 (INPUTS) from the fit's features x (N, 5) (FEATURES), with
    the ends of the forward model the network was trained against."""
    x = np.asarray(x, dtype=np.float64)
    coef = scatter_range.coefficients(x[:, 2])
    out = np.empty((len(x), 5), dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        for col, rho in ((0, x[:, 3]), (1, x[:, 4])):
            lo, hi = ScatterRange._ends(coef, rho)
            t = np.clip(np.nan_to_num((x[:, col] ** 2 - lo) / (hi - lo), nan=0.5), _LOGIT_CLIP, 1.0 - _LOGIT_CLIP)
            out[:, col] = np.log(t / (1.0 - t))
    out[:, 2:] = x[:, 2:]
    return out


class MlpInverter:
    def __init__(self, model: bytes, path: str | Path, map_checksum: str, log_sigma_range: tuple[float, float],
                 alpha_range: tuple[float, float], g_range: tuple[float, float]) -> None:
        """model: the ONNX file's bytes (trimeter.inversion.artifacts reads them), path: where they came from
        (for messages); the ranges: the map's ln σt, α and g boxes."""
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1   # one core: the benchmark's unit, and the machine is shared
        opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(model, sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for corrupt files
            raise MapFileError(f"{path}: not a loadable ONNX model ({str(exc).splitlines()[0]})") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if meta.get("trimeter.kind") != MODEL_KIND:
            raise MapFileError(f"{path}: not a trimeter MLP inverse model (metadata trimeter.kind is "
                               f"{shown(meta.get('trimeter.kind'))})")
        if meta.get("trimeter.format") != MODEL_FORMAT:
            raise MapFileError(f"{path}: metadata trimeter.format {shown(meta.get('trimeter.format'))} is not "
                               f"supported (expected {MODEL_FORMAT!r})")
        if meta.get("trimeter.features") != ",".join(INPUTS):
            raise MapFileError(f"{path}: metadata trimeter.features {shown(meta.get('trimeter.features'))} is not "
                               f"{','.join(INPUTS)!r}; retrain it with tools/train_mlp.py")
        if map_checksum and meta.get("trimeter.map_sha256") != map_checksum:
            raise MapFileError(f"{path}: trained on map {shown(meta.get('trimeter.map_sha256'), 12)}, not on this "
                               f"map ({map_checksum[:12]}…); retrain it with tools/train_mlp.py")
        self.path = path
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        wanted = ((inputs, len(INPUTS)), (outputs, 2))
        if any(len(io) != 1 or io[0].type != "tensor(float)" or len(io[0].shape) != 2 or io[0].shape[1] != width
               for io, width in wanted):
            declared = [(x.type, x.shape) for x in inputs + outputs]
            raise MapFileError(f"{path}: model must map float32 (N, {len(INPUTS)}) to float32 (N, 2), declares "
                               f"{shown(declared)}")
        self.input_name = inputs[0].name
        self.log_sigma_range = log_sigma_range
        self.alpha_range, self.g_range = alpha_range, g_range
        self._bound: tuple[ForwardGrid, MlpGuesser] | None = None  # (grid, its guesser)

    def on(self, grid: ForwardGrid) -> MlpGuesser:
        """This network as a fit's guesser (trimeter.inversion.kernel.Guesser) on the forward model `grid`
        (the last one kept: every fit of one map asks with the same grid)."""
        if self._bound is None or self._bound[0] is not grid:
            self._bound = (grid, MlpGuesser(self, grid))
        return self._bound[1]

    def run(self, inputs: np.ndarray) -> np.ndarray:
        """The network's raw (α, g) (N, 2) float32 for its inputs (N, 5) float32 (INPUTS), unclamped."""
        return self.session.run(None, {self.input_name: inputs})[0]


class MlpGuesser:
    """A network bound to the forward model its inputs are made with: the fit's Guesser."""

    def __init__(self, network: MlpInverter, grid: ForwardGrid) -> None:
        self.network, self.scatter_range = network, ScatterRange(grid)
        self.log_sigma_range = network.log_sigma_range

    def run(self, x: np.ndarray) -> np.ndarray:
        """(α, g) (N, 2) for the fit's features x (N, 5) (FEATURES), clamped to the map's box."""
        y = self.network.run(network_inputs(x, self.scatter_range)).astype(np.float64)
        y[:, 0] = np.minimum(np.maximum(y[:, 0], self.network.alpha_range[0]), self.network.alpha_range[1])
        y[:, 1] = np.minimum(np.maximum(y[:, 1], self.network.g_range[0]), self.network.g_range[1])
        return y

    def predict(self, I_b: np.ndarray, I_w: np.ndarray, sigma_t: np.ndarray, rho_b: np.ndarray,
                rho_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y = self.run(features(I_b, I_w, sigma_t, rho_b, rho_w, self.log_sigma_range))
        return y[:, 0], y[:, 1]


METHOD = Method("mlp", "a small network's guess (maps/<map-name>.onnx), then the Newton polish on the forward map",
                guesser=lambda model, options: model.mlp(options.get("mlp_model")).on(model.grid), needs=(".onnx",),
                # p0: the network alone; p2: two fixed Newton steps, as lut p2 (their cost side by side)
                bench_variants=(("p0", dict(polish=0)), ("p2", dict(polish=2, polish_tol=0.0)), ("p≤8", {})))
