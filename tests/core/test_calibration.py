"""Calibration and pelvis-relative features: known mountings are recovered, the world's heading drops out."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, read_body_motion
from service.core.calibration import (
    CalibrationError,
    features_per_frame,
    is_still,
    pelvis_heading_from_legs,
    pose_features,
    segment_readings,
    still_pose_calibration,
    still_pose_segment_frames,
)
from service.core.rotations import matrix_from_quat, quat_from_matrix

SENSORS = ["Pelvis", "Head", "LeftForeArm", "RightForeArm", "LeftLowerLeg", "RightLowerLeg"]


def _random_motion(rng: np.random.Generator, T: int = 50, N: int = 6) -> tuple[np.ndarray, np.ndarray]:
    R = Rotation.random(T * N, random_state=rng).as_matrix().reshape(T, N, 3, 3)
    return R, rng.normal(size=(T, N, 3)) * 3.0


def _sensor_readings(R_seg: np.ndarray, a_free: np.ndarray, R_seg_sensor: np.ndarray, R_world: np.ndarray):
    """What sensors mounted by ``R_seg_sensor`` report in a world frame turned by ``R_world``."""
    R_ws = np.einsum("ij,tnjk,nkl->tnil", R_world, R_seg, R_seg_sensor)
    f_world = np.einsum("ij,tnj->tni", R_world, a_free) + np.array([0.0, 0.0, 9.81])
    return quat_from_matrix(R_ws), np.einsum("tnji,tnj->tni", R_ws, f_world)


def test_declared_alignments_recover_the_segments_and_the_free_acceleration() -> None:
    rng = np.random.default_rng(0)
    R_seg, a = _random_motion(rng)
    R_ss = Rotation.random(6, random_state=rng).as_matrix()
    q, f = _sensor_readings(R_seg, a, R_ss, np.eye(3))
    R_back, a_back = segment_readings(q, f, quat_from_matrix(R_ss))
    np.testing.assert_allclose(R_back, R_seg, atol=1e-9)
    np.testing.assert_allclose(a_back, a, atol=1e-9)


@pytest.mark.parametrize("heading_deg", [37.0, 90.0, -150.0])
def test_features_do_not_change_when_the_sensors_world_turns_about_the_vertical(heading_deg: float) -> None:
    """ENU, NWU, or a magnetometer-free heading: the same motion gives the same features (Zheng et al. 2021 eq. 2-3)."""
    rng = np.random.default_rng(1)
    R_seg, a = _random_motion(rng)
    R_ss = Rotation.random(6, random_state=rng).as_matrix()
    Rz = Rotation.from_rotvec([0.0, 0.0, np.radians(heading_deg)]).as_matrix()
    feats = []
    for R_world in (np.eye(3), Rz):
        q, f = _sensor_readings(R_seg, a, R_ss, R_world)
        feats.append(pose_features(*segment_readings(q, f, quat_from_matrix(R_ss))))
    assert feats[0].shape == (50, features_per_frame(6))
    np.testing.assert_allclose(feats[0], feats[1], atol=1e-5)
    # ... but a tilt of the world (a wrong up axis) does change them: the check is not vacuous
    tilt = Rotation.from_rotvec([0.3, 0.0, 0.0]).as_matrix()
    q, f = _sensor_readings(R_seg, a, R_ss, tilt)
    assert np.abs(pose_features(*segment_readings(q, f, quat_from_matrix(R_ss))) - feats[0]).max() > 0.05


@pytest.mark.parametrize("pose", ["npose", "tpose"])
def test_a_still_pose_recovers_every_mounting_and_the_heading(pose: str) -> None:
    rng = np.random.default_rng(2)
    heading = Rotation.from_rotvec([0.0, 0.0, 2.1]).as_matrix()  # the body faces some direction in the world
    R_seg = np.einsum("ij,njk->nik", heading, still_pose_segment_frames(SENSORS, pose))
    R_ss = Rotation.random(6, random_state=rng).as_matrix()
    # the pelvis sensor sits on the lower back: its z out of the skin (posterior, −x of the pelvis), any roll
    roll = Rotation.from_rotvec([0.0, 0.0, 0.7]).as_matrix()
    R_ss[0] = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]) @ roll
    jitter = Rotation.from_rotvec(rng.normal(scale=0.002, size=(120, 6, 3))).as_matrix()
    R_ws = np.einsum("tnij,njk,nkl->tnil", jitter, R_seg, R_ss)
    q_cal = still_pose_calibration(quat_from_matrix(R_ws), SENSORS, pose)
    err = Rotation.from_matrix(matrix_from_quat(q_cal)).inv() * Rotation.from_matrix(R_ss)
    assert np.degrees(err.magnitude()).max() < 0.5


def test_a_still_pose_needs_a_horizontal_back_axis_and_a_still_span() -> None:
    up = np.tile([1.0, 0.0, 0.0, 0.0], (60, 6, 1))  # every sensor's z straight up: no heading in it
    with pytest.raises(CalibrationError, match="from vertical"):
        still_pose_calibration(up, SENSORS)
    rng = np.random.default_rng(3)
    acc = np.tile([0.0, 0.0, 9.81], (60, 6, 1)) + rng.normal(scale=0.05, size=(60, 6, 3))
    assert is_still(None, acc)[0]
    acc[:, 4] += rng.normal(scale=3.0, size=(60, 3))
    ok, why = is_still(None, acc, SENSORS)
    assert not ok and "LeftLowerLeg" in why


def test_the_segment_set_has_the_sensors_of_every_shipped_placement() -> None:
    assert set(SENSORS) <= set(BODY_SEGMENTS) and len(BODY_SEGMENTS) == 21


@pytest.fixture(scope="module")
def cmu_walk(data_dir: Path) -> SimpleNamespace:
    """Sensors on a real walk (CMU subject 07): random mountings, each sensor's orientation with up to 5° of
    fusion heading error (as the pose simulator draws it)."""
    motion = read_body_motion(data_dir / "mocap/cmu_iclone/07_01.bvh", source="cmu_iclone")
    rng = np.random.default_rng(2)
    R_seg = motion.R_world_segment[:, [BODY_SEGMENTS.index(s) for s in SENSORS]]
    R_ss = Rotation.random(len(SENSORS), random_state=rng).as_matrix()
    heading = Rotation.from_euler("z", rng.uniform(-5.0, 5.0, (len(SENSORS), 1)), degrees=True).as_matrix()
    R_ws = np.einsum("nij,tnjk,nkl->tnil", heading, R_seg, R_ss)
    return SimpleNamespace(q_world_sensor=quat_from_matrix(R_ws), q_segment_sensor=quat_from_matrix(R_ss))


@pytest.mark.parametrize("turn_deg", [0.0, 35.0, 110.0, -170.0])
@pytest.mark.parametrize("world_deg", [0.0, -120.0])
def test_the_legs_turn_a_pelvis_alignment_turned_about_the_vertical_back(cmu_walk, turn_deg: float, world_deg: float):
    """An alignment from a walk with the pelvis turned about its vertical (what I2S gives on some real people) is
    turned back to within the sensors' own heading errors, whatever the world's heading."""
    raw = cmu_walk
    true = matrix_from_quat(raw.q_segment_sensor)
    q = raw.q_segment_sensor.copy()
    q[0] = quat_from_matrix(Rotation.from_euler("z", turn_deg, degrees=True).as_matrix().T @ true[0])
    world = Rotation.from_euler("z", world_deg, degrees=True).as_matrix()
    q_world = quat_from_matrix(np.einsum("ij,tnjk->tnik", world, matrix_from_quat(raw.q_world_sensor)))
    out, turned = pelvis_heading_from_legs(q_world, q, SENSORS)
    left = Rotation.from_matrix(matrix_from_quat(out[0]).T @ true[0]).magnitude()
    assert np.degrees(left) < 6.0, (turned, np.degrees(left))
    assert abs((turned + turn_deg + 180.0) % 360.0 - 180.0) < 6.0
    np.testing.assert_allclose(out[1:], q[1:])  # the other sensors keep theirs


def test_the_legs_heading_needs_a_leg_sensor(cmu_walk) -> None:
    arms = ["Pelvis", "Head", "LeftForeArm", "RightForeArm"]
    with pytest.raises(CalibrationError, match="thigh, shank or foot"):
        pelvis_heading_from_legs(cmu_walk.q_world_sensor[:, :4], cmu_walk.q_segment_sensor[:4], arms)
