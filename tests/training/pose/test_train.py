"""How the pose training draws its sequences."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from training.pose.train import clip_weights


def _clip(source: str, activity: str, frames: int) -> SimpleNamespace:
    return SimpleNamespace(source=source, activity=activity, motion=SimpleNamespace(n_frames=frames))


def test_clips_are_drawn_by_frames_with_capped_activities_and_an_optional_bandai_share() -> None:
    clips = [
        _clip("bandai_namco_2", "wave", 90_000),
        _clip("bandai_namco_2", "walk", 9_000),
        _clip("cmu_li2018", "walk", 1_000),
        _clip("cmu_iclone", "dance", 2_000),
    ]
    w = clip_weights(clips, cap_frames=30_000)
    # the waves count 30,000 of their 90,000 frames (the cap); the walks (10,000) and the dance by their frames
    np.testing.assert_allclose(w, np.array([30_000, 9_000, 1_000, 2_000]) / 42_000)
    shared = clip_weights(clips, cap_frames=30_000, bandai_share=0.5)
    assert np.isclose(shared[:2].sum(), 0.5) and np.isclose(shared[2:].sum(), 0.5)
    np.testing.assert_allclose(shared[:2] / shared[:2].sum(), w[:2] / w[:2].sum())  # within a side, as before
    assert np.isclose(clip_weights(clips[2:], cap_frames=30_000, bandai_share=0.5).sum(), 1.0)  # one side only
