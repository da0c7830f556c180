"""Pose figures over several simulated sessions per clip, and their intervals over clips."""

from __future__ import annotations

import numpy as np
import pytest

from training.pose.evaluate import (
    METRICS,
    ClipResult,
    clip_intervals,
    draws_mean,
    joint_flexion_metrics,
    per_joint_mean,
    summarise,
)


def _result(path: str, activity: str, frames: int, angle: float, segment: float) -> ClipResult:
    metrics = dict.fromkeys(METRICS, 1.0) | {"angle_all_deg": angle, "jpe_cm": 2.0 * angle, "trans_5s_cm": np.nan}
    joints = {"LeftKnee_flexion": angle / 2.0}
    return ClipResult(path, activity, "cmu_07", frames, metrics, {"Head": segment}, {"Head": segment / 2.0}, joints)


def test_draws_mean_averages_each_clip_and_equals_the_pooled_summary() -> None:
    first = [_result("a", "walk", 100, 10.0, 4.0), _result("b", "run", 300, 20.0, 8.0)]
    second = [_result("a", "walk", 100, 12.0, 6.0), _result("b", "run", 300, 16.0, 8.0)]
    mean = draws_mean([first, second])
    assert [r.metrics["angle_all_deg"] for r in mean] == [11.0, 18.0]
    assert mean[0].per_segment_deg == {"Head": 5.0} and mean[0].per_segment_constant_deg == {"Head": 2.5}
    assert mean[0].per_joint_deg == {"LeftKnee_flexion": 5.5}
    assert np.isnan(mean[0].metrics["trans_5s_cm"])  # a figure no draw has stays absent, not zero
    pooled = summarise(first + second)["overall"]["all"]["angle_all_deg"]
    assert summarise(mean)["overall"]["all"]["angle_all_deg"] == pytest.approx(pooled)
    assert draws_mean([first]) is first
    with pytest.raises(ValueError, match="same clips"):
        draws_mean([first, second[::-1]])


def test_clip_intervals_hold_the_mean_and_widen_with_the_spread_between_clips() -> None:
    tight = [_result(f"w{i}", "walk", 100, 10.0 + 0.1 * (i % 3), 1.0) for i in range(12)]
    loose = [_result(f"r{i}", "run", 100, 10.0 + 5.0 * (i % 3), 1.0) for i in range(12)]
    intervals = clip_intervals(tight + loose)
    assert set(intervals) == {"all", "walk", "run"}
    for name, rs in (("walk", tight), ("run", loose), ("all", tight + loose)):
        low, high = intervals[name]
        assert low <= summarise(rs)["overall"]["all"]["angle_all_deg"] <= high
    assert intervals["run"][1] - intervals["run"][0] > 10 * (intervals["walk"][1] - intervals["walk"][0])
    assert clip_intervals(tight + loose) == intervals  # seeded: the same interval on every run
    one = clip_intervals([_result("x", "walk", 100, 7.0, 1.0)])
    assert one["walk"] == (7.0, 7.0)


def test_per_joint_errors_are_frame_weighted_per_motion_type_and_over_all_clips() -> None:
    results = [
        _result("a", "walk", 100, 10.0, 1.0),
        _result("b", "walk", 300, 2.0, 1.0),
        _result("c", "run", 100, 8.0, 1.0),
    ]
    means = per_joint_mean(results)
    assert list(means) == ["all", "run", "walk"]
    assert means["walk"]["LeftKnee_flexion"] == pytest.approx((5.0 * 100 + 1.0 * 300) / 400)
    assert means["run"]["LeftKnee_flexion"] == pytest.approx(4.0)
    assert means["all"]["LeftKnee_flexion"] == pytest.approx((500 + 300 + 400) / 500)


def test_the_gait_joints_flexion_errors_are_named_per_motion_type_and_overall() -> None:
    per_joint = {
        "all": {"LeftKnee_flexion": 5.0, "LeftKnee_abduction": 1.0, "LeftShoulder_flexion": 9.0},
        "walk": {"LeftKnee_flexion": 4.0},
    }
    assert joint_flexion_metrics(per_joint) == {"test_LeftKnee_flexion_deg": 5.0, "test_walk_LeftKnee_flexion_deg": 4.0}
