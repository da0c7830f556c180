"""The ankle in the joint-angle convention, which joints a pose answers, and the wrapped angle error."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.body import BODY_PARENT, BODY_SEGMENTS
from service.core.joint_angles import JOINTS, angle_difference_deg, answered_joints, joint_angles_deg


def _foot_turned(side: str, axis: str, degrees: float) -> np.ndarray:
    """One frame in neutral stance with the ``side`` foot (and its toe) turned about its shank's ``axis``."""
    R = np.tile(np.eye(3), (1, len(BODY_SEGMENTS), 1, 1))
    turned = Rotation.from_euler(axis, degrees, degrees=True).as_matrix()
    for s in (f"{side}Foot", f"{side}Toe"):
        R[0, BODY_SEGMENTS.index(s)] = turned
    return R


def _ankle(side: str, axis: str, degrees: float) -> np.ndarray:
    return joint_angles_deg(_foot_turned(side, axis, degrees), [f"{side}Ankle"])[0, 0]


@pytest.mark.parametrize("side", ["Left", "Right"])
def test_ankle_angles_read_with_anatomical_signs_on_both_sides(side: str) -> None:
    # toes up (the foot turned about the shank's y, left, by a negative angle: x anterior tilts to +z) is dorsiflexion
    np.testing.assert_allclose(_ankle(side, "y", -15.0), [15.0, 0.0, 0.0], atol=1e-9)
    # the sole turned away from the midline: for the left foot its lateral (+y) edge up, a turn about +x
    lateral_up = 10.0 if side == "Left" else -10.0
    np.testing.assert_allclose(_ankle(side, "x", lateral_up), [0.0, 10.0, 0.0], atol=1e-9)
    # toes turned in: for the left foot towards −y, a negative turn about z
    toes_in = -20.0 if side == "Left" else 20.0
    np.testing.assert_allclose(_ankle(side, "z", toes_in), [0.0, 0.0, 20.0], atol=1e-9)


def test_every_joint_is_zero_in_neutral_stance_and_has_two_body_segments() -> None:
    R = np.tile(np.eye(3), (2, len(BODY_SEGMENTS), 1, 1))
    np.testing.assert_allclose(joint_angles_deg(R, list(JOINTS)), 0.0, atol=1e-12)
    for j in JOINTS.values():  # each joint is a segment on its parent in the body's tree
        assert BODY_PARENT[j.child] == j.parent


def test_a_pose_answers_the_joints_whose_two_segments_it_covers() -> None:
    legs = {"Pelvis", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "RightUpperLeg", "RightLowerLeg", "RightFoot"}
    assert answered_joints(legs) == ["LeftHip", "RightHip", "LeftKnee", "RightKnee", "LeftAnkle", "RightAnkle"]
    assert answered_joints(set(BODY_SEGMENTS)) == list(JOINTS)
    assert answered_joints({"Pelvis", "LeftLowerLeg"}) == []  # the thigh between them is not answered


def test_the_angle_difference_wraps_at_a_half_turn() -> None:
    got = angle_difference_deg(np.array([179.0, 10.0, -170.0]), np.array([-179.0, 12.0, 175.0]))
    np.testing.assert_allclose(got, [-2.0, -2.0, 15.0])
