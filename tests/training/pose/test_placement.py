"""Zheng et al. 2021 §6's sensor placement on measurements whose dependence is known by construction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, BodyMotion
from service.core.calibration import pose_features
from training.pose.data import MotionClip
from training.pose.placement import (
    CANDIDATES,
    ROOT,
    greedy_placement,
    measurement_groups,
    measurements,
    mic_matrix,
    mrmr_gain,
    phi,
    relevance,
    sample_frames,
)


def test_mic_is_high_for_a_function_low_for_independent_noise_and_symmetric() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=3000)
    columns = np.c_[x, x**2, np.sin(2 * x) + 0.05 * rng.normal(size=3000), rng.normal(size=3000)]
    mic = mic_matrix(columns)
    np.testing.assert_allclose(mic, mic.T)
    np.testing.assert_allclose(np.diag(mic), 1.0, atol=1e-6)  # a column against itself: log2 a of log2 a bits
    assert mic[0, 1] > 0.8 and mic[0, 2] > 0.5  # a parabola; a noisy sine, not monotonic
    assert mic[0, 3] < 0.05 and mic[1, 3] < 0.05 and mic[2, 3] < 0.05  # independent


def test_too_few_samples_for_a_grid_are_refused() -> None:
    with pytest.raises(ValueError, match="no grid of 2 × 2 cells"):
        mic_matrix(np.zeros((5, 2)))


def test_the_greedy_starts_at_the_pelvis_and_skips_a_copy_of_a_chosen_position() -> None:
    """Positions: pelvis, A, a copy of A, B, C. A tells the most about the others; its copy then adds only
    redundancy, so B comes next although it is less relevant to the rest than the copy is."""
    positions = (ROOT, "A", "A copy", "B", "C")
    rele = np.array(
        [
            [1.0, 0.2, 0.2, 0.1, 0.1],
            [0.2, 1.0, 0.95, 0.3, 0.3],
            [0.2, 0.95, 1.0, 0.3, 0.3],
            [0.1, 0.3, 0.3, 1.0, 0.1],
            [0.1, 0.3, 0.3, 0.1, 1.0],
        ]
    )
    placement = greedy_placement(rele, positions, 3)
    assert placement.order == [ROOT, "A", "B"]
    assert placement.gain[0] is None
    # eq. 19 for the copy after A: relevance to B and C (0.3) minus redundancy with pelvis and A (0.575)
    np.testing.assert_allclose(mrmr_gain(rele, [0, 1], 2), 0.3 - (0.2 + 0.95) / 2)
    # eq. 18 for {pelvis, A}: T over the 2 × 3 pairs with the rest, R over the distinct pair
    np.testing.assert_allclose(phi(rele, [0, 1]), (0.2 + 0.1 + 0.1 + 0.95 + 0.3 + 0.3) / 6 - 0.2)


def _clip(frames: int = 400, phase: float = 0.0) -> MotionClip:
    """Every segment turns about its own x with a swing of its own phase; the pelvis drifts forward."""
    t = np.arange(frames) / 60.0
    S = len(BODY_SEGMENTS)
    angles = 30.0 * np.sin(2 * np.pi * 1.1 * t[:, None] + np.arange(S)[None, :] + phase)
    R = Rotation.from_euler("x", angles.reshape(-1, 1), degrees=True).as_matrix().reshape(frames, S, 3, 3)
    mid = np.zeros((frames, S, 3))
    mid[..., 0] = 1.2 * t[:, None] + 0.05 * np.sin(2 * np.pi * 2.2 * t[:, None] + np.arange(S)[None, :])
    return MotionClip("synthetic", "test", "", "walk", BodyMotion(R, mid.copy(), mid, 60.0), "synthetic")


def test_measurements_are_what_the_pose_model_reads_at_each_position() -> None:
    clip = _clip()
    m = measurements(clip)
    groups = measurement_groups(CANDIDATES)
    assert m.shape == (400, 6 + 12 * (len(CANDIDATES) - 1)) and groups[-1].stop == m.shape[1]
    assert "LeftToe" not in CANDIDATES and CANDIDATES[0] == ROOT
    # the layout of service.core.calibration.pose_features for these positions, with the midpoints' acceleration
    six = (ROOT, "Head", "LeftForeArm")
    index = [BODY_SEGMENTS.index(p) for p in six]
    from training.pose.simulate import acceleration

    expected = pose_features(
        clip.motion.R_world_segment[:, index], acceleration(clip.motion.midpoint_m[:, index], 60.0)
    )
    np.testing.assert_allclose(measurements(clip, six), expected)
    with pytest.raises(ValueError, match="first position must be Pelvis"):
        measurements(clip, ("Head", ROOT))


def test_frames_are_drawn_with_the_given_share_of_bandai_namco() -> None:
    bandai = MotionClip("b", "bandai_namco_1", "", "walk", _clip(300).motion, "b")
    cmu = MotionClip("c", "cmu_iclone", "cmu_01", "walk", _clip(100, phase=0.5).motion, "c")
    x = sample_frames([bandai, cmu], 200, 0.25, np.random.default_rng(0))
    assert x.shape == (200, 6 + 12 * (len(CANDIDATES) - 1))
    rows_of = {name: {r.tobytes() for r in measurements(c)} for name, c in (("b", bandai), ("c", cmu))}
    from_bandai = sum(r.tobytes() in rows_of["b"] for r in x)
    assert from_bandai == 50  # a quarter, although Bandai-Namco holds three quarters of the frames


def test_relevance_is_highest_for_a_position_with_itself_on_a_clip() -> None:
    x = measurements(_clip(3000))
    rele = relevance(mic_matrix(x), measurement_groups(CANDIDATES))
    assert rele.shape == (len(CANDIDATES), len(CANDIDATES))
    np.testing.assert_allclose(rele, rele.T, atol=1e-12)
    off = rele[~np.eye(len(rele), dtype=bool)].reshape(len(rele), -1)
    assert np.all(np.diag(rele) > off.max(axis=1))
