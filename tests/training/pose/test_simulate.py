"""Virtual IMUs on the canonical body: what a real sensor would read, through the service's calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.core.body import BODY_SEGMENTS, BodyMotion
from service.core.rotations import matrix_from_quat
from training.pose.config import SIX_SENSORS
from training.pose.data import MotionClip, load_motion, mirrored
from training.pose.simulate import NO_NOISE, acceleration, root_relative_targets, simulate_sensors, simulate_session
from training.pose.train import geodesic_deg


def test_both_acceleration_methods_differentiate_twice() -> None:
    t = np.arange(600) / 60.0
    x = np.stack([0.5 * 2.0 * t**2, np.sin(2 * np.pi * 1.0 * t), 0 * t], axis=1)  # a = (2, -(2π)² sin, 0)
    truth = np.stack([2.0 + 0 * t, -((2 * np.pi) ** 2) * np.sin(2 * np.pi * t), 0 * t], axis=1)
    for method, tol in (("finite_difference", 0.7), ("butterworth", 0.2)):
        a = acceleration(x, 60.0, method)
        # a second difference over h reads a sine (ωh)²/12 low: 1.5 % for n = 4, 0.4 % for h = 1/60 s; no delay
        assert np.abs(a[60:-60] - truth[60:-60]).max() < tol, method
    with pytest.raises(ValueError, match="acc_method"):
        acceleration(x, 60.0, "spline")


def _still_motion(T: int = 120) -> BodyMotion:
    R = np.broadcast_to(np.eye(3), (T, len(BODY_SEGMENTS), 3, 3)).copy()
    p = np.zeros((T, len(BODY_SEGMENTS), 3))
    return BodyMotion(R, p, p.copy(), 60.0)


def test_a_sensor_at_rest_reads_gravity_up_and_no_rotation() -> None:
    raw = simulate_sensors(_still_motion(), SIX_SENSORS, np.random.default_rng(0), NO_NOISE)
    R_ws = matrix_from_quat(raw.q_world_sensor)  # (T, N, 3, 3), in a world turned by raw.heading_rad about z
    up_in_sensor = np.einsum("tnji,j->tni", R_ws, [0.0, 0.0, 9.81])
    np.testing.assert_allclose(raw.acc_mps2, up_in_sensor, atol=1e-9)
    np.testing.assert_allclose(raw.gyr_rads, 0.0, atol=1e-9)


def test_a_session_recovers_the_true_segments_through_the_declared_calibration(data_dir: Path) -> None:
    motion = load_motion(data_dir / "mocap/cmu_iclone/07_01.bvh", "cmu_iclone")
    outputs = [s for s in BODY_SEGMENTS if s not in SIX_SENSORS]
    s = simulate_session(motion, SIX_SENSORS, outputs, np.random.default_rng(1), NO_NOISE)
    # no noise: the calibrated sensor segments are the truth in the sensors' world frame
    from scipy.spatial.transform import Rotation

    Rz = Rotation.from_rotvec([0.0, 0.0, s.heading_rad]).as_matrix()
    idx = [BODY_SEGMENTS.index(x) for x in SIX_SENSORS]
    np.testing.assert_allclose(
        s.R_world_sensor_segment, np.einsum("ij,tnjk->tnik", Rz, motion.R_world_segment[:, idx]), atol=1e-6
    )
    np.testing.assert_allclose(s.targets, root_relative_targets(motion, outputs), atol=1e-6)
    assert s.features.shape == (motion.n_frames, 66) and s.features.dtype == np.float32
    with pytest.raises(ValueError, match="Pelvis"):
        simulate_session(motion, ["Head", "Pelvis"], outputs, np.random.default_rng(1))


# each segment by its counterpart on the other side (the midline keeps its own)
_SIDE_SWAPPED = [s.replace("Left", "#").replace("Right", "Left").replace("#", "Right") for s in BODY_SEGMENTS]


def test_the_mirror_image_body_swaps_sides_and_keeps_left_on_the_left(data_dir: Path) -> None:
    motion = load_motion(data_dir / "mocap/cmu_iclone/07_01.bvh", "cmu_iclone")
    clip = MotionClip("07_01.bvh", "cmu_iclone", "cmu_07", "walk", motion, "d")
    m = mirrored(clip).motion
    R, Rm = motion.R_world_segment, m.R_world_segment
    np.testing.assert_allclose(np.linalg.det(Rm), 1.0, atol=1e-6)  # proper rotations, not reflections
    i = BODY_SEGMENTS.index

    def lateral(mo: BodyMotion, seg: str) -> np.ndarray:  # the joint's offset from the hips' centre, pelvis frame
        p = mo.origin_m[:, i(seg)] - mo.origin_m[:, i("Pelvis")]
        return np.einsum("tji,tj->ti", mo.R_world_segment[:, i("Pelvis")], p)[:, 1]

    # the left hip stays on the pelvis's left (+y), as far out as the original's right hip is to the right
    assert np.median(lateral(m, "LeftUpperLeg")) > 0.03 and np.median(lateral(m, "RightUpperLeg")) < -0.03
    np.testing.assert_allclose(lateral(m, "LeftUpperLeg"), -lateral(motion, "RightUpperLeg"), atol=1e-9)
    # a joint's angle moves to the other side unchanged (the left knee now bends as the right one did)
    knee = geodesic_deg(R[:, i("RightUpperLeg")], R[:, i("RightLowerLeg")])
    np.testing.assert_allclose(geodesic_deg(Rm[:, i("LeftUpperLeg")], Rm[:, i("LeftLowerLeg")]), knee, atol=1e-4)
    assert knee.max() > 30.0  # a walk: the check above compares something that moves
    # the midline stays the midline; heights are kept; mirrored twice is the clip itself
    np.testing.assert_allclose(m.origin_m[..., 2], motion.origin_m[:, [i(s) for s in _SIDE_SWAPPED], 2], atol=0)
    twice = mirrored(mirrored(clip))
    np.testing.assert_array_equal(twice.motion.R_world_segment, R)
    np.testing.assert_array_equal(twice.motion.midpoint_m, motion.midpoint_m)
    assert mirrored(clip).digest != clip.digest
