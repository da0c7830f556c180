"""How pose clips are cut for Zheng et al. 2021 §7's protocol: the last share of a training clip held back."""

from __future__ import annotations

import numpy as np

from service.core.body import BodyMotion
from training.pose.data import MotionClip, tail_split


def _clip(frames: int) -> MotionClip:
    R = np.broadcast_to(np.eye(3), (frames, 23, 3, 3)).copy()
    pos = np.arange(frames * 23 * 3, dtype=np.float64).reshape(frames, 23, 3)
    return MotionClip("07_01.bvh", "cmu_iclone", "cmu_07", "walk", BodyMotion(R, pos, pos + 1, 60.0), "abc123")


def test_the_tail_is_the_clips_last_frames_and_the_head_the_rest() -> None:
    c = _clip(1200)
    head, tail = tail_split(c, 0.1, 120)
    assert (head.motion.n_frames, tail.motion.n_frames) == (1080, 120)
    np.testing.assert_array_equal(np.concatenate([head.motion.origin_m, tail.motion.origin_m]), c.motion.origin_m)
    # a clip of its own: its own path and digest (which seed its evaluation session), the same person and activity
    assert (tail.path, tail.digest) == ("07_01.bvh#tail", "abc123-tail")
    assert (tail.subject, tail.activity, head.path, head.digest) == ("cmu_07", "walk", "07_01.bvh", "abc123")


def test_a_clip_too_short_for_a_tail_of_the_least_length_stays_whole() -> None:
    c = _clip(1000)
    head, tail = tail_split(c, 0.1, 120)
    assert tail is None and head is c
