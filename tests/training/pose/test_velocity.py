"""The learned pelvis velocity's frames and look-ahead (``training.pose.velocity``): the target is the pelvis
velocity in the pelvis frame, the service turns it back into the world, and the training targets are shifted as
the network answers (frame t − L at output t)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, BodyMotion
from service.inference.velocity import world_velocity
from training.pose.data import MotionClip
from training.pose.simulate import Session
from training.pose.velocity import _batch, pelvis_velocity

RATE = 60.0


def _turning_walker(frames: int = 120) -> BodyMotion:
    """A pelvis moving at (1.0, 0.5, 0) m/s in the world while it turns about the vertical at 1 rad/s."""
    t = np.arange(frames) / RATE
    R = Rotation.from_rotvec(np.outer(t, [0.0, 0.0, 1.0])).as_matrix()
    S = len(BODY_SEGMENTS)
    R_all = np.repeat(R[:, None], S, axis=1)
    origin = np.zeros((frames, S, 3))
    origin[:, 0] = np.outer(t, [1.0, 0.5, 0.0])
    return BodyMotion(R_all, origin, origin.copy(), RATE)


def test_the_target_is_the_pelvis_velocity_in_the_pelvis_frame_and_the_service_turns_it_back() -> None:
    motion = _turning_walker()
    v = pelvis_velocity(motion)
    R = motion.R_world_segment[:, 0]
    np.testing.assert_allclose(world_velocity(R, v.astype(np.float64)), np.tile([1.0, 0.5, 0.0], (120, 1)), atol=1e-5)
    # in the pelvis frame the same velocity turns the other way as the pelvis turns
    np.testing.assert_allclose(v[60], R[60].T @ [1.0, 0.5, 0.0], atol=1e-5)
    assert np.linalg.norm(v[0] - v[60]) > 0.5


def test_the_training_targets_are_shifted_by_the_look_ahead() -> None:
    motion = _turning_walker()
    clip = MotionClip("walker.bvh", "test", "test_01", "walk", motion, "0" * 40)
    session = Session(
        np.zeros((120, 66), np.float32), np.zeros((120, 15, 3, 3), np.float32), np.zeros((120, 6, 3, 3)), 0.0
    )
    L = 5
    x, v, R, mask = _batch([clip], [session], L)
    truth = pelvis_velocity(motion)
    assert x.shape == (1, 120, 66) and v.shape == (1, 120, 3) and R.shape == (1, 120, 3, 3)
    np.testing.assert_allclose(v[0, L:].numpy(), truth[:-L])  # output t answers frame t - L
    np.testing.assert_allclose(R[0, L:].numpy(), motion.R_world_segment[:-L, 0], atol=1e-6)
    assert mask[0, :L].sum() == 0 and mask[0, L:].min() == 1
