"""The body's translation (``service.core.translation``): a walker whose feet stand still moves as it walks, a throw
follows gravity, the answer turns with the world, a block answers as its pieces do, and on a real CMU walk the
rule on the true pose follows the pelvis. Service code only (the service-only install runs these)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, clip_body, feet_of, read_body_motion, resample_motion
from service.core.translation import Feet, RootTracker
from service.core.units import GRAVITY_MPS2

RATE = 60.0
ANKLES = (BODY_SEGMENTS.index("LeftFoot"), BODY_SEGMENTS.index("RightFoot"))
BALLS = (BODY_SEGMENTS.index("LeftToe"), BODY_SEGMENTS.index("RightToe"))
FEET = Feet(ANKLES, BALLS, 0.08)
PELVIS_HEIGHT_M = 0.9


def _walker(seconds: float, speed: float, heading_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions relative to the pelvis ``(T, 21, 3)`` of a walker at ``speed`` along its heading, and its
    pelvis in the world: each foot stands flat on the floor for 0.5 s, then swings forward at twice the speed in
    an arc 10 cm high, the feet in turn (the other joints stay at the pelvis)."""
    t = np.arange(int(seconds * RATE)) / RATE
    pelvis = np.column_stack([speed * t, np.zeros_like(t), np.full_like(t, PELVIS_HEIGHT_M)])
    joints = np.zeros((len(t), len(BODY_SEGMENTS), 3))
    for side, y in ((0, 0.1), (1, -0.1)):
        phase = (t + 0.5 * side) % 1.0  # stance in [0, 0.5), swing in [0.5, 1)
        start = t - phase  # when this stance began
        swing = np.clip((phase - 0.5) / 0.5, 0.0, 1.0)
        x = speed * (start + 0.25) + swing * speed  # under the pelvis mid-stance; a stride per second
        ball = np.column_stack([x, np.full_like(t, y), 0.1 * np.sin(np.pi * swing)])
        joints[:, BALLS[side]] = ball - pelvis
        joints[:, ANKLES[side]] = ball + np.array([-0.15, 0.0, 0.08]) - pelvis
    turn = Rotation.from_euler("z", heading_deg, degrees=True).as_matrix()
    return joints @ turn.T, pelvis @ turn.T


def test_a_walker_whose_standing_foot_holds_still_moves_as_it_walks() -> None:
    joints, pelvis = _walker(4.0, 1.2)
    root, carried = RootTracker(FEET, RATE).advance(joints, np.zeros((len(joints), 3)))
    np.testing.assert_allclose(root[:, 2], PELVIS_HEIGHT_M, atol=1e-9)  # the floor at the first frame's feet
    np.testing.assert_allclose(root[:, :2] - root[0, :2], pelvis[:, :2] - pelvis[0, :2], atol=0.03)
    assert (carried >= 0).all()


def test_in_flight_the_pelvis_keeps_its_speed_and_falls() -> None:
    joints, pelvis = _walker(2.0, 1.5)
    acc = np.zeros((len(joints), 3))
    acc[-12:, 2] = -GRAVITY_MPS2  # the last 0.2 s in free fall: the pelvis sensor reads no specific force
    tracker = RootTracker(FEET, RATE)
    root, carried = tracker.advance(joints, acc)
    assert (carried[-12:] == -1).all() and (carried[:-12] >= 0).all()
    s = np.arange(1, 13) / RATE
    np.testing.assert_allclose(root[-12:, 2], PELVIS_HEIGHT_M - 0.5 * GRAVITY_MPS2 * s**2, atol=1e-6)
    np.testing.assert_allclose(np.diff(root[-13:, 0]) * RATE, 1.5, atol=0.05)


def test_the_translation_turns_with_the_world() -> None:
    joints, _ = _walker(3.0, 1.0)
    turned, _ = _walker(3.0, 1.0, heading_deg=40.0)
    acc = np.random.default_rng(1).normal(scale=4.0, size=(len(joints), 3))  # flight now and then
    Rz = Rotation.from_euler("z", 40.0, degrees=True).as_matrix()
    root, carried = RootTracker(FEET, RATE).advance(joints, acc)
    root_turned, carried_turned = RootTracker(FEET, RATE).advance(turned, acc @ Rz.T)
    np.testing.assert_allclose(root_turned, root @ Rz.T, atol=1e-9)
    # the same foot (its heel and ball stand alike on this walker's flat feet: either may be the one chosen)
    np.testing.assert_array_equal(carried_turned // 2, carried // 2)
    assert (carried == -1).any()


def test_a_block_answers_as_its_pieces_do() -> None:
    rng = np.random.default_rng(3)
    joints = rng.normal(scale=0.3, size=(300, len(BODY_SEGMENTS), 3))
    acc = rng.normal(scale=6.0, size=(300, 3))  # free fall now and then
    whole, carried = RootTracker(FEET, RATE).advance(joints, acc)
    tracker, pieces = RootTracker(FEET, RATE), []
    for start in range(0, 300, 7):
        pieces.append(tracker.advance(joints[start : start + 7], acc[start : start + 7]))
    np.testing.assert_array_equal(whole, np.concatenate([p for p, _ in pieces]))
    np.testing.assert_array_equal(carried, np.concatenate([c for _, c in pieces]))
    assert (carried == -1).any() and (carried >= 0).any()


@pytest.mark.needs_data
def test_on_a_real_walk_the_rule_on_the_true_pose_follows_the_pelvis(data_dir: Path) -> None:
    """CMU 07_01 on the canonical body at 60 Hz, its pelvis's true free acceleration (second difference of its path):
    the pelvis displacement over every 1 s window is within 15 % of the distance walked in it."""
    motion = resample_motion(read_body_motion(data_dir / "mocap/cmu_iclone/07_01.bvh", source="cmu_iclone"), RATE)
    truth = motion.origin_m[:, 0]
    acc = np.gradient(np.gradient(truth, axis=0), axis=0) * RATE**2
    body = clip_body(motion)
    root, _ = RootTracker(feet_of(body), RATE).advance(body.forward(motion.R_world_segment), acc)
    n = int(RATE)
    error = np.linalg.norm((root[n:] - root[:-n]) - (truth[n:] - truth[:-n]), axis=-1).mean()
    walked = np.linalg.norm(truth[n:] - truth[:-n], axis=-1).mean()
    print(f"07_01: {error * 100:.1f} cm per 1 s window, walked {walked * 100:.1f} cm")
    assert walked > 0.8 and error < 0.15 * walked


def test_bodies_moved_together_move_as_each_alone() -> None:
    """A live batch: bodies of different sizes, some with no frame in a call, two whose first frames come late
    (one of them before another body in the list), one moved with a learned velocity beside two without."""
    from service.core.translation import advance_bodies

    rng = np.random.default_rng(5)
    feet = [Feet(ANKLES, BALLS, h) for h in (0.06, 0.08, 0.1)]
    blocks = [
        [
            (
                rng.normal(scale=0.3, size=(n, len(BODY_SEGMENTS), 3)),
                rng.normal(scale=6.0, size=(n, 3)),
                rng.normal(scale=1.5, size=(n, 3)) if learned else None,
            )
            for n in counts
        ]
        for counts, learned in (((5, 0, 3), False), ((0, 4, 1), True), ((0, 6, 2), False))
    ]
    together = [RootTracker(f, RATE, learned_share=0.25) for f in feet]
    alone = [RootTracker(f, RATE, learned_share=0.25) for f in feet]
    for call in range(3):
        moved = advance_bodies(together, *([b[call][part] for b in blocks] for part in range(3)))
        for k in range(3):
            expected = alone[k].advance(*blocks[k][call])
            np.testing.assert_array_equal(moved[k][0], expected[0])
            np.testing.assert_array_equal(moved[k][1], expected[1])
            assert moved[k][0].shape == (len(blocks[k][call][0]), 3)


def test_a_learned_velocity_moves_the_body_along_the_floor_by_its_share() -> None:
    """With a learned velocity: alone (share 1) the pelvis moves by it whatever the feet do, at share 0 as the
    feet say; the height is the feet's either way; in flight the learned velocity carries it along the floor."""
    joints, pelvis = _walker(3.0, 1.2)
    acc = np.zeros((len(joints), 3))
    learned = np.tile([0.5, -0.2, 0.3], (len(joints), 1))  # not what the feet say, and a vertical part
    alone, _ = RootTracker(FEET, RATE, learned_share=1.0).advance(joints, acc, learned)
    np.testing.assert_allclose(np.diff(alone[:, :2], axis=0) * RATE, learned[1:, :2], atol=1e-9)
    np.testing.assert_allclose(alone[:, 2], PELVIS_HEIGHT_M, atol=1e-9)  # the feet keep it on the floor
    feet_only, _ = RootTracker(FEET, RATE, learned_share=0.0).advance(joints, acc, learned)
    np.testing.assert_allclose(feet_only[:, :2] - feet_only[0, :2], pelvis[:, :2] - pelvis[0, :2], atol=0.03)
    half, _ = RootTracker(FEET, RATE, learned_share=0.5).advance(joints, acc, learned)
    np.testing.assert_allclose(half[:, :2], 0.5 * (alone[:, :2] + feet_only[:, :2]), atol=1e-9)
    acc[-12:, 2] = -GRAVITY_MPS2  # flight: the learned velocity along the floor, gravity on the height
    flying, carried = RootTracker(FEET, RATE, learned_share=0.0).advance(joints, acc, learned)
    assert (carried[-12:] == -1).all()
    np.testing.assert_allclose(np.diff(flying[-12:, :2], axis=0) * RATE, learned[-11:, :2], atol=1e-9)
    assert np.all(np.diff(flying[-12:, 2]) < 0)


def test_a_block_with_a_learned_velocity_answers_as_its_pieces_do() -> None:
    rng = np.random.default_rng(4)
    joints = rng.normal(scale=0.3, size=(200, len(BODY_SEGMENTS), 3))
    acc = rng.normal(scale=6.0, size=(200, 3))
    learned = rng.normal(size=(200, 3))
    whole, carried = RootTracker(FEET, RATE, learned_share=0.25).advance(joints, acc, learned)
    tracker, pieces = RootTracker(FEET, RATE, learned_share=0.25), []
    for start in range(0, 200, 9):
        s = slice(start, start + 9)
        pieces.append(tracker.advance(joints[s], acc[s], learned[s]))
    np.testing.assert_array_equal(whole, np.concatenate([p for p, _ in pieces]))
    np.testing.assert_array_equal(carried, np.concatenate([c for _, c in pieces]))
