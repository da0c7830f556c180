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
3b. The probability that the whole joint assignment is right (``SessionConfidence``): a second logistic
   regression over ``service.core.assignment.session_features`` of each session's sensor probabilities (the logit
   of their product and the number of sensors), fitted on sensor probabilities that are themselves cross-fitted
   (``calibrated_model``). The product alone would be the answer if the sensors erred independently; they do not
   (a swap makes two wrong at once), and requiring every sensor to pass its own threshold left seven-sensor
   sessions uncommitted for good. The service commits on this probability when the manifest carries it.
4. Time to answer (``time_to_answer``): each recording replayed from its start, the running joint answer after
   every window, as the stream's ``assignment`` message gives it; the seconds from the first moving window until
   the answer is right and stays right, until the session's status is ``assigned``, and until each sensor
   commits on its own (``ConfidenceModel.committed``).

Each threshold (a sensor's, a session's) is the lowest probability above which the answers are right at least 99.5 %
of the time (the selective accuracy asked for) with 95 % confidence (``choose_threshold``). It is chosen inside the
leave-one-person-out loop too (``nested``): each person is judged by calibrations and thresholds fitted on the
others only.
"""

from __future__ import annotations

import json
import logging
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import mlflow
import numpy as np
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from service.core.assignment import (
    CONFIDENCE_FEATURES,
    SESSION_FEATURES,
    SWING_WEIGHT,
    ConfidenceModel,
    SessionConfidence,
    confidence_features,
    gyro_norm,
    is_moving,
    session_assignment,
    session_features,
    swing_per_moment,
)
from service.core.manifest import ConfidenceSpec
from service.core.recordings import RealRecording, read_all_real
from service.core.segments import SEGMENTS
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, sliding_windows
from training.i2s.evaluate import onnx_predictor
from training.plots import reliability_png
from training.run_labels import label_run
from training.snapshot import local_run_id
from training.tracking import download_onnx

log = logging.getLogger(__name__)

TARGET = 0.995  # the selective accuracy asked for: the threshold is the lowest probability that reaches it
MIN_GIVEN = 200  # answers above a candidate threshold needed to judge it
BOUND_Z = 1.645  # the one-sided 95 % normal quantile of ``lower_bound``
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
    # per moment, how its sensors swung together (``service.core.assignment.swing_per_moment``); None: not weighed
    swing: np.ndarray | None = None

    def swing_over(self, window: slice, subset: list[int] | None = None) -> np.ndarray | None:
        """The summed swing of ``window``'s moments, of ``subset``'s sensors (all if None)."""
        if self.swing is None:
            return None
        swing = self.swing[window]
        if subset is not None:
            swing = swing[:, subset][:, :, subset]
        return swing.sum(axis=0, dtype=np.float64)


PREDICTIONS_ARTIFACT = "evaluation/held_out_predictions"  # .npz (arrays) and .json (what each array is)


def fold_predictions(summary_run_id: str, data_dir: Path) -> list[HeldOut]:
    """Each fold of a ``real-loso`` summary run predicts its held-out person's labelled sensors. The predictions
    are kept with the summary run (``PREDICTIONS_ARTIFACT``), so that the calibration can be fitted again from a
    snapshot of the store, which keeps no fold's model file; they are computed from the fold models only the first
    time. Run ids may be original ones of a restored store (``training.snapshot.local_run_id``)."""
    client = MlflowClient()
    summary = local_run_id(summary_run_id)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            folder = Path(client.download_artifacts(summary, str(Path(PREDICTIONS_ARTIFACT).parent), tmp))
            stored = folder / Path(PREDICTIONS_ARTIFACT).name
            if stored.with_suffix(".json").is_file():
                return _read_predictions(stored)
        except (MlflowException, OSError):
            pass
        held_out = _predict_folds(client, summary, data_dir)
        _write_predictions(held_out, Path(tmp) / "out" / Path(PREDICTIONS_ARTIFACT).name)
        client.log_artifacts(summary, str(Path(tmp) / "out"), str(Path(PREDICTIONS_ARTIFACT).parent))
    return held_out


def with_swing(held_out: list[HeldOut], data_dir: Path) -> list[HeldOut]:
    """``held_out`` with, per recording, how its labelled sensors swung together at each moment (``HeldOut.swing``),
    from the recordings' gyroscopes: the service's joint answer weighs it."""
    recordings = {r.name: r for r in read_all_real(data_dir)}
    out = []
    for rec in held_out:
        sensors = [s for s in recordings[rec.recording].sensors if s.segment is not None]
        if [s.segment for s in sensors] != [s.segment for s in rec.sensors]:
            raise ValueError(f"{rec.recording}: the recording's labelled sensors are not those predicted")
        norms = [gyro_norm(sliding_windows(s.imu.astype(np.float32))) for s in sensors]
        out.append(replace(rec, swing=swing_per_moment(norms, [s.moving for s in rec.sensors])))
    return out


def _predict_folds(client: MlflowClient, summary_run_id: str, data_dir: Path) -> list[HeldOut]:
    tags = client.get_run(summary_run_id).data.tags
    folds = {k.removeprefix("fold_run."): v for k, v in tags.items() if k.startswith("fold_run.")}
    if not folds:
        raise ValueError(f"run {summary_run_id} is not a real-loso summary run (no fold_run.* tags)")
    uris = {}
    for person, run_id in sorted(folds.items()):
        fold = client.get_run(local_run_id(run_id))
        if "model_uri" not in fold.data.tags:
            raise ValueError(
                f"fold run {run_id} ({person}) has no model in this store (a snapshot keeps none) and the summary "
                f"run {summary_run_id} no {PREDICTIONS_ARTIFACT}: run real-loso again"
            )
        uris[person] = fold.data.tags["model_uri"]
    by_person: dict[str, list[RealRecording]] = {}
    for recording in read_all_real(data_dir):
        by_person.setdefault(recording.subject, []).append(recording)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (person, uri) in enumerate(uris.items()):
            log.info("fold %d/%d: %s", k + 1, len(uris), person)
            predict = onnx_predictor(download_onnx(uri, f"{tmp}/{k}"))
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


def _write_predictions(held_out: list[HeldOut], stem: Path) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    arrays, index = {}, []
    for i, rec in enumerate(held_out):
        segments = []
        for j, sensor in enumerate(rec.sensors):
            arrays[f"{i}_{j}_log_probs"] = sensor.log_probs.astype(np.float32)
            arrays[f"{i}_{j}_moving"] = sensor.moving
            segments.append(int(sensor.segment))
        index.append({"person": rec.person, "recording": rec.recording, "activity": rec.activity, "segments": segments})
    np.savez_compressed(stem.with_suffix(".npz"), **arrays)
    stem.with_suffix(".json").write_text(json.dumps(index, indent=1))


def _read_predictions(stem: Path) -> list[HeldOut]:
    index = json.loads(stem.with_suffix(".json").read_text())
    with np.load(stem.with_suffix(".npz")) as arrays:
        return [
            HeldOut(
                rec["person"],
                rec["recording"],
                rec["activity"],
                [
                    SensorPrediction(seg, arrays[f"{i}_{j}_log_probs"].astype(np.float64), arrays[f"{i}_{j}_moving"])
                    for j, seg in enumerate(rec["segments"])
                ],
            )
            for i, rec in enumerate(index)
        ]


@dataclass(frozen=True)
class Samples:
    """Per sensor of a session: features, right or not, and the session and person it belongs to."""

    features: np.ndarray  # (M, F)
    correct: np.ndarray  # (M,) bool
    session: np.ndarray  # (M,) int
    person: np.ndarray  # (M,) str
    span_s: np.ndarray  # (M,)
    moving: np.ndarray  # (M,) moving windows of the sensor
    swing_weight: float = 0.0  # of how the sensors swung together in the answers (0: not weighed)


def answer(
    sensors: list[SensorPrediction], window: slice, swing: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joint answer over ``window`` of each sensor's windows, as the service gives it (with ``swing``, the
    sensors' summed swing over the window's moments, ``HeldOut.swing_over``): segments, features, and each sensor's
    moving-window count."""
    joint, votes, n = session_assignment(
        [s.log_probs[window] for s in sensors], [s.moving[window] for s in sensors], swing=swing
    )
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
                    window = slice(start, start + length)
                    segment, features, n = answer(chosen, window, rec.swing_over(window, subset))
                    for k, sensor in enumerate(chosen):
                        if segment[k] < 0:
                            continue
                        rows.append((features[k], segment[k] == sensor.segment, session, rec.person, span, n[k]))
                    session += 1
    features, correct, ids, person, span, moving = zip(*rows, strict=True)
    weighed = all(rec.swing is not None for rec in held_out)  # ``answer`` weighs the swing where it is given
    return Samples(
        np.array(features),
        np.array(correct),
        np.array(ids),
        np.array(person),
        np.array(span),
        np.array(moving),
        SWING_WEIGHT if weighed else 0.0,
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


def _by_person(person: np.ndarray, mask: np.ndarray, fit_predict) -> np.ndarray:
    """Each row's probability from ``fit_predict(train, rows)``, a fit on the other people's rows within ``mask``
    predicting ``rows``; NaN outside ``mask``."""
    p = np.full(len(person), np.nan)
    for name in np.unique(person[mask]):
        own = person == name
        p[own & mask] = fit_predict(mask & ~own, own & mask)
    return p


def cross_fitted(samples: Samples, mask: np.ndarray | None = None) -> np.ndarray:
    """Each sample's probability from a calibration fitted on the other people's sessions only (within ``mask``;
    samples outside it read NaN)."""
    mask = np.ones(len(samples.correct), bool) if mask is None else mask
    return _by_person(samples.person, mask, lambda train, rows: fit(samples, train).p_correct(samples.features[rows]))


UNREACHED = 0.999  # ``choose_threshold``'s answer when no probability on its grid (0.500-0.998) reaches ``TARGET``


def lower_bound(right: int, given: int, z: float = BOUND_Z) -> float:
    """The one-sided Wilson lower confidence bound (Wilson 1927) of a share ``right / given``."""
    if given == 0:
        return 0.0
    share, z2 = right / given, z * z
    centre = share + z2 / (2 * given)
    spread = z * np.sqrt(share * (1.0 - share) / given + z2 / (4 * given * given))
    return float((centre - spread) / (1.0 + z2 / given))


def choose_threshold(p: np.ndarray, correct: np.ndarray, moving: np.ndarray) -> float:
    """The lowest probability (on a 0.001 grid) above which at least ``MIN_GIVEN`` answers with enough moving
    windows are right at least ``TARGET`` of the time, with 95 % confidence (``lower_bound``): a threshold whose
    answers merely reach ``TARGET`` on the people it is fitted on falls short on the next person about half the
    time. ``UNREACHED`` if none is."""
    enough = moving >= MIN_MOVING_WINDOWS
    for t in np.arange(0.5, UNREACHED, 0.001):
        given = enough & (p >= t)
        if given.sum() >= MIN_GIVEN and lower_bound(int(correct[given].sum()), int(given.sum())) >= TARGET:
            return float(round(t, 3))
    return UNREACHED


def servable(model: ConfidenceModel) -> ConfidenceModel:
    """``model`` as a manifest should carry it: without its session calibration when no session probability
    reached ``TARGET`` (a service committing on it would never commit), so that the service commits per sensor."""
    if model.session is not None and model.session.threshold >= UNREACHED:
        return replace(model, session=None)
    return model


@dataclass(frozen=True)
class SessionTable:
    """Per session: ``SESSION_FEATURES`` from its sensors' probabilities, whether every sensor is right, its
    person, and its fewest moving windows on a sensor."""

    features: np.ndarray  # (N, 2)
    correct: np.ndarray  # (N,) bool
    person: np.ndarray  # (N,) str
    moving: np.ndarray  # (N,) the session's least-moved sensor's moving windows
    session: np.ndarray  # (N,) the session ids of ``Samples``


def session_table(samples: Samples, p: np.ndarray) -> SessionTable:
    """Group the sensor rows of ``samples`` (with their probabilities ``p``) into sessions."""
    order = np.argsort(samples.session, kind="stable")
    ids, starts = np.unique(samples.session[order], return_index=True)
    groups = np.split(order, starts[1:])
    return SessionTable(
        np.array([session_features(p[g]) for g in groups]),
        np.array([samples.correct[g].all() for g in groups]),
        np.array([samples.person[g[0]] for g in groups]),
        np.array([samples.moving[g].min() for g in groups]),
        ids,
    )


def fit_session(table: SessionTable, mask: np.ndarray, threshold: float = TARGET) -> SessionConfidence:
    coef, intercept = fit_logistic(
        table.features[mask], table.correct[mask].astype(float), _person_weights(table.person[mask])
    )
    return SessionConfidence(tuple(float(c) for c in coef), intercept, threshold)


def session_cross_fitted(table: SessionTable, mask: np.ndarray) -> np.ndarray:
    """Each session's probability from a session calibration fitted on the other people's sessions (within
    ``mask``; NaN outside)."""
    return _by_person(table.person, mask, lambda train, rows: fit_session(table, train).p(table.features[rows]))


def calibrated_model(samples: Samples, mask: np.ndarray) -> ConfidenceModel:
    """The whole recipe fitted on the people of ``mask``: the sensors' calibration and threshold, then the
    session's calibration on their cross-fitted sensor probabilities and its threshold on the session
    probabilities cross-fitted again by person. No figure of a person outside ``mask`` is read."""
    inner = cross_fitted(samples, mask)
    sensor_threshold = choose_threshold(inner[mask], samples.correct[mask], samples.moving[mask])
    table = session_table(samples, np.where(mask, inner, 0.0))
    within = np.isin(table.person, np.unique(samples.person[mask]))
    session_p = session_cross_fitted(table, within)
    session_threshold = choose_threshold(session_p[within], table.correct[within], table.moving[within])
    sensors = fit(samples, mask, sensor_threshold)
    return replace(sensors, session=fit_session(table, within, session_threshold), swing_weight=samples.swing_weight)


def nested(samples: Samples) -> tuple[np.ndarray, dict[str, ConfidenceModel]]:
    """Leave one person out around the whole recipe (``calibrated_model``): for each person, calibrations and
    thresholds are fitted on the others only, so that the person's probabilities and the answers committed for
    them come from a recipe that never saw them. Returns each sample's probability and, per person, the
    calibration that judged them."""
    p = np.zeros(len(samples.correct))
    models = {}
    for person in np.unique(samples.person):
        own = samples.person == person
        models[person] = calibrated_model(samples, ~own)
        p[own] = models[person].p_correct(samples.features[own])
    return p, models


def nested_sessions(
    samples: Samples, p: np.ndarray, models: dict[str, ConfidenceModel]
) -> tuple[SessionTable, np.ndarray]:
    """The sessions of ``nested``'s sensor probabilities, each with its probability that all its sensors are right
    from the session calibration of the recipe that never saw its person."""
    table = session_table(samples, p)
    p_all = np.array(
        [models[person].session.p(f[None])[0] for person, f in zip(table.person, table.features, strict=True)]  # type: ignore[union-attr]
    )
    return table, p_all


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
    """Per sensor and per session, committing per sensor (probability at least the sample's threshold, on
    ``MIN_MOVING_WINDOWS`` or more; a session when all its sensors are): of the answers given, how many are right,
    and how often the service abstains."""
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
    # per number of sensors worn: how many sensors commit on their own (the service's per-sensor `committed`)
    _, index, counts = np.unique(samples.session, return_inverse=True, return_counts=True)
    size = counts[index]
    for n in np.unique(size):
        at = size == n
        out[f"sensor_answers_{n}_sensors"] = float(at.sum())
        out[f"sensor_coverage_{n}_sensors"] = float(given[at].mean())
        if (given & at).any():
            out[f"sensor_selective_accuracy_{n}_sensors"] = float(samples.correct[given & at].mean())
    return out


def selective_sessions(
    samples: Samples, table: SessionTable, p_all: np.ndarray, thresholds: np.ndarray
) -> dict[str, float]:
    """Committing per session (``p_all`` at least the session's threshold, every sensor on ``MIN_MOVING_WINDOWS``
    or more), as the service does with a session calibration: of the sessions committed, how many are right; how
    often it abstains; the same per sensor count; and per number of sensors worn."""
    committed = (p_all >= thresholds) & (table.moving >= MIN_MOVING_WINDOWS)
    sensor_given = np.isin(samples.session, table.session[committed])
    out = {
        "all_selective_accuracy": float(table.correct[committed].mean()) if committed.any() else float("nan"),
        "all_abstain_rate": float(1.0 - committed.mean()),
        "all_confident_wrong": float((committed & ~table.correct).sum()),
        "all_sensor_selective_accuracy": (
            float(samples.correct[sensor_given].mean()) if sensor_given.any() else float("nan")
        ),
        "all_sensor_coverage": float(sensor_given.mean()),
        "all_sessions_right": float(table.correct.mean()),
    }
    sizes = np.rint(np.exp(table.features[:, 1])).astype(int)
    for size in np.unique(sizes):
        at = sizes == size
        out[f"all_abstain_rate_{size}_sensors"] = float(1.0 - committed[at].mean())
        out[f"all_sessions_{size}_sensors"] = float(at.sum())
        if (committed & at).any():
            out[f"all_selective_accuracy_{size}_sensors"] = float(table.correct[committed & at].mean())
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
        sensor_committed = np.full(len(truth), -1)  # per sensor the first window it commits at (-1: never)
        sensor_right = np.zeros(len(truth), bool)  # and whether its segment was right then
        model = models[rec.person]
        swung = None if rec.swing is None else np.cumsum(rec.swing[:n_windows], axis=0, dtype=np.float64)
        for t in range(first, n_windows):
            segment, features, n = answer(rec.sensors, slice(0, t + 1), None if swung is None else swung[t])
            right[t] = (segment == truth).all()
            p = model.p_correct(features)
            status[t] = model.status(p, n, segment >= 0) == "assigned"
            new = model.committed(p, n, segment >= 0) & (sensor_committed < 0)
            sensor_committed[new], sensor_right[new] = t, (segment == truth)[new]
        wrong_after = np.flatnonzero(~right[first:])
        settle = first + (wrong_after[-1] + 1 if len(wrong_after) else 0)
        committed = np.flatnonzero(status)
        out[rec.recording] = {
            "right_s": (settle - first) * HOP_S if settle < n_windows else float("nan"),
            "committed_s": (committed[0] - first) * HOP_S if len(committed) else float("nan"),
            "committed_right": float(right[committed[0]]) if len(committed) else float("nan"),
            "duration_s": (n_windows - first) * HOP_S,
            # each sensor on its own (``ConfidenceModel.committed``): seconds to its first commitment (NaN: never)
            "sensor_committed_s": [(c - first) * HOP_S if c >= 0 else float("nan") for c in sensor_committed.tolist()],
            "sensor_committed_right": [
                float(r) if c >= 0 else float("nan") for c, r in zip(sensor_committed, sensor_right, strict=True)
            ],
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
    from training.data.catalog import is_bandai_namco, read_catalog
    from training.i2s.data.imu_sim import alignment, imu_readings
    from training.i2s.data.mocap import KinematicsParams, build_kinematics

    rng = np.random.default_rng(seed)
    entries = []
    for activity in NON_GAIT:
        found = sorted(
            (e for e in read_catalog(data_dir) if e.activity == activity and is_bandai_namco(e.source)),
            key=lambda e: e.path,
        )
        if found:
            keep = rng.choice(len(found), min(NON_GAIT_CLIPS_PER_ACTIVITY, len(found)), replace=False)
            entries += [found[i] for i in sorted(keep)]
    clips = build_kinematics(data_dir, entries, cache_dir, KinematicsParams())
    committed = wrong = 0
    by_activity: dict[str, list[int]] = {}
    for clip in clips:
        sensors, norms = [], []
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
            norms.append(gyro_norm(windows))
        else:
            swing = swing_per_moment(norms, [s.moving for s in sensors]).sum(axis=0, dtype=np.float64)
            segment, features, n = answer(sensors, slice(0, None), swing)
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


def confidence_spec(model: ConfidenceModel, fitted_on: str, metrics: dict[str, float], command: str) -> ConfidenceSpec:
    """The manifest's ``confidence`` of a fitted calibration (``servable`` first: a session probability that reached
    no threshold is left out, and the service then commits sensor by sensor)."""
    model = servable(model)
    return ConfidenceSpec(
        features=list(CONFIDENCE_FEATURES),
        coef=list(model.coef),
        intercept=model.intercept,
        threshold=model.threshold,
        min_moving_windows=model.min_moving_windows,
        session=model.session_spec(),
        swing_weight=model.swing_weight,
        fitted_on=fitted_on,
        metrics={k: round(float(v), 5) for k, v in metrics.items() if np.isfinite(v)},
        command=command,
    )


def calibrate(
    summary_run_id: str, data_dir: Path, model_dir: Path, cache_dir: Path
) -> tuple[ConfidenceModel, dict[str, float], dict]:
    """Steps 1-4 of the module docstring, logged as one MLflow run (metrics, the reliability diagram, the time to
    answer per recording), and the non-gait check of the model in ``model_dir`` with the final calibration
    (``non_gait_sessions``). Returns the calibration fitted on every person, its metrics (cross-fitted where they
    are on real people), and the time to answer per recording."""
    held_out = with_swing(fold_predictions(summary_run_id, data_dir), data_dir)
    samples = sessions(held_out)
    p, per_person = nested(samples)
    thresholds = np.array([per_person[person].threshold for person in samples.person])
    final = calibrated_model(samples, np.ones(len(samples.correct), bool))
    table, p_all = nested_sessions(samples, p, per_person)
    session_thresholds = np.array([per_person[person].session.threshold for person in table.person])  # type: ignore[union-attr]
    metrics = {"ece": expected_calibration_error(p, samples.correct), "samples": float(len(p))}
    metrics |= {"all_ece": expected_calibration_error(p_all, table.correct)}
    metrics |= selective(samples, p, thresholds)
    metrics |= selective_sessions(samples, table, p_all, session_thresholds)
    metrics |= {f"threshold/{person}": m.threshold for person, m in per_person.items()}
    metrics |= {f"all_threshold/{person}": m.session.threshold for person, m in per_person.items()}  # type: ignore[union-attr]
    for span in SPANS_S:
        at = samples.span_s == span
        if at.any():
            metrics[f"sensor_accuracy_all_{int(span)}s"] = float(samples.correct[at].mean())
    # replayed and checked as the service will judge (``servable``: a session rule that reached no threshold is not
    # served, and the service then commits sensor by sensor)
    timing = time_to_answer(held_out, {person: servable(m) for person, m in per_person.items()})
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
    alone = np.array([s for t in walking for s in t["sensor_committed_s"]])  # every sensor of every walk
    metrics["time_to_sensor_committed_median_s"] = (
        float(np.nanmedian(alone)) if np.isfinite(alone).any() else float("nan")
    )
    metrics["sensors_committed_share"] = float(np.isfinite(alone).mean()) if len(alone) else float("nan")
    metrics["sensors_committed_wrong"] = float(sum(r == 0.0 for t in walking for r in t["sensor_committed_right"]))
    metrics["recordings_replayed"] = float(len(timing))
    metrics |= non_gait_sessions(onnx_predictor(model_dir / "model.onnx"), servable(final), data_dir, cache_dir)
    with mlflow.start_run(run_name="i2s_assignment_confidence") as run, tempfile.TemporaryDirectory() as tmp:
        mlflow.set_tags({"task": "assignment", "calibrated_from": summary_run_id})
        mlflow.log_params(
            {
                "target_selective_accuracy": TARGET,
                "threshold": final.threshold,
                "session_threshold": final.session.threshold,  # type: ignore[union-attr]
                "min_moving_windows": MIN_MOVING_WINDOWS,
                "features": CONFIDENCE_FEATURES,
                "session_features": SESSION_FEATURES,
            }
        )
        mlflow.log_metrics({k: v for k, v in metrics.items() if np.isfinite(v)})
        session = final.session
        mlflow.log_dict(
            {"coef": final.coef, "intercept": final.intercept, "session": vars(session) if session else None},
            "calibration/model.json",
        )
        mlflow.log_dict(timing, "calibration/time_to_answer.json")
        people = len(np.unique(samples.person))
        title = f"one sensor's segment, held-out people ({people}); ECE {metrics['ece']:.3f}"
        mlflow.log_artifact(str(reliability_png(p, samples.correct, Path(tmp) / "reliability.png", title)), "plots")
        title = f"the whole joint assignment, held-out people ({people}); ECE {metrics['all_ece']:.3f}"
        png = reliability_png(
            p_all, table.correct, Path(tmp) / "reliability_session.png", title, what=("p_all_correct", "sessions")
        )
        mlflow.log_artifact(str(png), "plots")
        metrics["run"] = run.info.run_id  # type: ignore[assignment]
    label_run(MlflowClient(), str(metrics["run"]))  # its name and description in the UI
    return final, metrics, timing


def _is_walk(held_out: list[HeldOut], name: str) -> bool:
    return next(h.activity for h in held_out if h.recording == name).startswith(("walk", "stairs"))
