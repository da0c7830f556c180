"""Shipping a streaming pose model exported with a batch of one again with a symbolic batch dimension."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.servers import REPO
from service.core.manifest import read_manifest
from service.inference.pose import PoseModel
from service.inference.registry import load_model
from training.pose.export import free_batch_dimension

ARCHIVED = REPO / "mlflow_snapshot" / "models" / "pose_lower3_stream" / "1.0.0"


def test_the_derived_model_batches_sessions_and_says_where_it_came_from(tmp_path) -> None:
    folder = free_batch_dimension(ARCHIVED, "9.9.9", tmp_path)
    manifest = read_manifest(folder / "manifest.json")
    assert manifest.version == "9.9.9" and manifest.exporter["derived_from"] == "pose_lower3_stream/1.0.0"
    assert manifest.inputs[0].shape[0] == "batch" and manifest.inputs[1].shape == [2, "batch", 128]
    assert manifest.mlflow == read_manifest(ARCHIVED / "manifest.json").mlflow  # the same run's weights
    before, after = PoseModel(load_model(ARCHIVED, 1)), PoseModel(load_model(folder, 1))
    assert not before.batchable and after.batchable
    rng = np.random.default_rng(0)
    features = [rng.normal(size=(n, 30)).astype(np.float32) for n in (4, 4, 6)]
    one = [before.step(f, before.new_state()) for f in features]
    many, states = after.step_many(features, [after.new_state() for _ in features])
    for (y, state), y_batched, state_batched in zip(one, many, states, strict=True):
        np.testing.assert_allclose(y_batched, y, atol=1e-5)
        np.testing.assert_allclose(state_batched.h, state.h, atol=1e-5)
    with pytest.raises(ValueError, match="symbolic already"):
        free_batch_dimension(folder, "9.9.10", tmp_path)
