"""Warm start from a shipped ONNX model: the rebuilt torch weights reproduce the model's golden output."""

from pathlib import Path

import numpy as np
import pytest
import torch

from training.models import AssignmentNet
from training.warmstart import warm_start_from_shipped

SHIPPED = Path(__file__).resolve().parents[2] / "onnx_models" / "i2s_assignment"


def test_rebuilt_weights_match_the_shipped_model() -> None:
    model_dir = sorted(p.parent for p in SHIPPED.glob("*/manifest.json"))[-1]
    net = AssignmentNet()
    net.load_state_dict(warm_start_from_shipped(model_dir, net))
    net.eval()
    with np.load(model_dir / "golden.npz") as golden, torch.no_grad():
        got = torch.softmax(net(torch.from_numpy(golden["imu"])), -1).numpy()
        np.testing.assert_allclose(got, golden["expected"], atol=1e-4)


def test_a_wrong_golden_is_refused(tmp_path: Path) -> None:
    model_dir = sorted(p.parent for p in SHIPPED.glob("*/manifest.json"))[-1]
    (tmp_path / "model.onnx").write_bytes((model_dir / "model.onnx").read_bytes())
    with np.load(model_dir / "golden.npz") as golden:
        np.savez(tmp_path / "golden.npz", imu=golden["imu"], expected=golden["expected"][:, ::-1])
    with pytest.raises(ValueError, match="differ from its golden output"):
        warm_start_from_shipped(tmp_path, AssignmentNet())
