"""Zheng et al. 2021 §5's training-data selection on clips whose similarity is known by construction."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, BodyMotion
from training.pose.data import MotionClip
from training.pose.selection import (
    BINS,
    greedy_deletion,
    pose_features,
    score,
    select,
    selected_clips,
    similar_runs,
)

S = len(BODY_SEGMENTS)


def _clip(angles_deg: np.ndarray, name: str, heading_deg: float = 0.0) -> MotionClip:
    """Every segment but the pelvis turned about x by ``angles_deg`` (T,) relative to a pelvis facing
    ``heading_deg``."""
    T = len(angles_deg)
    pelvis = Rotation.from_euler("z", heading_deg, degrees=True).as_matrix()
    R = np.tile(pelvis, (T, S, 1, 1))
    R[:, 1:] = pelvis @ Rotation.from_euler("x", np.asarray(angles_deg)[:, None], degrees=True).as_matrix()[:, None]
    zeros = np.zeros((T, S, 3))
    return MotionClip(name, "test", "", "walk", BodyMotion(R, zeros, zeros, 60.0), name)


def _swing(frames: int, amplitude: float, period: int = 60, phase: float = 0.0) -> np.ndarray:
    return amplitude * np.sin(2 * np.pi * np.arange(frames) / period + phase)


def test_features_are_pelvis_relative_so_the_heading_does_not_matter() -> None:
    a = _swing(90, 30.0)
    np.testing.assert_allclose(pose_features(_clip(a, "a")), pose_features(_clip(a, "b", heading_deg=70.0)), atol=1e-6)
    assert pose_features(_clip(a, "a")).shape == (90, (S - 1) * 9)


def test_similar_runs_cover_the_units_like_the_reference_and_only_runs_long_enough() -> None:
    reference = [_clip(_swing(600, 20.0), "ref")]
    # 300 frames like the reference, 300 frames 120° away (cos 120° = −0.5: far below η0), 60 like it again
    far = np.full(300, 120.0)
    clip = _clip(np.concatenate([_swing(300, 20.0), far, _swing(60, 20.0)]), "mixed")
    runs = similar_runs([clip], reference, unit_frames=30, eta0=0.8, min_frames=120)
    assert [(r.clip, r.start, r.stop) for r in runs] == [(0, 0, 300)]  # the last 60 frames are too short a run
    # η0 = 0.8 admits poses about 45° apart on every segment and not 60° (the module docstring)
    assert similar_runs([_clip(np.full(120, 40.0), "c")], [_clip(np.zeros(120), "z")], 30, 0.8, 30)
    assert not similar_runs([_clip(np.full(120, 60.0), "c")], [_clip(np.zeros(120), "z")], 30, 0.8, 30)


def test_the_score_is_the_entropy_minus_the_divergence_minus_the_log_size() -> None:
    uniform = np.ones((3, BINS)) * 10.0
    log_q = np.log(np.full((3, BINS), 1.0 / BINS))
    # P = Q uniform: H = log 20, d_KL = 0
    np.testing.assert_allclose(score(uniform, 200.0, log_q, (1, 1, 1)), np.log(BINS) - np.log(200.0))
    peaked = np.zeros((3, BINS))
    peaked[:, 0] = 200.0
    # all mass in one interval: H = 0, d_KL = log 20
    np.testing.assert_allclose(score(peaked, 200.0, log_q, (1, 1, 1)), -np.log(BINS) - np.log(200.0))


def test_the_greedy_deletion_drops_what_the_reference_lacks_and_stops_at_a_local_maximum() -> None:
    reference = [_clip(_swing(1200, 30.0), "ref")]
    like = [_clip(_swing(600, 30.0, phase=p), f"like{p}") for p in (0.3, 1.1, 2.0)]
    # similar to the reference (within η0) but held near its extreme: a distribution the reference lacks
    skewed = [_clip(25.0 + _swing(600, 3.0), "skewed")]
    clips = like + skewed
    sel = select(clips, reference, unit_frames=30, eta0=0.8, min_frames=300)
    assert len(sel.candidates) == 4 and len(sel.trace) >= 2
    kept = {clips[r.clip].path for r in sel.runs}
    assert "skewed" not in kept and kept  # eq. 12 deletes it first; something stays
    out = selected_clips(clips, sel.runs)
    assert all("#" in c.path and c.motion.n_frames == r.frames for c, r in zip(out, sel.runs, strict=True))
    assert sel.frames_by_label()["test/walk"][0] == 2400


def test_the_greedy_deletion_only_deletes_what_raises_the_score_and_ends_at_a_local_maximum() -> None:
    rng = np.random.default_rng(0)
    K, F = 12, 4
    counts = rng.integers(0, 30, size=(K, F, BINS)).astype(np.float64)
    counts[3] = 0.0
    counts[3][:, 0] = 400.0  # one segment with all its frames in one interval: eq. 12's first deletion
    frames = counts[:, 0].sum(axis=1)
    q = rng.integers(1, 30, size=(F, BINS)).astype(np.float64)
    log_q = np.log(q / q.sum(axis=1, keepdims=True))
    alive, trace = greedy_deletion(counts, frames, log_q, (1.0, 1.0, 1.0))
    assert not alive[3] and alive.any()
    assert all(b > a for a, b in zip(trace[1:], trace[2:], strict=False))  # eq. 13 deletes only what raises f
    assert len(trace) == 1 + int((~alive).sum())
    total, n = counts[alive].sum(axis=0), frames[alive].sum()
    np.testing.assert_allclose(score(total, n, log_q, (1, 1, 1)), trace[-1])
    if alive.sum() > 1:  # a local maximum: no single further deletion raises it
        for k in np.flatnonzero(alive):
            assert score(total - counts[k], n - frames[k], log_q, (1, 1, 1)) <= trace[-1] + 1e-12
