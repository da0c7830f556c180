"""The joint-angle convention, the bend a strip feels, the functional knee hinge, and the per-stream window."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS
from service.core.flex import (
    FLEX_JOINTS,
    FlexWindow,
    ReadoutCheck,
    bend_angles_deg,
    block_windows,
    fit_hinge,
    hinge_angle_deg,
)
from service.core.joint_angles import joint_angles_deg

JOINTS = list(FLEX_JOINTS)


def _pose(**turns: tuple[str, float]) -> np.ndarray:
    """One frame, every segment in neutral stance, except ``segment=(axis, degrees)`` turned about its parent's
    axis (world frame = segment frames in neutral stance); children follow their parents."""
    R = np.tile(np.eye(3), (1, len(BODY_SEGMENTS), 1, 1))
    from service.core.body import BODY_PARENT

    for k, seg in enumerate(BODY_SEGMENTS):
        parent = BODY_PARENT[seg]
        base = R[0, BODY_SEGMENTS.index(parent)] if parent else np.eye(3)
        local = np.eye(3)
        if seg in turns:
            axis, deg = turns[seg]
            local = Rotation.from_euler(axis, deg, degrees=True).as_matrix()
        R[0, k] = base @ local
    return R


def _angle(R: np.ndarray, joint: str, component: int) -> float:
    return float(joint_angles_deg(R, [joint])[0, 0, component])


def test_neutral_stance_is_zero_everywhere() -> None:
    np.testing.assert_allclose(joint_angles_deg(_pose(), JOINTS), 0.0, atol=1e-9)
    np.testing.assert_allclose(bend_angles_deg(_pose(), JOINTS), 0.0, atol=1e-6)


@pytest.mark.parametrize(
    "segment, axis, degrees, joint",
    [
        ("LeftLowerLeg", "y", 40.0, "LeftKnee"),  # the shank turns back: its z towards the thigh's +x
        ("RightLowerLeg", "y", 40.0, "RightKnee"),
        ("LeftUpperLeg", "y", -30.0, "LeftHip"),  # the thigh swings forward
        ("LeftForeArm", "y", -70.0, "LeftElbow"),  # the hand comes forward and up
        ("RightUpperArm", "y", -50.0, "RightShoulder"),  # the arm raised forward
        ("T8", "y", 15.0, "ThoracicSpine"),  # bending forward
    ],
)
def test_flexion_is_positive_as_anatomy_names_it(segment: str, axis: str, degrees: float, joint: str) -> None:
    R = _pose(**{segment: (axis, degrees)})
    assert _angle(R, joint, 0) == pytest.approx(abs(degrees), abs=1e-6)
    assert float(bend_angles_deg(R, [joint])[0, 0]) == pytest.approx(abs(degrees), abs=1e-4)


def test_abduction_is_positive_away_from_the_midline_on_both_sides() -> None:
    # the left thigh's distal end to the left (+y): its z turns towards -y, a positive turn about x
    assert _angle(_pose(LeftUpperLeg=("x", 20.0)), "LeftHip", 1) == pytest.approx(20.0)
    assert _angle(_pose(RightUpperLeg=("x", -20.0)), "RightHip", 1) == pytest.approx(20.0)


def test_internal_rotation_is_positive_on_both_sides() -> None:
    # internal: the thigh's front (x) turns towards the midline: -z for the left leg, +z for the right
    assert _angle(_pose(LeftUpperLeg=("z", -25.0)), "LeftHip", 2) == pytest.approx(25.0)
    assert _angle(_pose(RightUpperLeg=("z", 25.0)), "RightHip", 2) == pytest.approx(25.0)


def test_angles_are_of_the_joint_not_of_the_chain_above_it() -> None:
    R = _pose(LeftUpperLeg=("y", -45.0), LeftLowerLeg=("y", 60.0))
    assert _angle(R, "LeftHip", 0) == pytest.approx(45.0)
    assert _angle(R, "LeftKnee", 0) == pytest.approx(60.0)


def test_a_simulated_knee_is_recovered_by_its_functional_hinge() -> None:
    """A hinge flexing 0-70° about the thigh's y, sensors mounted at random, small out-of-axis wobble, a moving
    thigh: the fitted angle is the flexion to within a degree (its zero is the most extended posture)."""
    rng = np.random.default_rng(0)
    t = np.arange(3000) / 100.0
    flexion = 35.0 - 35.0 * np.cos(2 * np.pi * t / 1.1)
    thigh = Rotation.from_euler(
        "zyx", np.c_[20 * np.sin(0.3 * t), 25 * np.sin(2 * np.pi * t / 1.1), 3 * np.sin(t)], degrees=True
    )
    wobble = Rotation.from_euler("xz", rng.normal(0.0, 0.5, size=(len(t), 2)), degrees=True)
    shank = thigh * Rotation.from_euler("y", flexion[:, None], degrees=True) * wobble
    mount_thigh, mount_shank = Rotation.random(random_state=1), Rotation.random(random_state=2)
    q_thigh = (thigh * mount_thigh).as_quat(scalar_first=True)
    q_shank = (shank * mount_shank).as_quat(scalar_first=True)
    cal = fit_hinge(q_thigh, q_shank, extension_percentile=0.0)
    got = hinge_angle_deg(q_thigh, q_shank, cal)
    assert np.abs(got - flexion).mean() < 1.0
    other = Rotation.random(random_state=3)  # the same hinge in another world frame: the same angles
    again = hinge_angle_deg(
        (other * thigh * mount_thigh).as_quat(scalar_first=True),
        (other * shank * mount_shank).as_quat(scalar_first=True),
        cal,
    )
    np.testing.assert_allclose(again, got, atol=1e-6)


def test_the_stream_window_yields_exactly_the_block_windows() -> None:
    x = np.random.default_rng(0).normal(size=(57, 3)).astype(np.float32)
    live = FlexWindow(20, 3)
    streamed = [w for k in range(0, 57, 6) for w in live.push(x[k : k + 6])]
    np.testing.assert_array_equal(np.stack(streamed), block_windows(x, 20))
    assert len(streamed) == 57 - 20 + 1
    with pytest.raises(ValueError, match="fewer than the window"):
        block_windows(x[:10], 20)


def test_a_read_out_failure_is_the_first_reading_off_its_channel_s_reference_by_more_than_the_limit() -> None:
    rng = np.random.default_rng(0)
    x = 1000.0 + 50.0 * rng.standard_normal((3000, 3))  # within 20 % of the reference: healthy
    x[:, 1] *= 10.0  # channels read on their own scales
    assert ReadoutCheck(100.0, 10.0, 0.5).first_failure(x) is None
    x[2500:, 1] *= 1.6  # 60 % above its first 10 s
    assert ReadoutCheck(100.0, 10.0, 0.5).first_failure(x).row == 2500
    failure = ReadoutCheck(100.0, 10.0, 0.5).first_failure(x)
    assert failure.channel == 1 and failure.value == x[2500, 1] and abs(failure.reference - 10_000) < 100
    x[2200, 2] = np.nan
    assert ReadoutCheck(100.0, 10.0, 0.5).first_failure(x).row == 2200


def test_a_streamed_read_out_is_judged_against_the_same_reference_as_a_block() -> None:
    rng = np.random.default_rng(1)
    x = 500.0 + 20.0 * rng.standard_normal((2500, 2))
    x[1700:, 0] = 5e6
    check = ReadoutCheck(50.0, 10.0, 0.5)
    found = None
    for k in range(0, len(x), 7):
        failure = check.first_failure(x[k : k + 7])
        if failure is not None:
            found = k + failure.row
            break
    assert found == 1700 and check.reference is not None
    np.testing.assert_allclose(check.reference, np.median(x[:500], axis=0))
