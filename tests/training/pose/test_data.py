"""The seen-people protocol of Zheng et al. 2021 §7 and Chen et al. 2024 §3.3: training clips held back."""

from __future__ import annotations

import hashlib

import numpy as np

from service.core.body import BodyMotion
from training.pose.data import MotionClip, seen_split


def _clip(i: int, activity: str) -> MotionClip:
    R = np.broadcast_to(np.eye(3), (10, 23, 3, 3)).copy()
    pos = np.zeros((10, 23, 3))
    digest = hashlib.sha256(str(i).encode()).hexdigest()[:20]
    return MotionClip(f"{i}.bvh", "bandai_namco_1", "", activity, BodyMotion(R, pos, pos, 60.0), digest)


def test_about_the_share_of_every_activitys_takes_is_held_back_the_same_way_every_time() -> None:
    clips = [_clip(i, a) for i in range(2000) for a in ("walk", "run")]
    train, seen = seen_split(clips, 0.1)
    assert len(train) + len(seen) == len(clips) and not {c.path for c in train} & {c.path for c in seen}
    for activity in ("walk", "run"):
        share = sum(c.activity == activity for c in seen) / 2000
        assert 0.08 < share < 0.12
    again_train, again_seen = seen_split(list(reversed(clips)), 0.1)
    assert {c.path for c in again_seen} == {c.path for c in seen}  # by digest, not by order
    assert seen_split(clips, 0.0) == (clips, [])
