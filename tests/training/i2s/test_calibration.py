"""The calibrated confidence of the joint assignment (training/i2s/calibration.py, service/core/assignment.py):
the logistic fit recovers a known model, the calibration error tells calibrated from overconfident, sessions and
the time to answer follow the service's joint answer, and the status commits only with enough evidence."""

from __future__ import annotations

from dataclasses import replace

import mlflow
import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from service.core.assignment import (
    ConfidenceModel,
    SessionConfidence,
    confidence_features,
    joint_assignment,
    session_features,
    vote_counts,
)
from service.core.segments import SEGMENTS
from service.core.windowing import sliding_windows
from training.i2s.calibration import (
    HOP_S,
    HeldOut,
    SensorPrediction,
    _read_predictions,
    _write_predictions,
    calibrated_model,
    choose_threshold,
    cross_fitted,
    expected_calibration_error,
    fit_logistic,
    fold_predictions,
    lower_bound,
    nested,
    nested_sessions,
    selective,
    selective_sessions,
    servable,
    sessions,
    time_to_answer,
)
from training.i2s.ship import confusion_table, held_out_confusions, real_confusion

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
    # per number of sensors worn, the shares of committed sensors add up to the overall one
    sizes = {int(k.split("_")[2]) for k in figures if k.startswith("sensor_coverage_")}
    _, index, counts = np.unique(samples.session, return_inverse=True, return_counts=True)
    weights = {n: float((counts[index] == n).mean()) for n in sizes}
    assert len(sizes) > 1 and sum(weights.values()) == pytest.approx(1.0)
    assert sum(weights[n] * figures[f"sensor_coverage_{n}_sensors"] for n in sizes) == pytest.approx(
        figures["sensor_coverage"]
    )


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


def test_the_threshold_asks_for_the_target_with_confidence_not_just_on_the_fitted_answers() -> None:
    # every answer below 0.9 wrong, one in a hundred wrong between 0.9 and 0.95, none above: from 0.9 up the answers
    # read 99.5 % (what a threshold on the share alone takes), but that share is no 95 % bound on the next ones
    p = np.linspace(0.5, 1.0, 20000, endpoint=False)
    correct = p >= 0.9
    doubtful = np.flatnonzero((p >= 0.9) & (p < 0.95))
    correct[doubtful[::100]] = False
    moving = np.full(len(p), 20)

    def bound_above(t: float) -> float:
        given = p >= t
        return lower_bound(int(correct[given].sum()), int(given.sum()))

    assert correct[p >= 0.9].mean() >= 0.995
    threshold = choose_threshold(p, correct, moving)
    assert 0.9 < threshold < 0.95
    assert bound_above(threshold) >= 0.995 > bound_above(threshold - 0.001)
    # the bound itself: below the share, closing on it as answers grow, 0 without answers
    assert lower_bound(299, 300) < lower_bound(2990, 3000) < 2990 / 3000
    assert lower_bound(0, 0) == 0.0 and 0.99 < lower_bound(1000, 1000) < 1.0


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
    assert timing["sensor_committed_s"] == [0.0, 0.0] and timing["sensor_committed_right"] == [0.0, 0.0]
    never = ConfidenceModel((0.0, 0.0, 0.0), -10.0, 0.99, 1)
    assert np.isnan(time_to_answer(held, {"p": never})["rec"]["committed_s"])
    assert np.isnan(time_to_answer(held, {"p": never})["rec"]["sensor_committed_s"]).all()


def test_the_session_probability_nests_the_product_of_the_sensors_and_decides_the_status() -> None:
    """With coefficients (1, 0) and intercept 0 the probability that every sensor is right is the product of the
    sensors' probabilities; with a session calibration the status follows it, not each sensor's own threshold."""
    p = np.array([0.97, 0.89, 0.99])
    product = SessionConfidence((1.0, 0.0), 0.0, 0.9)
    assert product.p(session_features(p)[None])[0] == pytest.approx(np.prod(p))
    assert session_features(np.ones(3))[0] == 30.0 and session_features(np.zeros(2))[0] == -30.0  # clipped logits
    assert session_features(p)[1] == pytest.approx(np.log(3))
    assigned, moving = np.ones(3, bool), np.full(3, 20)
    per_sensor = ConfidenceModel((0.0, 0.0, 0.0), 0.0, 0.95, 8)
    assert per_sensor.status(p, moving, assigned) == "not_enough_walking"  # 0.89 < 0.95
    assert per_sensor.committed(p, moving, assigned).tolist() == [True, False, True]  # the others commit alone
    assert per_sensor.committed(p, np.array([20, 20, 7]), assigned).tolist() == [True, False, False]
    assert not per_sensor.committed(p, moving, np.zeros(3, bool)).any()
    assert per_sensor.p_all_correct(p, assigned) is None
    lenient = replace(per_sensor, session=SessionConfidence((1.0, 0.0), 3.0, 0.95))  # logit 0.26 + 3 → 0.96
    assert lenient.p_all_correct(p, assigned) == pytest.approx(1 / (1 + np.exp(-(np.log(0.8547 / 0.1453) + 3))), 1e-3)
    assert lenient.status(p, moving, assigned) == "assigned"
    assert lenient.status(p, np.array([20, 20, 7]), assigned) == "not_enough_walking"  # one sensor under 8
    assert replace(lenient, session=product).status(p, moving, assigned) == "not_enough_walking"  # 0.855 < 0.9
    assert lenient.status(p, moving, np.zeros(3, bool)) == "not_enough_walking"  # nothing assigned


def test_the_session_calibration_of_a_person_never_reads_that_persons_sessions() -> None:
    rng = np.random.default_rng(4)
    people = _people(rng)
    samples = sessions(people)
    own = samples.person == "person0"
    model = calibrated_model(samples, ~own)
    flipped = replace(samples, correct=np.where(own, ~samples.correct, samples.correct))
    assert calibrated_model(flipped, ~own) == model  # person0's labels changed, the recipe without them did not
    assert calibrated_model(flipped, np.ones(len(own), bool)) != calibrated_model(samples, np.ones(len(own), bool))
    p, models = nested(samples)
    table, p_all = nested_sessions(samples, p, models)
    assert len(table.correct) == len(np.unique(samples.session)) and 0.0 < table.correct.mean() < 1.0
    for session in table.session[:50]:
        rows = samples.session == session
        k = int(np.flatnonzero(table.session == session)[0])
        assert table.correct[k] == samples.correct[rows].all() and table.moving[k] == samples.moving[rows].min()
        person = table.person[k]
        expected = models[person].p_all_correct(p[rows], np.ones(rows.sum(), bool))
        assert p_all[k] == pytest.approx(expected)
    thresholds = np.array([models[person].session.threshold for person in table.person])
    figures = selective_sessions(samples, table, p_all, thresholds)
    assert figures["all_abstain_rate"] < 1.0
    assert figures["all_selective_accuracy"] > figures["all_sessions_right"]  # committing picks the right ones
    never = selective_sessions(samples, table, p_all, np.full(len(p_all), 2.0))
    assert never["all_abstain_rate"] == 1.0 and np.isnan(never["all_selective_accuracy"])


def test_held_out_predictions_survive_the_round_trip_through_their_artifact(tmp_path) -> None:
    rng = np.random.default_rng(5)
    held = _people(rng)[:2]
    _write_predictions(held, tmp_path / "held_out_predictions")
    back = _read_predictions(tmp_path / "held_out_predictions")
    assert [(h.person, h.recording, h.activity) for h in back] == [(h.person, h.recording, h.activity) for h in held]
    for a, b in zip(held, back, strict=True):
        for sa, sb in zip(a.sensors, b.sensors, strict=True):
            assert sa.segment == sb.segment and (sa.moving == sb.moving).all()
            np.testing.assert_allclose(sa.log_probs, sb.log_probs, atol=1e-6)


def test_held_out_predictions_are_kept_with_the_summary_run_and_found_by_its_original_id(
    mlflow_server: str, tmp_path
) -> None:
    """A snapshot keeps no fold's model file: the calibration reads the held-out predictions stored with the
    summary run, also in a store where that run was restored under a new id; without them it says what to do."""
    client = MlflowClient()
    experiment = mlflow.set_experiment("calibration-test").experiment_id
    fold = client.create_run(experiment, tags={"real_loso_held_out": "person0"}).info.run_id
    original = "0123456789abcdef0123456789abcdef"
    summary = client.create_run(
        experiment, tags={"real_loso": "summary", "fold_run.person0": fold, "restored_from_run_id": original}
    ).info.run_id
    with pytest.raises(ValueError, match="run real-loso again"):
        fold_predictions(original, tmp_path / "no-data")  # found by its original id; its fold has no model
    held = _people(np.random.default_rng(6))[:1]
    _write_predictions(held, tmp_path / "out" / "held_out_predictions")
    client.log_artifacts(summary, str(tmp_path / "out"), "evaluation")
    back = fold_predictions(original, tmp_path / "no-data")
    assert [h.recording for h in back] == ["rec0"] and len(back[0].sensors) == len(held[0].sensors)
    np.testing.assert_allclose(back[0].sensors[2].log_probs, held[0].sensors[2].log_probs, atol=1e-6)

    # what each sensor is taken for (`real-confusion`): counted from the same predictions, one image per person
    table = real_confusion(original, tmp_path / "no-data")
    assert {a.path for a in client.list_artifacts(summary, "plots/real_confusion")} == {
        "plots/real_confusion/person0.png",
        "plots/real_confusion/pooled.png",
    }
    for sensor in held[0].sensors:
        answers = sensor.log_probs[sensor.moving].argmax(axis=1)
        right = 100 * np.mean(answers == sensor.segment)
        assert f"| person0 | {SEGMENTS[sensor.segment]} ({len(answers)}) | {right:.1f} % |" in table


def test_the_confusion_counts_each_person_s_moving_windows_and_names_what_a_sensor_is_taken_for() -> None:
    """``real-confusion``'s counts: per person over their recordings and pooled over everyone, moving windows only,
    each window's own answer; the table names the segment each worn one is most often taken for."""

    def sensor(segment: int, answers: list[int], moving: list[int]) -> SensorPrediction:
        log_probs = np.full((len(answers), K), -10.0)
        log_probs[np.arange(len(answers)), answers] = 0.0
        return SensorPrediction(segment, log_probs, np.asarray(moving, bool))

    pelvis, left, right = (SEGMENTS.index(n) for n in ("Pelvis", "LeftLowerLeg", "RightLowerLeg"))
    held = [
        HeldOut("anna", "a/1", "walk", [sensor(left, [left, right, right, left], [1, 1, 1, 0])]),
        HeldOut("anna", "a/2", "walk", [sensor(left, [left, left], [1, 1]), sensor(pelvis, [pelvis], [0])]),
        HeldOut("ben", "b/1", "walk", [sensor(right, [right, right, left], [1, 1, 1])]),
    ]
    matrices = held_out_confusions(held)
    assert set(matrices) == {"anna", "ben", "pooled"}
    assert (matrices["anna"][left, left], matrices["anna"][left, right], matrices["anna"].sum()) == (3, 2, 5)
    np.testing.assert_array_equal(matrices["pooled"], matrices["anna"] + matrices["ben"])
    table = confusion_table(matrices)
    assert "| anna | LeftLowerLeg (5) | 60.0 % | RightLowerLeg (2) |" in table
    assert "| ben | RightLowerLeg (3) | 66.7 % | LeftLowerLeg (1) |" in table
    assert "| pooled | RightLowerLeg (3) | 66.7 % | LeftLowerLeg (1) |" in table
    assert "Pelvis" not in table  # its one window is still
    assert table.index("| anna |") < table.index("| ben |") < table.index("| pooled |")
    with pytest.raises(ValueError, match="pooled"):
        held_out_confusions([HeldOut("pooled", "p/1", "walk", [])])


def test_a_session_calibration_that_never_reaches_the_target_is_not_served() -> None:
    per_sensor = ConfidenceModel((1.0, 0.0, 0.0), 0.0, 0.95, 8)
    never = replace(per_sensor, session=SessionConfidence((1.0, 0.0), 0.0, 0.999))
    reached = replace(per_sensor, session=SessionConfidence((1.0, 0.0), 0.0, 0.97))
    assert servable(never) == per_sensor and servable(reached) == reached and servable(per_sensor) == per_sensor
    p = np.linspace(0.5, 1.0, 1000)
    assert choose_threshold(p, np.zeros(len(p), bool), np.full(len(p), 20)) == 0.999  # UNREACHED


def test_a_calibration_fitted_on_answers_that_weigh_the_swing_says_so(data_dir) -> None:
    """Held-out predictions with how their sensors swung (``with_swing``, from the real recording): the sessions are
    answered as the service answers them, with the swing, and the calibration records the weight it saw, which the
    service then answers its sessions with (``session_swing_weight``)."""
    from service.core.assignment import SWING_WEIGHT
    from service.core.recordings import read_all_real
    from training.i2s.calibration import confidence_spec, with_swing

    recording = next(r for r in read_all_real(data_dir) if r.name == "movingreality/pp02/1Reg")
    labelled = [s for s in recording.sensors if s.segment is not None]
    rng = np.random.default_rng(7)
    n = len(sliding_windows(labelled[0].imu))
    held = [HeldOut("pp02", recording.name, "walk", [_sensor(s.segment, 0.5, n, rng) for s in labelled])]
    assert sessions(held).swing_weight == 0.0  # without the recording's gyroscopes: not weighed
    swung = with_swing(held, data_dir)
    assert swung[0].swing.shape == (n, len(labelled), len(labelled), 12)
    samples = sessions(swung)
    assert samples.swing_weight == SWING_WEIGHT
    model = calibrated_model(
        replace(samples, person=np.where(samples.session % 2, "a", "b")), np.ones(len(samples.correct), bool)
    )
    assert model.swing_weight == SWING_WEIGHT
    assert confidence_spec(model, "test", {}, "").swing_weight == SWING_WEIGHT
    # The swing moves answers: the feet and shanks of this walk swing as legs do, so weighed they are right more often.
    assert samples.correct.mean() > sessions(held).correct.mean()


def test_the_swing_table_scores_a_runs_held_out_predictions_and_records_them(
    mlflow_server: str, data_dir, tmp_path
) -> None:
    """``swing-table`` reads a real-loso run's stored held-out predictions with the recordings' gyroscopes, and
    writes the swing-weighted per-moment figures into a model's manifest."""
    import shutil

    from service.core.manifest import read_manifest
    from service.core.recordings import read_all_real
    from training.i2s.swing import SWING_LOSO, swing_table

    recording = next(r for r in read_all_real(data_dir) if r.name == "movingreality/pp02/1Reg")
    labelled = [s for s in recording.sensors if s.segment is not None]
    n = len(sliding_windows(labelled[0].imu))
    rng = np.random.default_rng(8)
    held = [HeldOut("movingreality_pp02", recording.name, "walk", [_sensor(s.segment, 0.5, n, rng) for s in labelled])]
    client = MlflowClient()
    experiment = mlflow.set_experiment("swing-table-test").experiment_id
    summary = client.create_run(
        experiment, tags={"real_loso": "summary", "fold_run.movingreality_pp02": "x"}
    ).info.run_id
    _write_predictions(held, tmp_path / "out" / "held_out_predictions")
    client.log_artifacts(summary, str(tmp_path / "out"), "evaluation")
    model_dir = tmp_path / "model"
    shutil.copytree("onnx_models/i2s_assignment/1.10.2", model_dir, ignore=shutil.ignore_patterns("*.onnx", "*.npz"))
    table = swing_table(summary, data_dir, weights=[0.5], model_dir=model_dir, command="test")
    assert "| movingreality_pp02 (" in table and "weight 0.5" in table
    recorded = next(e for e in read_manifest(model_dir / "manifest.json").evaluations if e.name == SWING_LOSO)
    swung = recorded.metrics["real_window_joint_swing_accuracy/pooled"]
    plain = float(table.split("| pooled (")[1].split("|")[1].split("/")[0])  # the first column, without the swing
    assert swung * 100 > plain  # half the windows right alone: the legs' swing sets many of the others right
    assert recorded.metrics["n_windows/pooled"] == sum(int(p.moving.sum()) for p in held[0].sensors)
