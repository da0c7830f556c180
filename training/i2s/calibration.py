"""A confidence that knows when it does not know: the probability that a session's joint sensor assignment is
right, calibrated on people the model never trained on, and how long a live session takes to reach it.

Zimmermann et al. 2018 gives each window a softmax and the trial a joint answer (§2.2, §3.3), but no probability that
the answer is right. The summed window log-probabilities of ``joint_assignment`` are no such probability: windows
overlap and agree with each other, so their softmax reaches 1 within seconds, right or wrong. Here:

1. The leave-one-person-out folds of ``training.i2s.pipeline.run_real_loso`` each predict their held-out person's
   windows (``fold_predictions``): every figure below is on a person the predicting model never saw.
2. Sessions are cut from those recordings (``sessions``): every span of 2-120 s from many starts, all the
   recording's sensors and a random subset of them, each answered by ``joint_assignment`` as the service answers
   ``/v1/imu/assign``. Each sensor of a session gives ``confidence_features`` and whether its segment is right.
3. A logistic regression on those features, each person weighing the same (``fit_logistic``), is the
   ``service.core.assignment.ConfidenceModel``. Its own figures are leave-one-person-out again: the calibration
   of each person is fitted on the others (``cross_fitted``), so expected calibration error, the reliability
   diagram and the selective accuracy at the threshold are on people the calibration never saw either.
4. Time to answer (``time_to_answer``): each recording replayed from its start, the running joint answer after
   every window, as the stream's ``assignment`` message gives it; the seconds from the first moving window until
   the answer is right and stays right, and until the session's status is ``assigned``.

The threshold is the lowest probability above which the answers are right at least 99.5 % of the time (the
selective accuracy asked for; ``choose_threshold``). It is chosen inside the leave-one-person-out loop too
(``nested``): each person is judged by a calibration and a threshold fitted on the others only.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import mlflow
import numpy as np
from mlflow.tracking import MlflowClient

from service.core.assignment import (
    CONFIDENCE_FEATURES,
    ConfidenceModel,
    confidence_features,
    is_moving,
    session_assignment,
)
from service.core.recordings import RealRecording, read_all_real
from service.core.segments import SEGMENTS
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, sliding_windows
from training.i2s.evaluate import onnx_predictor
from training.plots import reliability_png

log = logging.getLogger(__name__)

TARGET = 0.995  # the selective accuracy asked for: the threshold is the lowest probability that reaches it
MIN_GIVEN = 200  # answers above a candidate threshold needed to judge it
MIN_MOVING_WINDOWS = 8  # about 2 s of walking after the first window (hop 16 samples at 60 Hz)
SPANS_S = (2.0, 4.0, 8.0, 15.0, 30.0, 60.0, 120.0)
STARTS_PER_SPAN = 8
HOP_S = HOP_SAMPLES / MODEL_RATE_HZ


@dataclass(frozen=True)
class SensorPrediction:
    segment: int  # the truth
    log_probs: np.ndarray  # (N, K) every window of the recording
    moving: np.ndarray  # (N,) bool


@dataclass(frozen=True)
class HeldOut:
    """One recording of a held-out person, predicted by the fold that never saw that person."""

    person: str
    recording: str
    activity: str
    sensors: list[SensorPrediction]


def fold_predictions(summary_run_id: str, data_dir: Path) -> list[HeldOut]:
    """Each fold of a ``real-loso`` summary run predicts its held-out person's labelled sensors."""
    client = MlflowClient()
    tags = client.get_run(summary_run_id).data.tags
    folds = {k.removeprefix("fold_run."): v for k, v in tags.items() if k.startswith("fold_run.")}
    if not folds:
        raise ValueError(f"run {summary_run_id} is not a real-loso summary run (no fold_run.* tags)")
    by_person: dict[str, list[RealRecording]] = {}
    for recording in read_all_real(data_dir):
        by_person.setdefault(recording.subject, []).append(recording)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (person, run_id) in enumerate(sorted(folds.items())):
            log.info("fold %d/%d: %s", k + 1, len(folds), person)
            uri = client.get_run(run_id).data.tags["model_uri"]
            onnx_path = next(Path(mlflow.artifacts.download_artifacts(uri, dst_path=f"{tmp}/{k}")).rglob("*.onnx"))
            predict = onnx_predictor(onnx_path)
            for recording in by_person[person]:
                sensors = []
                for s in recording.sensors:
                    if s.segment is None:
                        continue
                    windows = np.ascontiguousarray(sliding_windows(s.imu.astype(np.float32)))
                    probs = predict(windows)
                    sensors.append(SensorPrediction(s.segment, np.log(np.clip(probs, 1e-12, 1.0)), is_moving(windows)))
                out.append(HeldOut(person, recording.name, recording.activity, sensors))
    return out


@dataclass(frozen=True)
class Samples:
    """Per sensor of a session: features, right or not, and the session and person it belongs to."""

    features: np.ndarray  # (M, F)
    correct: np.ndarray  # (M,) bool
    session: np.ndarray  # (M,) int
    person: np.ndarray  # (M,) str
    span_s: np.ndarray  # (M,)
    moving: np.ndarray  # (M,) moving windows of the sensor


def answer(sensors: list[SensorPrediction], window: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joint answer over ``window`` of each sensor's windows, as the service gives it: segments, features,
    and each sensor's moving-window count."""
    joint, votes, n = session_assignment([s.log_probs[window] for s in sensors], [s.moving[window] for s in sensors])
    return joint.segment, confidence_features(joint.segment, joint.margin, votes, n), n


def sessions(held_out: list[HeldOut], seed: int = 0) -> Samples:
    """Sessions cut from the held-out recordings (module docstring, step 2)."""
    rng = np.random.default_rng(seed)
    rows: list[tuple] = []
    session = 0
    for rec in held_out:
        n_windows = min(len(s.moving) for s in rec.sensors)
        for span in SPANS_S:
            length = int(round(span / HOP_S))
            if length > n_windows:
                continue
            for start in np.linspace(0, n_windows - length, STARTS_PER_SPAN).astype(int):
                subsets = [list(range(len(rec.sensors)))]
                if len(rec.sensors) > 2:
                    size = int(rng.integers(2, len(rec.sensors)))
                    subsets.append(sorted(rng.choice(len(rec.sensors), size, replace=False).tolist()))
                for subset in subsets:
                    chosen = [rec.sensors[i] for i in subset]
                    segment, features, n = answer(chosen, slice(start, start + length))
                    for k, sensor in enumerate(chosen):
                        if segment[k] < 0:
                            continue
                        rows.append((features[k], segment[k] == sensor.segment, session, rec.person, span, n[k]))
                    session += 1
    features, correct, ids, person, span, moving = zip(*rows, strict=True)
    return Samples(
        np.array(features), np.array(correct), np.array(ids), np.array(person), np.array(span), np.array(moving)
    )


def fit_logistic(x: np.ndarray, y: np.ndarray, weight: np.ndarray, l2: float = 1e-3) -> tuple[np.ndarray, float]:
    """Weighted logistic regression by Newton's method (IRLS) with a small ridge; returns (coef, intercept)."""
    a = np.column_stack([x, np.ones(len(x))])
    w = np.zeros(a.shape[1])
    weight = weight / weight.mean()
    for _ in range(100):
        p = 1.0 / (1.0 + np.exp(-np.clip(a @ w, -50, 50)))
        grad = a.T @ (weight * (p - y)) + l2 * np.r_[w[:-1], 0.0]
        hess = (a * (weight * p * (1 - p))[:, None]).T @ a + l2 * np.diag(np.r_[np.ones(len(w) - 1), 0.0])
        step = np.linalg.solve(hess + 1e-9 * np.eye(len(w)), grad)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w[:-1], float(w[-1])


def _person_weights(person: np.ndarray) -> np.ndarray:
    """Each person weighs the same in the fit, however long their recordings."""
    names, inverse, counts = np.unique(person, return_inverse=True, return_counts=True)
    return 1.0 / counts[inverse]


def fit(samples: Samples, mask: np.ndarray | None = None, threshold: float = TARGET) -> ConfidenceModel:
    mask = np.ones(len(samples.correct), bool) if mask is None else mask
    coef, intercept = fit_logistic(
        samples.features[mask], samples.correct[mask].astype(float), _person_weights(samples.person[mask])
    )
    return ConfidenceModel(tuple(float(c) for c in coef), intercept, threshold, MIN_MOVING_WINDOWS)


def cross_fitted(samples: Samples, mask: np.ndarray | None = None) -> np.ndarray:
    """Each sample's probability from a calibration fitted on the other people's sessions only (within ``mask``;
    samples outside it read NaN)."""
    mask = np.ones(len(samples.correct), bool) if mask is None else mask
    p = np.full(len(samples.correct), np.nan)
    for person in np.unique(samples.person[mask]):
        own = samples.person == person
        p[own & mask] = fit(samples, mask & ~own).p_correct(samples.features[own & mask])
    return p


def choose_threshold(p: np.ndarray, correct: np.ndarray, moving: np.ndarray) -> float:
    """The lowest probability (on a 0.001 grid) above which at least ``MIN_GIVEN`` answers with enough moving
    windows are right at least ``TARGET`` of the time; 0.999 if none is."""
    enough = moving >= MIN_MOVING_WINDOWS
    for t in np.arange(0.5, 0.999, 0.001):
        given = enough & (p >= t)
        if given.sum() >= MIN_GIVEN and correct[given].mean() >= TARGET:
            return float(round(t, 3))
    return 0.999


def nested(samples: Samples) -> tuple[np.ndarray, dict[str, ConfidenceModel]]:
    """Leave one person out around the whole recipe: for each person, the calibration is fitted on the others and
    its threshold chosen on the others' cross-fitted probabilities (``choose_threshold``), so that the person's
    probabilities and the answers committed for them come from a recipe that never saw them. Returns each
    sample's probability and, per person, the calibration (with its threshold) that judged them."""
    p = np.zeros(len(samples.correct))
    models = {}
    for person in np.unique(samples.person):
        own = samples.person == person
        inner = cross_fitted(samples, ~own)
        threshold = choose_threshold(inner[~own], samples.correct[~own], samples.moving[~own])
        models[person] = fit(samples, ~own, threshold)
        p[own] = models[person].p_correct(samples.features[own])
    return p, models


def expected_calibration_error(p: np.ndarray, correct: np.ndarray, bins: int = 10) -> float:
    """Mean |accuracy − confidence| over equal-width probability bins, weighted by their counts (Guo et al. 2017)."""
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(p, edges[1:-1]), 0, bins - 1)
    return float(
        sum(
            abs(correct[which == b].mean() - p[which == b].mean()) * (which == b).mean()
            for b in range(bins)
            if (which == b).any()
        )
    )


def selective(samples: Samples, p: np.ndarray, thresholds: np.ndarray) -> dict[str, float]:
    """Per sensor and per session: of the answers given (probability at least the sample's threshold, on
    ``MIN_MOVING_WINDOWS`` or more; status ``assigned``), how many are right, and how often the service abstains."""
    given = (p >= thresholds) & (samples.moving >= MIN_MOVING_WINDOWS)
    out = {
        "sensor_selective_accuracy": float(samples.correct[given].mean()) if given.any() else float("nan"),
        "sensor_coverage": float(given.mean()),
        "sensor_accuracy_all": float(samples.correct.mean()),
        "sensor_confident_wrong": float((given & ~samples.correct).sum()),
    }
    ids = np.unique(samples.session)
    committed = np.array([given[samples.session == i].all() for i in ids])
    right = np.array([samples.correct[samples.session == i].all() for i in ids])
    out |= {
        "session_selective_accuracy": float(right[committed].mean()) if committed.any() else float("nan"),
        "session_abstain_rate": float(1.0 - committed.mean()),
        "session_confident_wrong": float((committed & ~right).sum()),
        "sessions": float(len(ids)),
    }
    return out


def time_to_answer(held_out: list[HeldOut], models: dict[str, ConfidenceModel]) -> dict[str, dict[str, float]]:
    """Per recording, replayed from its start (module docstring, step 4): seconds from the first moving window to
    the running answer being right for good (``right_s``; NaN if it never is) and to the status ``assigned``
    (``committed_s``; NaN if never), and whether the committed answer was right. ``models``: per person, the
    calibration fitted without that person."""
    out = {}
    for rec in held_out:
        n_windows = min(len(s.moving) for s in rec.sensors)
        moving_any = np.flatnonzero(np.any([s.moving[:n_windows] for s in rec.sensors], axis=0))
        if not len(moving_any):
            continue
        first = int(moving_any[0])
        truth = np.array([s.segment for s in rec.sensors])
        right = np.zeros(n_windows, bool)
        status = np.zeros(n_windows, bool)
        for t in range(first, n_windows):
            segment, features, n = answer(rec.sensors, slice(0, t + 1))
            right[t] = (segment == truth).all()
            model = models[rec.person]
            status[t] = model.status(model.p_correct(features), n, segment >= 0) == "assigned"
        wrong_after = np.flatnonzero(~right[first:])
        settle = first + (wrong_after[-1] + 1 if len(wrong_after) else 0)
        committed = np.flatnonzero(status)
        out[rec.recording] = {
            "right_s": (settle - first) * HOP_S if settle < n_windows else float("nan"),
            "committed_s": (committed[0] - first) * HOP_S if len(committed) else float("nan"),
            "committed_right": float(right[committed[0]]) if len(committed) else float("nan"),
            "duration_s": (n_windows - first) * HOP_S,
        }
    return out


# Motions that are not gait, of people no I2S model trained on (Bandai-Namco's actors; I2S training reads the CMU
# sets), to check that the service does not commit to an answer it cannot know.
NON_GAIT = ("raise_hand", "wave", "gesture", "bow", "punch", "slash", "kick", "dance")
NON_GAIT_CLIPS_PER_ACTIVITY = 12


def non_gait_sessions(
    predict, model: ConfidenceModel, data_dir: Path, cache_dir: Path, seed: int = 0
) -> dict[str, float]:
    """Simulated seven-sensor sessions of non-gait motion (``NON_GAIT``, up to ``NON_GAIT_CLIPS_PER_ACTIVITY``
    Bandai-Namco clips each, every sensor at a random eq. 8 alignment, each clip one session): how many the served
    model with its calibration commits to (status ``assigned``), and how many of those are wrong."""
    from training.data.catalog import read_catalog
    from training.i2s.data.imu_sim import alignment, imu_readings
    from training.i2s.data.mocap import KinematicsParams, build_kinematics

    rng = np.random.default_rng(seed)
    entries = []
    for activity in NON_GAIT:
        found = sorted(
            (e for e in read_catalog(data_dir) if e.activity == activity and e.source.startswith("bandai_namco")),
            key=lambda e: e.path,
        )
        if found:
            keep = rng.choice(len(found), min(NON_GAIT_CLIPS_PER_ACTIVITY, len(found)), replace=False)
            entries += [found[i] for i in sorted(keep)]
    clips = build_kinematics(data_dir, entries, cache_dir, KinematicsParams())
    committed = wrong = 0
    by_activity: dict[str, list[int]] = {}
    for clip in clips:
        sensors = []
        for seg in range(len(SEGMENTS)):
            R = alignment(seg, rng.uniform(0, 2 * np.pi, 1), rng.uniform(0, 2 * np.pi, 1))
            k = clip.kin
            imu = imu_readings(
                k.lin_acc_mps2[None, :, seg],
                k.up_mps2[None, :, seg],
                k.gyr_rads[None, :, seg],
                k.ang_acc_rads2[None, :, seg],
                R,
            )[0].astype(np.float32)
            windows = np.ascontiguousarray(sliding_windows(imu))
            if not len(windows):
                break
            probs = predict(windows)
            sensors.append(SensorPrediction(seg, np.log(np.clip(probs, 1e-12, 1.0)), is_moving(windows)))
        else:
            segment, features, n = answer(sensors, slice(0, None))
            done = model.status(model.p_correct(features), n, segment >= 0) == "assigned"
            bad = done and not (segment == np.arange(len(SEGMENTS))).all()
            committed, wrong = committed + done, wrong + bad
            counts = by_activity.setdefault(clip.entry.activity, [0, 0, 0])
            counts[0], counts[1], counts[2] = counts[0] + 1, counts[1] + done, counts[2] + bad
    out = {"non_gait_sessions": float(sum(c[0] for c in by_activity.values())), "non_gait_committed": float(committed)}
    out["non_gait_committed_wrong"] = float(wrong)
    for activity, (n, done, bad) in by_activity.items():
        out |= {f"non_gait_sessions/{activity}": float(n), f"non_gait_committed/{activity}": float(done)}
        out[f"non_gait_committed_wrong/{activity}"] = float(bad)
    return out


def calibrate(
    summary_run_id: str, data_dir: Path, model_dir: Path, cache_dir: Path
) -> tuple[ConfidenceModel, dict[str, float], dict]:
    """Steps 1-4 of the module docstring, logged as one MLflow run (metrics, the reliability diagram, the time to
    answer per recording), and the non-gait check of the model in ``model_dir`` with the final calibration
    (``non_gait_sessions``). Returns the calibration fitted on every person, its metrics (cross-fitted where they
    are on real people), and the time to answer per recording."""
    held_out = fold_predictions(summary_run_id, data_dir)
    samples = sessions(held_out)
    p, per_person = nested(samples)
    thresholds = np.array([per_person[person].threshold for person in samples.person])
    everyone = cross_fitted(samples)
    final = fit(samples, threshold=choose_threshold(everyone, samples.correct, samples.moving))
    metrics = {"ece": expected_calibration_error(p, samples.correct), "samples": float(len(p))}
    metrics |= selective(samples, p, thresholds)
    metrics |= {f"threshold/{person}": m.threshold for person, m in per_person.items()}
    for span in SPANS_S:
        at = samples.span_s == span
        if at.any():
            metrics[f"sensor_accuracy_all_{int(span)}s"] = float(samples.correct[at].mean())
    timing = time_to_answer(held_out, per_person)
    walking = [t for name, t in timing.items() if _is_walk(held_out, name)]
    for key in ("right_s", "committed_s"):
        values = np.array([t[key] for t in walking])
        metrics[f"time_to_{key.removesuffix('_s')}_median_s"] = (
            float(np.nanmedian(values)) if np.isfinite(values).any() else float("nan")
        )
        metrics[f"time_to_{key.removesuffix('_s')}_worst_s"] = (
            float(np.nanmax(values)) if np.isfinite(values).any() else float("nan")
        )
        metrics[f"time_to_{key.removesuffix('_s')}_never"] = float(np.isnan(values).sum())
    metrics["committed_wrong_recordings"] = float(sum(t["committed_right"] == 0.0 for t in timing.values()))
    metrics["recordings_replayed"] = float(len(timing))
    metrics |= non_gait_sessions(onnx_predictor(model_dir / "model.onnx"), final, data_dir, cache_dir)
    with mlflow.start_run(run_name="i2s_assignment_confidence") as run, tempfile.TemporaryDirectory() as tmp:
        mlflow.set_tags({"task": "assignment", "calibrated_from": summary_run_id})
        mlflow.log_params(
            {
                "target_selective_accuracy": TARGET,
                "threshold": final.threshold,
                "min_moving_windows": MIN_MOVING_WINDOWS,
                "features": CONFIDENCE_FEATURES,
            }
        )
        mlflow.log_metrics({k: v for k, v in metrics.items() if np.isfinite(v)})
        mlflow.log_dict({"coef": final.coef, "intercept": final.intercept}, "calibration/model.json")
        mlflow.log_dict(timing, "calibration/time_to_answer.json")
        title = f"joint assignment, held-out people ({len(np.unique(samples.person))}); ECE {metrics['ece']:.3f}"
        mlflow.log_artifact(str(reliability_png(p, samples.correct, Path(tmp) / "reliability.png", title)), "plots")
        metrics["run"] = run.info.run_id  # type: ignore[assignment]
    return final, metrics, timing


def _is_walk(held_out: list[HeldOut], name: str) -> bool:
    return next(h.activity for h in held_out if h.recording == name).startswith(("walk", "stairs"))
