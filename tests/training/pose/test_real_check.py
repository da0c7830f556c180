"""The real-data pose check on one real recording with the shipped lower-body model and I2S alignment."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.core.recordings import MOVINGREALITY_SEGMENTS, read_capacitive_oriented, read_movingreality_trial
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
    # each knee at its most extended (2nd percentile): the model's straightens about as far as the sensors' knee
    extended = out["knee_extended_sensors_deg"], out["knee_extended_model_deg"]
    assert all(-20.0 < e < 40.0 for e in extended) and abs(extended[1] - extended[0]) < 10.0


def test_the_legs_turn_a_real_pelvis_alignment_round_to_where_the_feet_point(data_dir: Path) -> None:
    """MovingReality pp03 (after stroke, treadmill): I2S aligns the pelvis sensor turned by more than a quarter turn
    against the legs, so the pose's feet point sideways; turned to the shanks' heading, the model's feet come near
    the foot sensors (which the turn does not read)."""
    models = load_models(REPO / "onnx_models", 1)
    lower = PoseModel(load_model(REPO / "onnx_models/pose_lower3/3.0.0", 1))
    sensors = {MOVINGREALITY_SEGMENTS[s.name]: s for s in read_movingreality_trial(data_dir, "pp03", "1Reg")}
    got = {h: check_recording(sensors, lower, models["i2s_alignment"], h) for h in ("alignment", "legs")}
    print({h: round(r["foot_angle_deg"], 1) for h, r in got.items()}, round(got["legs"]["pelvis_turn_deg"], 1))
    assert abs(got["legs"]["pelvis_turn_deg"]) > 60.0
    assert got["legs"]["foot_angle_deg"] < 40.0 < 60.0 < got["alignment"]["foot_angle_deg"]
