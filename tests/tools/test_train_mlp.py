"""tools/train_mlp.py's export: the fitted pipeline as a plain Gemm graph (scaler folded into the
first layer) that onnxruntime runs to scikit-learn's predictions and trimeter's loader accepts."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
pytest.importorskip("sklearn")
onnx = pytest.importorskip("onnx")
_spec = importlib.util.spec_from_file_location("train_mlp", ROOT / "tools" / "train_mlp.py")
train_mlp = importlib.util.module_from_spec(_spec)
sys.modules["train_mlp"] = train_mlp
_spec.loader.exec_module(train_mlp)


@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_the_exported_graph_is_gemm_layers_that_reproduce_the_pipeline(tmp_path, activation):
    from trimeter.inversion.mlp import MlpInverter, ScatterRange, features, network_inputs
    from trimeter.formats.appearance import AppearanceMap

    amap = AppearanceMap.load(ROOT / "tests" / "inversion" / "data" / "ideal-l0.5.tmap")
    model, stats = train_mlp.train(amap, hidden=(8, 6), samples=2000, epochs=3, activation=activation)
    path = train_mlp.export(model, amap, tmp_path / "m.onnx", (8, 6), stats)

    ops = [node.op_type for node in onnx.load(path).graph.node]
    assert ops == ["Gemm", activation.capitalize(), "Gemm", activation.capitalize(), "Gemm"]
    inverter = MlpInverter(path.read_bytes(), path, amap.checksum,
                           (float(np.log(amap.sigma_t[0])), float(np.log(amap.sigma_t[-1]))),
                           (0.0, 1.0), (-1.0, 1.0))
    rng = np.random.default_rng(5)
    n = 500
    x = network_inputs(features(rng.uniform(0, 0.5, n), rng.uniform(0.3, 1, n), np.exp(rng.uniform(-3, 3, n)),
                                rng.uniform(0, 0.1, n), rng.uniform(0.85, 1, n), inverter.log_sigma_range),
                       ScatterRange(amap.between_nodes))
    np.testing.assert_allclose(inverter.run(x), model.predict(x), atol=2e-5)


def test_a_network_the_graph_cannot_express_is_refused():
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    model = make_pipeline(StandardScaler(), MLPRegressor(hidden_layer_sizes=(4,), activation="logistic", max_iter=2))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(np.random.default_rng(0).uniform(size=(50, 5)), np.random.default_rng(1).uniform(size=(50, 2)))
    with pytest.raises(ValueError, match="unsupported network"):
        train_mlp.network_graph(model)


def test_the_learning_rate_decays_on_a_cosine_to_its_floor():
    from trimeter.maps.mlp_training import LEARNING_RATE_FLOOR, learning_rates

    rates = learning_rates(3e-3, 61)
    assert len(rates) == 61 and np.all(np.diff(rates) < 0)
    assert rates[0] == pytest.approx(3e-3) and rates[-1] == pytest.approx(3e-3 * LEARNING_RATE_FLOOR)
    assert rates[30] == pytest.approx((rates[0] + rates[-1]) / 2)  # a cosine: halfway down at half time
    assert learning_rates(1e-3, 1) == pytest.approx([1e-3])  # one epoch: the initial rate, no division by zero


def test_training_follows_the_schedule_and_reports_the_scored_g(monkeypatch):
    """Every epoch is one partial_fit at that epoch's rate (the first at the initial rate), and the
    validation names g's error over the materials where it is scored."""
    from sklearn.neural_network import MLPRegressor

    from trimeter.maps import mlp_training
    from trimeter.formats.appearance import AppearanceMap

    seen = []
    original = MLPRegressor.partial_fit

    def spy(self, x, y, *args, **kwargs):
        seen.append(self._optimizer.learning_rate_init if hasattr(self, "_optimizer") else self.learning_rate_init)
        return original(self, x, y, *args, **kwargs)

    monkeypatch.setattr(MLPRegressor, "partial_fit", spy)
    amap = AppearanceMap.load(ROOT / "tests" / "inversion" / "data" / "ideal-l0.5.tmap")
    _, stats = mlp_training.train(amap, hidden=(8,), samples=500, epochs=4, learning_rate=2e-3)
    np.testing.assert_allclose(seen, mlp_training.learning_rates(2e-3, 4))
    assert set(stats) == {"alpha_abs_p95", "g_abs_p95", "g_abs_p95_scored"}
    assert all(np.isfinite(v) and v >= 0 for v in stats.values())


def test_weights_whose_products_would_be_subnormal_are_flushed():
    """A dead unit's weights decay to ~1e-38 (normal floats, but subnormal once multiplied by an activation):
    zero, like subnormal ones; weights within float32 reach of the tensor's largest are kept exactly."""
    from trimeter.maps.mlp_training import flush_subnormals

    w = np.array([[2.5, -1e-3, 3e-9], [1.2e-38, -4e-30, 1e-45]], dtype=np.float32)
    np.testing.assert_array_equal(flush_subnormals(w), np.array([[2.5, -1e-3, 3e-9], [0, 0, 0]], dtype=np.float32))
    np.testing.assert_array_equal(flush_subnormals(np.zeros(3)), np.zeros(3))
