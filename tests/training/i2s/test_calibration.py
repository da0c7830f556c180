"""The calibrated confidence of the joint assignment (training/i2s/calibration.py, service/core/assignment.py):
the logistic fit recovers a known model, the calibration error tells calibrated from overconfident, sessions and
the time to answer follow the service's joint answer, and the status commits only with enough evidence."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.assignment import ConfidenceModel, confidence_features, joint_assignment, vote_counts
from service.core.segments import SEGMENTS
from training.i2s.calibration import (
    HOP_S,
    HeldOut,
    SensorPrediction,
    choose_threshold,
    cross_fitted,
    expected_calibration_error,
    fit_logistic,
    nested,
    selective,
    sessions,
    time_to_answer,
)

K = len(SEGMENTS)


def test_the_logistic_fit_recovers_the_model_that_drew_the_labels() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20000, 3))
    coef, intercept = np.array([2.0, -1.0, 0.5]), 0.3
    y = rng.random(len(x)) < 1.0 / (1.0 + np.exp(-(x @ coef + intercept)))
    got, got_intercept = fit_logistic(x, y.astype(float), np.ones(len(x)))
    np.testing.assert_allclose(got, coef, atol=0.1)
    assert got_intercept == pytest.approx(intercept, abs=0.1)


def test_calibration_error_is_small_for_calibrated_and_large_for_overconfident_probabilities() -> None:
    rng = np.random.default_rng(1)
    p = rng.uniform(0.5, 1.0, 50000)
    right = rng.random(len(p)) < p
    assert expected_calibration_error(p, right) < 0.01
    assert expected_calibration_error(np.full(len(p), 0.999), right) > 0.2


def _sensor(segment: int, right: float, n: int, rng: np.random.Generator, still: int = 0) -> SensorPrediction:
    """A sensor whose windows favour its own segment with probability ``right`` (a wrong one otherwise)."""
    logits = rng.normal(0.0, 0.3, size=(n, K))
    favoured = np.where(rng.random(n) < right, segment, (segment + 1 + rng.integers(0, K - 1, n)) % K)
    logits[np.arange(n), favoured] += 2.0
    log_probs = logits - np.log(np.exp(logits).sum(axis=1, keepdims=True))
    moving = np.arange(n) >= still
    return SensorPrediction(segment, log_probs, moving)


def _people(rng: np.random.Generator) -> list[HeldOut]:
    out = []
    for k in range(6):
        quality = 0.9 if k % 2 else 0.35  # half the people easy, half hard
        sensors = [_sensor(seg, quality, 400, rng, still=40) for seg in range(5)]
        out.append(HeldOut(f"person{k}", f"rec{k}", "walk", sensors))
    return out


def test_sessions_score_the_services_joint_answer_and_the_cross_fitted_calibration_is_honest() -> None:
    rng = np.random.default_rng(2)
    people = _people(rng)
    samples = sessions(people)
    assert set(samples.person) == {h.person for h in people}
    assert samples.features.shape[1] == 3 and 0.0 < samples.correct.mean() < 1.0
    # one session checked by hand: the first span of the first person, all sensors
    first = samples.session == 0
    length = int(round(2.0 / HOP_S))
    window = slice(0, length)
    evidence = [s.log_probs[window][s.moving[window]] for s in people[0].sensors]
    sensors = people[0].sensors
    joint = joint_assignment([e if len(e) else s.log_probs[window] for e, s in zip(evidence, sensors, strict=True)])
    truth = np.array([s.segment for s in people[0].sensors])
    np.testing.assert_array_equal(samples.correct[first], joint.segment == truth)
    p = cross_fitted(samples)
    assert expected_calibration_error(p, samples.correct) < 0.08
    figures = selective(samples, np.full(len(p), 0.5), np.full(len(p), 0.995))  # never reaches the threshold
    assert figures["sensor_coverage"] == 0.0 and figures["session_abstain_rate"] == 1.0
    nested_p, models = nested(samples)
    assert set(models) == {h.person for h in people}
    for person, model in models.items():  # each person's threshold is the others' choice, applied to them
        own = samples.person == person
        np.testing.assert_allclose(nested_p[own], model.p_correct(samples.features[own]))
    thresholds = np.array([models[person].threshold for person in samples.person])
    figures = selective(samples, nested_p, thresholds)
    assert figures["sensor_coverage"] > 0.2 and figures["sensor_selective_accuracy"] > samples.correct.mean()


def test_the_threshold_is_the_lowest_probability_whose_answers_reach_the_target() -> None:
    rng = np.random.default_rng(3)
    p = rng.uniform(0.5, 1.0, 20000)
    correct = p >= 0.9  # everything above 0.9 right, everything below wrong
    moving = np.full(len(p), 20)
    threshold = choose_threshold(p, correct, moving)
    assert 0.89 <= threshold <= 0.9
    assert correct[p >= threshold].mean() >= 0.995 and correct[p >= threshold - 0.01].mean() < 0.995
    assert choose_threshold(p, np.zeros(len(p), bool), moving) == 0.999  # never reached
    assert choose_threshold(p, correct, np.full(len(p), 2)) == 0.999  # too few moving windows to count


def test_status_commits_only_on_enough_moving_windows_and_probability() -> None:
    model = ConfidenceModel((10.0, 0.0, 0.0), -5.0, 0.99, 8)  # p from the vote share alone
    segment, margin = np.array([0, 1]), np.array([20.0, 15.0])
    votes = np.zeros((2, K), int)
    votes[0, 0], votes[1, 1] = 10, 10
    features = confidence_features(segment, margin, votes, np.array([10, 10]))
    np.testing.assert_allclose(features[:, 0], [1.0, 1.0])
    np.testing.assert_allclose(features[:, 1], [2.0, 1.5])
    p = model.p_correct(features)
    assert model.status(p, np.array([10, 10]), segment >= 0) == "assigned"
    assert model.status(p, np.array([10, 7]), segment >= 0) == "not_enough_walking"
    votes[1] = 0
    votes[1, 2] = 10  # the second sensor's windows favour another segment than the one it got
    p = model.p_correct(confidence_features(segment, margin, votes, np.array([10, 10])))
    assert p[1] < 0.01 and model.status(p, np.array([10, 10]), segment >= 0) == "not_enough_walking"
    assert vote_counts(np.log(np.eye(K)[[3, 3, 1]] + 1e-9), K).tolist() == [0, 1, 0, 2, 0, 0, 0]


def test_time_to_answer_is_counted_from_the_first_moving_window() -> None:
    """Two sensors whose windows are wrong for the first 20 moving windows and right after: the answer settles
    once the right windows outweigh the wrong ones (14 × log(0.8 / 0.01) > 20 × log(0.9 / 0.05)), and a
    calibration that commits at once commits wrongly."""
    n, still = 200, 10
    sensors = []
    for seg, other in ((0, 1), (1, 0)):
        log_probs = np.full((n, K), np.log(0.01))
        log_probs[: still + 20, other] = np.log(0.9)
        log_probs[: still + 20, seg] = np.log(0.05)
        log_probs[still + 20 :, seg] = np.log(0.8)
        sensors.append(SensorPrediction(seg, log_probs, np.arange(n) >= still))
    held = [HeldOut("p", "rec", "walk", sensors)]
    eager = ConfidenceModel((0.0, 0.0, 0.0), 10.0, 0.99, 1)
    timing = time_to_answer(held, {"p": eager})["rec"]
    assert timing["right_s"] == pytest.approx(33 * HOP_S)  # moving windows 0-19 wrong, then 14 right ones
    assert timing["committed_s"] == 0.0 and timing["committed_right"] == 0.0
    never = ConfidenceModel((0.0, 0.0, 0.0), -10.0, 0.99, 1)
    assert np.isnan(time_to_answer(held, {"p": never})["rec"]["committed_s"])
