"""The real-data pose check on one real recording with the shipped lower-body model and I2S alignment."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.core.recordings import read_capacitive_oriented
from service.inference.pose import PoseModel
from service.inference.registry import load_model, load_models
from training.pose.real_check import check_recording, knee_flexion_deg

REPO = Path(__file__).resolve().parents[3]


def test_knee_flexion_reads_a_known_bend() -> None:
    from scipy.spatial.transform import Rotation

    thigh = np.broadcast_to(np.eye(3), (3, 3, 3))
    shank = Rotation.from_rotvec([[0, np.radians(a), 0] for a in (0.0, 30.0, 60.0)]).as_matrix()  # ankle behind
    np.testing.assert_allclose(knee_flexion_deg(thigh, shank), [0.0, 30.0, 60.0], atol=1e-9)


def test_the_lower_body_model_follows_the_real_thigh_sensors(data_dir: Path) -> None:
    models = load_models(REPO / "onnx_models", 1)
    lower = next(
        m
        for m in models.values()
        if m.manifest.task == "imu_pose"
        and not m.manifest.pose.streaming
        and m.manifest.pose.sensors == ["Pelvis", "LeftLowerLeg", "RightLowerLeg"]
    )
    out = check_recording(
        read_capacitive_oriented(data_dir, "CSBaseline"), PoseModel(load_model(lower.path, 1)), models["i2s_alignment"]
    )
    print(out)
    assert out["knee_flexion_correlation"] > 0.7  # the predicted knee bends with the measured one
    assert out["knee_range_sensors_deg"] > 30.0 and out["knee_range_model_deg"] > 15.0
    assert out["upperleg_angle_deg"] < 40.0
