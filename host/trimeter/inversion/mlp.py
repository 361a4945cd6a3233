"""`mlp`: a small network (trained by tools/train_mlp.py, shipped as maps/<map-name>.onnx) gives the
initial (α, g); the forward-map Newton polish (trimeter.inversion.newton) refines it at the bins'
true backgrounds. Inference through onnxruntime only (no scikit-learn at run time).

Model contract (checked on load; a mismatch is a MapFileError, never a silent wrong answer):
- metadata `trimeter.kind` = "mlp-inverse", `trimeter.map_sha256` = the SHA-256 of the map it was
  trained on, `trimeter.features` = FEATURES (comma-separated), `trimeter.format` = "1";
- one float32 input (N, 5) in the order FEATURES, one float32 output (N, 2) = (α, g).
σt is not a network output: it comes exactly from I_c (see trimeter.inversion.api).
"""

from __future__ import annotations

import numpy as np

from trimeter.errors import MapFileError
from trimeter.inversion.strategy import Method
from trimeter.validation import shown

MODEL_KIND = "mlp-inverse"
MODEL_FORMAT = "1"
FEATURES = ("sqrt_I_b", "sqrt_I_w", "ln_sigma_t", "rho_b", "rho_w")


def features(I_b, I_w, sigma_t, rho_b, rho_w, log_sigma_range) -> np.ndarray:
    """The network input (N, 5) float32; ln σt clamped to the map's range."""
    ls = np.log(np.maximum(np.asarray(sigma_t, float), 1e-30))
    ls = np.minimum(np.maximum(ls, log_sigma_range[0]), log_sigma_range[1])
    x = np.empty((len(ls), 5), dtype=np.float32)
    x[:, 0] = np.sqrt(np.minimum(np.maximum(I_b, 0.0), 1.0))
    x[:, 1] = np.sqrt(np.minimum(np.maximum(I_w, 0.0), 1.0))
    x[:, 2] = ls
    x[:, 3] = rho_b
    x[:, 4] = rho_w
    return x


class MlpInverter:
    def __init__(self, model: bytes, path, map_checksum: str, log_sigma_range, alpha_range, g_range):
        """model: the ONNX file's bytes (trimeter.maps.artifacts reads them), path: where they came from
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
        if meta.get("trimeter.format", MODEL_FORMAT) != MODEL_FORMAT:
            raise MapFileError(f"{path}: metadata trimeter.format {shown(meta.get('trimeter.format'))} is not "
                               f"supported (expected {MODEL_FORMAT!r})")
        if meta.get("trimeter.features") != ",".join(FEATURES):
            raise MapFileError(f"{path}: metadata trimeter.features {shown(meta.get('trimeter.features'))} is not "
                               f"{','.join(FEATURES)!r}")
        if map_checksum and meta.get("trimeter.map_sha256") != map_checksum:
            raise MapFileError(f"{path}: trained on map {shown(meta.get('trimeter.map_sha256'), 12)}, not on this "
                               f"map ({map_checksum[:12]}…); retrain it with tools/train_mlp.py")
        self.path = path
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        wanted = ((inputs, len(FEATURES)), (outputs, 2))
        if any(len(io) != 1 or io[0].type != "tensor(float)" or len(io[0].shape) != 2 or io[0].shape[1] != width
               for io, width in wanted):
            declared = [(x.type, x.shape) for x in inputs + outputs]
            raise MapFileError(f"{path}: model must map float32 (N, {len(FEATURES)}) to float32 (N, 2), declares "
                               f"{shown(declared)}")
        self.input_name = inputs[0].name
        self.log_sigma_range = log_sigma_range
        self.alpha_range, self.g_range = alpha_range, g_range

    def predict(self, I_b, I_w, sigma_t, rho_b, rho_w):
        y = self.run(features(I_b, I_w, sigma_t, rho_b, rho_w, self.log_sigma_range)).astype(np.float64)
        return (np.minimum(np.maximum(y[:, 0], self.alpha_range[0]), self.alpha_range[1]),
                np.minimum(np.maximum(y[:, 1], self.g_range[0]), self.g_range[1]))

    def run(self, x: np.ndarray) -> np.ndarray:
        """The network's raw (α, g) (N, 2) float32 for features x (N, 5) float32, unclamped."""
        return self.session.run(None, {self.input_name: x})[0]


METHOD = Method("mlp", "a small network's guess (maps/<map-name>.onnx), then the Newton polish on the forward map",
                guesser=lambda model, options: model.mlp(options.get("mlp_model")), needs=(".onnx",),
                bench_variants=(("p0", dict(polish=0)), ("p≤8", {})))
