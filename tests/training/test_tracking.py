"""Logging a shipped file to MLflow as a model: what the registry and `mlflow models serve` read."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import onnx
import pytest
from mlflow.models import Model

from service.core.manifest import read_manifest
from training.tracking import default_tracking_uri, log_onnx_model, onnx_model_requirements

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    mlflow.set_tracking_uri(default_tracking_uri())
    mlflow.set_experiment("tracking")  # not the active experiment of an earlier test's store


def test_a_streaming_graph_is_logged_with_its_state_inputs_and_answers_several_sessions(store) -> None:
    """A streaming graph (features, h0, c0 → velocity, h, c) is logged with every input named as in its manifest,
    its batch axes variable (the state's is the second), an input example with the zero state, and the pip
    requirements written out; MLflow's own loader answers its example and a batch of three sessions."""
    model_dir = REPO / "onnx_models/pose_full6_velocity/1.0.0"
    manifest = read_manifest(model_dir / "manifest.json")
    with np.load(model_dir / "golden.npz") as z:
        golden = dict(z)
    with mlflow.start_run():
        info = log_onnx_model(onnx.load(str(model_dir / "model.onnx")), golden, manifest)
    inputs = {s.name: s.shape for s in info.signature.inputs.inputs}
    assert inputs == {"features": (-1, -1, 66), "h0": (2, -1, 256), "c0": (2, -1, 256)}
    local = Path(mlflow.artifacts.download_artifacts(info.model_uri))
    assert (local / "requirements.txt").read_text().split() == onnx_model_requirements()
    example = Model.load(info.model_uri).load_input_example(str(local))
    assert set(example) == {"features", "h0", "c0"} and not example["h0"].any()
    served = mlflow.pyfunc.load_model(info.model_uri)
    np.testing.assert_allclose(served.predict(example)["velocity"], golden["expected"], atol=manifest.parity_atol)
    three = {k: np.repeat(v, 3, axis=1 if k in ("h0", "c0") else 0) for k, v in example.items()}
    answers = served.predict(three)
    assert answers["velocity"].shape == (3, *golden["expected"].shape[1:]) and answers["h"].shape == (2, 3, 256)


def test_a_single_input_graph_keeps_its_unnamed_array_signature(store) -> None:
    """The I2S files take one array (what `mlflow models serve` is benchmarked with), and keep doing so."""
    model_dir = max((REPO / "onnx_models/i2s_assignment").glob("*/manifest.json")).parent
    manifest = read_manifest(model_dir / "manifest.json")
    with np.load(model_dir / "golden.npz") as z:
        golden = dict(z)
    with mlflow.start_run():
        info = log_onnx_model(onnx.load(str(model_dir / "model.onnx")), golden, manifest)
    assert not info.signature.inputs.has_input_names()
    (answer,) = mlflow.pyfunc.load_model(info.model_uri).predict(golden["imu"][:2]).values()
    np.testing.assert_allclose(answer, golden["expected"][:2], atol=manifest.parity_atol)
