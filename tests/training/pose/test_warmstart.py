"""Pose networks rebuilt from shipped ONNX files (``train.init_from_onnx``): the served weights, exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from service.core.calibration import features_per_frame
from service.core.manifest import read_manifest
from training.pose.config import PoseConfig
from training.pose.pipeline import shipped_config
from training.pose.train import build_net
from training.pose.warmstart import warm_start_from_shipped

MODELS = Path(__file__).resolve().parents[3] / "onnx_models"


def recipe(model_dir: Path, **changes) -> PoseConfig:
    """The config of a shipped file's recipe as far as its weights go (sensors, outputs, frames, network)."""
    m = read_manifest(model_dir / "manifest.json")
    model = {**architecture(model_dir), "look_ahead": m.pose.look_ahead_frames if m.pose.streaming else 0}
    base = {**shipped_config(m).model_dump(), "output_segments": m.pose.output_segments, "model": model}
    return PoseConfig.model_validate(base | changes)


def architecture(model_dir: Path) -> dict:
    """The network of a shipped file ("bilstm hidden 128 x 2"; an average's: "mean of 2 × bilstm hidden …")."""
    text = read_manifest(model_dir / "manifest.json").pose.architecture.split("×")[-1]
    kind, _, hidden, _, layers = text.split()[:5]
    return {"kind": kind, "hidden": int(hidden), "layers": int(layers)}


@pytest.mark.parametrize("model", ["pose_lower3/3.0.0", "pose_full6_stream/4.0.0"])
def test_a_shipped_file_comes_back_as_the_network_that_answers_like_it(model: str) -> None:
    """Offline (a Bi-LSTM) and streaming (an LSTM with look-ahead and state): torch with the rebuilt weights
    answers a stretch of features as onnxruntime answers it from the file (beyond the golden frames the check
    inside already compares)."""
    model_dir = MODELS / model
    m = read_manifest(model_dir / "manifest.json")
    a = architecture(model_dir)
    cfg = recipe(model_dir)
    net = build_net(cfg, features_per_frame(len(cfg.sensors)))
    net.load_state_dict(warm_start_from_shipped(model_dir, cfg, net))
    net.eval()
    x = np.random.default_rng(0).normal(size=(2, 90, features_per_frame(len(cfg.sensors)))).astype(np.float32)
    session = ort.InferenceSession(str(model_dir / "model.onnx"), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        if m.pose.streaming:
            z = np.zeros((a["layers"], 2, a["hidden"]), np.float32)
            got = net.step(torch.from_numpy(x), torch.from_numpy(z), torch.from_numpy(z))[0].numpy()
            expected = session.run(None, {"features": x, "h0": z, "c0": z})[0]
        else:
            got = net(torch.from_numpy(x)).numpy()
            expected = session.run(None, {"features": x})[0]
    np.testing.assert_allclose(got, expected, atol=2e-5)
    # the feature standardisation is the shipped one, not recomputed
    assert not np.allclose(net.std.numpy(), 1.0)


def test_a_file_of_another_recipe_or_an_average_of_networks_is_refused_with_what_differs() -> None:
    lower3 = MODELS / "pose_lower3/3.0.0"
    base = recipe(lower3).model_dump()
    a = architecture(lower3)

    def attempt(model_dir: Path, **changes) -> str:
        cfg = PoseConfig.model_validate(base | changes)
        with pytest.raises(ValueError) as err:
            warm_start_from_shipped(model_dir, cfg, build_net(cfg, features_per_frame(len(cfg.sensors))))
        return str(err.value)

    assert "do not fit" in attempt(lower3, model={**a, "hidden": 64})
    frames = attempt(lower3, data={**base["data"], "limb_twist": "rig"})
    assert "limb_twist" in frames and "'shipped': 'hinge'" in frames
    sensors = attempt(lower3, sensors=["Pelvis", "LeftUpperLeg", "RightUpperLeg"])
    assert "sensors" in sensors
    average = MODELS / "pose_full6/4.1.0"  # the mean of two networks
    m6 = read_manifest(average / "manifest.json")
    assert len(m6.training_data["ensemble_of"]) == 2
    said = attempt(
        average, sensors=m6.pose.sensors, output_segments=m6.pose.output_segments, model=architecture(average)
    )
    assert "restore-model" in said and m6.training_data["ensemble_of"][0] in said
