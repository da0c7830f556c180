"""How flex clips are cut for Chen et al. 2024 §3.3's protocol: the last share of a training clip held back."""

from __future__ import annotations

import numpy as np

from training.flex.data import FlexClip, tail_split, window_set


def _clip(frames: int, window: int) -> FlexClip:
    t = window - 1 + frames
    angles = np.arange(t * 2 * 3, dtype=np.float32).reshape(t, 2, 3)
    bend = np.abs(np.sin(np.arange(t * 2, dtype=np.float32).reshape(t, 2) / 7.0)) * 90.0
    return FlexClip("mocap/x.bvh.gz", "cmu_iclone", "cmu_08", "walk", angles, bend, window - 1)


def test_the_tail_is_the_clips_last_frames_with_the_motion_before_them_as_its_calibration_window() -> None:
    window = 100
    c = _clip(400, window)
    head, tail = tail_split(c, 0.1, window)
    assert (head.frames, tail.frames) == (360, 40) and tail.path == "mocap/x.bvh.gz#tail"
    # no scored frame is in both; the tail's windows see exactly what the whole clip's last 40 windows see
    np.testing.assert_array_equal(tail.angles[tail.pad :], c.angles[-40:])
    np.testing.assert_array_equal(tail.bend, c.bend[-40 - window + 1 :])
    np.testing.assert_array_equal(head.angles, c.angles[: len(c.angles) - 40])
    whole, cut = window_set([c], 1, 0, window), window_set([tail], 1, 0, window)
    assert len(cut.ends) == 40 and len(window_set([head], 1, 0, window).ends) == 360
    _, y_whole = whole.batch(np.zeros(40, int), whole.ends[-40:], 1)
    _, y_tail = cut.batch(np.zeros(40, int), cut.ends, 1)
    np.testing.assert_array_equal(y_tail, y_whole)


def test_a_clip_too_short_for_a_tail_frame_keeps_all_its_frames() -> None:
    c = _clip(4, 100)
    head, tail = tail_split(c, 0.1, 100)
    assert tail is None and head is c
