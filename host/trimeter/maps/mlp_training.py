"""Training the `mlp` inverse of an appearance map (the pipeline's onnx stage; trimeter.maps.pipeline).

Training data: random materials at continuous (α, σt, g) (α denser towards 1, ln σt uniform, g
uniform over the map's range) and random backgrounds (ρ_b ∈ [0, 0.1], ρ_w ∈ [0.85, 1]) pushed
through the map as it is evaluated between its nodes (AppearanceMap.between_nodes: the model the
polish refines the guess on), I_b and I_w jittered by a fraction of the fit's default noise model so
that the network answers noisy bins smoothly. Inputs (the forward model's normalisation of I_b, I_w)
and targets (α, g): trimeter.inversion.mlp.
scikit-learn trains (StandardScaler + MLPRegressor, Adam with a cosine-decayed learning rate: one
epoch per partial_fit); the network is written as a plain ONNX graph
(network_graph: Gemm layers, the scaler folded in) with the map's SHA-256 (its parent) and the
producer's version stored in the model's metadata; inference refuses a model used with any other map.
Needs the `maps` extra (scikit-learn, onnx).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    import onnx

    from trimeter.formats.appearance import AppearanceMap


# Size, samples, epochs, schedule and jitter are chosen on the l0.4 held-out set with the network alone (`trimeter
# bench fit`'s mlp p0 row; the sweep: in git, maps/README.md's MLP section): a constant step leaves a network short of
# what its size can fit, and wider layers then fit the thin samples' weak α and g signal better. jitter: a tenth of
# the fit's default noise model keeps the guess smooth across noisy bins without blurring that signal.
class TrainingDefaults(TypedDict):
    hidden: tuple[int, ...]
    samples: int
    epochs: int
    seed: int
    activation: str
    jitter: float
    learning_rate: float  # Adam's initial step, decayed on a cosine to LEARNING_RATE_FLOOR of it by the last epoch


DEFAULTS: TrainingDefaults = {"hidden": (64, 64), "samples": 300000, "epochs": 60, "seed": 0, "activation": "relu",
                              "jitter": 0.1, "learning_rate": 3e-3}
LEARNING_RATE_FLOOR = 0.02
# the validation's g error is taken where g is determined enough to be scored (trimeter.bench.fit_scoring.G_MIN_ALPHA)
G_SCORED_ALPHA = 0.5


def training_set(amap: AppearanceMap, n: int, rng: np.random.Generator,
                 jitter: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(network inputs (n, 5) float32, targets (α, g) (n, 2) float32); jitter: the intensities' noise as a
    fraction of the fit's default noise model (σ_I = 0.005·I + 2e-4)."""
    from trimeter.inversion.mlp import ScatterRange, features, network_inputs

    grid = amap.between_nodes
    a_lo, a_hi = grid.alpha_range
    u = rng.uniform(0, 1, n)
    alpha = np.where(rng.uniform(0, 1, n) < 0.5, a_lo + (a_hi - a_lo) * u, a_hi - (a_hi - a_lo) * u ** 2)
    log_s = rng.uniform(float(grid.log_sigma_t[0]), float(grid.log_sigma_t[-1]), n)
    g = rng.uniform(*grid.g_range, n)
    rho_b = rng.uniform(0.0, 0.1, n)
    rho_w = rng.uniform(0.85, 1.0, n)
    sigma_t = np.exp(log_s)
    I_b, I_w, _ = grid.intensities(alpha, sigma_t, g, rho_b, rho_w)
    if jitter:
        I_b = I_b + jitter * (0.005 * I_b + 2e-4) * rng.standard_normal(n)
        I_w = I_w + jitter * (0.005 * I_w + 2e-4) * rng.standard_normal(n)
    x = features(I_b, I_w, sigma_t, rho_b, rho_w, (grid.log_sigma_t[0], grid.log_sigma_t[-1]))
    return network_inputs(x, ScatterRange(grid)), np.column_stack([alpha, g]).astype(np.float32)


def learning_rates(initial: float, epochs: int) -> np.ndarray:
    """Adam's step per epoch: a cosine from `initial` down to LEARNING_RATE_FLOOR·initial at the last epoch."""
    phase = np.arange(epochs) / max(epochs - 1, 1)
    return initial * (LEARNING_RATE_FLOOR + (1.0 - LEARNING_RATE_FLOOR) * 0.5 * (1.0 + np.cos(np.pi * phase)))


def train(amap: AppearanceMap, hidden: tuple[int, ...] = DEFAULTS["hidden"], samples: int = DEFAULTS["samples"],
          epochs: int = DEFAULTS["epochs"], seed: int = DEFAULTS["seed"], activation: str = DEFAULTS["activation"],
          jitter: float = DEFAULTS["jitter"],
          learning_rate: float = DEFAULTS["learning_rate"]) -> tuple[Any, dict[str, float]]:
    """The fitted StandardScaler + MLPRegressor pipeline and its validation on fresh noise-free samples
    (α abs p95 over all of them, g abs p95 over all and over α ≥ G_SCORED_ALPHA)."""
    import warnings

    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    rng = np.random.default_rng(seed)
    x, y = training_set(amap, samples, rng, jitter)
    scaler = StandardScaler().fit(x)
    xs = scaler.transform(x)
    # partial_fit runs one epoch (shuffled mini-batches) per call and keeps Adam's moments between calls
    net = MLPRegressor(hidden_layer_sizes=hidden, activation=activation, batch_size=256,
                       learning_rate_init=learning_rate, max_iter=1, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ConvergenceWarning: each call is one epoch by design
        for epoch, rate in enumerate(learning_rates(learning_rate, epochs)):
            if epoch:  # scikit-learn has no public way to change Adam's step between partial_fit calls
                optimizer: Any = getattr(net, "_optimizer", None)
                if not hasattr(optimizer, "learning_rate_init"):
                    raise RuntimeError("scikit-learn's MLPRegressor no longer keeps its Adam optimizer in "
                                       "`_optimizer.learning_rate_init`: the cosine step schedule cannot be applied")
                optimizer.learning_rate_init = rate
            net.partial_fit(xs, y)
    model = make_pipeline(scaler, net)
    xv, yv = training_set(amap, 20000, np.random.default_rng(seed + 1))
    err = np.abs(model.predict(xv) - yv)
    scored = yv[:, 0] >= G_SCORED_ALPHA
    return model, {"alpha_abs_p95": float(np.percentile(err[:, 0], 95)),
                   "g_abs_p95": float(np.percentile(err[:, 1], 95)),
                   "g_abs_p95_scored": float(np.percentile(err[scored, 1], 95))}


def network_graph(model: Any) -> onnx.ModelProto:
    """The fitted StandardScaler + MLPRegressor pipeline as a plain ONNX graph: Gemm, activation, …,
    Gemm, with the scaler folded into the first layer (W₁' = diag(1/scale)·W₁,
    b₁' = b₁ − (mean/scale)·W₁).
    Why not skl2onnx: its graph (an ai.onnx.ml Scaler, a Cast, MatMul + Add per layer, a final
    Reshape that interleaved the two outputs) runs markedly slower in onnxruntime than this one, for the
    same predictions to float32 rounding."""
    from onnx import TensorProto, helper, numpy_helper

    from trimeter.inversion.mlp import INPUTS

    scaler, net = model.steps[0][1], model.steps[-1][1]
    activation = {"relu": "Relu", "tanh": "Tanh"}.get(net.activation)
    if activation is None or net.out_activation_ != "identity":
        raise ValueError(f"unsupported network: activation {net.activation!r}, output {net.out_activation_!r}")
    weights = [np.asarray(w, dtype=np.float64) for w in net.coefs_]
    biases = [np.asarray(b, dtype=np.float64) for b in net.intercepts_]
    mean = np.zeros(weights[0].shape[0]) if scaler.mean_ is None else scaler.mean_
    scale = np.ones(weights[0].shape[0]) if scaler.scale_ is None else scaler.scale_
    biases[0] = biases[0] - (mean / scale) @ weights[0]
    weights[0] = weights[0] / scale[:, None]
    nodes, inits, x = [], [], "features"
    for k, (w, b) in enumerate(zip(weights, biases, strict=True)):
        inits += [numpy_helper.from_array(flush_subnormals(w), f"W{k}"),
                  numpy_helper.from_array(flush_subnormals(b), f"b{k}")]
        last = k == len(weights) - 1
        y = "alpha_g" if last else f"z{k}"
        nodes.append(helper.make_node("Gemm", [x, f"W{k}", f"b{k}"], [y]))
        if not last:
            nodes.append(helper.make_node(activation, [y], [f"h{k}"]))
            x = f"h{k}"
    n_in, n_out = len(INPUTS), weights[-1].shape[1]
    graph = helper.make_graph(nodes, "trimeter-mlp-inverse",
                              [helper.make_tensor_value_info("features", TensorProto.FLOAT, [None, n_in])],
                              [helper.make_tensor_value_info("alpha_g", TensorProto.FLOAT, [None, n_out])], inits)
    onx = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="trimeter")
    onx.ir_version = 8  # onnxruntime ≥ 1.17 reads IR 8 / opset 17
    return onx


# A weight below this fraction of the largest in its tensor changes no prediction beyond float32 rounding (~6e-8).
NEGLIGIBLE_WEIGHT = 1e-12


def flush_subnormals(values: ArrayLike) -> np.ndarray:
    """float32 weights with the values that make subnormals set to zero: subnormal weights, and weights
    below NEGLIGIBLE_WEIGHT of the tensor's largest (the L2 penalty decays a dead unit's weights towards
    ~1e-38, still normal, but their products with the activations are subnormal). Either changes no
    prediction beyond float32 rounding, but onnxruntime's CPU kernels take the processor's slow path on
    them, several times slower."""
    out = np.asarray(values, dtype=np.float32).copy()
    largest = float(np.max(np.abs(out))) if out.size else 0.0
    out[np.abs(out) < max(np.finfo(np.float32).tiny, NEGLIGIBLE_WEIGHT * largest)] = 0.0
    return out


def export(model: Any, amap: AppearanceMap, path: Path, hidden: tuple[int, ...], stats: dict[str, float],
           producer: dict[str, str] | None = None) -> Path:
    """Write the network as ONNX (atomically), its metadata naming the parent map's SHA-256 and the
    producer (name, version), after checking it reproduces scikit-learn's predictions."""
    import onnx

    from trimeter.atomic import atomic_write
    from trimeter.inversion.mlp import INPUTS, MODEL_FORMAT, MODEL_KIND
    from trimeter.formats.stages import stage_producer

    producer = producer or stage_producer("onnx")

    onx = network_graph(model)
    onnx.checker.check_model(onx)
    check = np.random.default_rng(0).uniform(0, 1, (64, len(INPUTS))).astype(np.float32)
    import onnxruntime as ort

    got = ort.InferenceSession(onx.SerializeToString(), providers=["CPUExecutionProvider"]).run(
        None, {onx.graph.input[0].name: check})[0]
    if got.shape != (64, 2) or not np.allclose(got, model.predict(check), atol=1e-4):
        raise RuntimeError("exported ONNX model does not reproduce scikit-learn's predictions")
    meta = {"trimeter.kind": MODEL_KIND, "trimeter.format": MODEL_FORMAT, "trimeter.map_sha256": amap.checksum,
            "trimeter.map_name": amap.name, "trimeter.features": ",".join(INPUTS), "trimeter.outputs": "alpha,g",
            "trimeter.hidden": ",".join(map(str, hidden)),
            "trimeter.producer": producer["name"], "trimeter.producer_version": producer["version"],
            "trimeter.validation": ",".join(f"{k}={v:.4g}" for k, v in stats.items())}
    for key, value in meta.items():
        prop = onx.metadata_props.add()
        prop.key, prop.value = key, value
    return atomic_write(path, onx.SerializeToString())
