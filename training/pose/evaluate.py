"""Pose metrics, per clip and per motion type and held-out subject (Zheng et al. 2021 Table 1; DIP 2018, TransPose
2021).

For each clip one fixed simulated session (``train.fixed_sessions``) goes through the predictor; the answer is
assembled into the whole body the way the service assembles it (``service.inference.pose.whole_body``: the
sensors' segments as measured, the others the measured pelvis times the model's answer). Metrics:

- ``angle_all_deg``: mean geodesic angle between predicted and true global segment orientations over every
  segment the model covers (sensors and outputs); ``angle_unsensed_deg``: over the output segments only
  (Zheng et al. 2021 Table 1 reports "the relative rotation angle between the reconstructed pose and the actual pose");
  ``angle_major_deg``: over the covered segments without pelvis, hands, feet and toes, the joint set of DIP's and
  TransPose's angular error;
- ``sip_deg``: the same over the upper arms and upper legs (SIP error, DIP 2018 / TransPose 2021);
- per joint (``per_joint_deg``): the mean absolute error of each joint angle of ``service.core.joint_angles``
  (flexion, abduction, rotation; hip, knee and ankle for a gait lab) over the joints whose two segments the model
  covers, and its mean signed error (``per_joint_bias_deg``, answer − truth);
- ``jpe_cm``: mean distance of the segment origins after forward kinematics with the clip's own skeleton
  (``body.clip_body``), root-aligned (Vlutters 2016 §IV-E; TransPose's joint position error);
- ``jitter_mps3``: mean magnitude of the third time derivative of the predicted joint positions (TransPose), and
  ``jitter_true_mps3`` of the truth for reference;
- ``trans_1s_cm``, ``trans_5s_cm``: the body's translation (``service.core.translation``, the service's rule on the
  answer and the simulated pelvis accelerometer): over every window of 1 s (5 s), the distance between the
  predicted and the true displacement of the pelvis, averaged over the windows (TransPose 2021 plots the same
  distance against the distance walked); ``trans_truth_1s_cm`` the rule on the true pose (what the rule itself
  costs), ``trans_still_1s_cm`` a pelvis kept in place (the mean distance the pelvis travels in 1 s).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS, Body, clip_body, feet_of
from service.core.calibration import ACC_SCALE_MPS2
from service.core.joint_angles import JOINT_COMPONENTS, angle_difference_deg, answered_joints, joint_angles_deg
from service.core.translation import RootTracker
from service.inference.pose import whole_body
from training.pose.data import MotionClip
from training.pose.simulate import Session
from training.pose.train import geodesic_deg

SIP_SEGMENTS = ("LeftUpperArm", "RightUpperArm", "LeftUpperLeg", "RightUpperLeg")
# DIP 2018 and TransPose 2021 leave the root, ankles, feet, wrists and hands out of their angular error
# (their evaluation's ignored joints); ``angle_major_deg`` does the same: every covered segment but the pelvis,
# hands, feet and toes.
MINOR_SEGMENTS = ("Pelvis", "LeftHand", "RightHand", "LeftFoot", "RightFoot", "LeftToe", "RightToe")
METRICS = (
    "angle_all_deg",
    "angle_major_deg",
    "angle_unsensed_deg",
    "sip_deg",
    "jpe_cm",
    "jitter_mps3",
    "jitter_true_mps3",
    "trans_1s_cm",
    "trans_5s_cm",
    "trans_truth_1s_cm",
    "trans_still_1s_cm",
)


@dataclass(frozen=True)
class ClipResult:
    path: str
    activity: str
    group: str
    frames: int
    metrics: dict[str, float]
    per_segment_deg: dict[str, float]
    # the constant part of each segment's error in this clip: the angle of the rotation mean of R_true⁻¹ R_pred
    # (how the person holds a segment no sensor sees, or a frame convention that differs between rigs)
    per_segment_constant_deg: dict[str, float]
    # each answered joint angle's mean absolute error, "LeftKnee_flexion" -> degrees, and its mean signed error
    per_joint_deg: dict[str, float] = field(default_factory=dict)
    per_joint_bias_deg: dict[str, float] = field(default_factory=dict)


def clip_metrics(
    clip: MotionClip,
    session: Session,
    R_root_out: np.ndarray,
    sensors: Sequence[str],
    outputs: Sequence[str],
    hinges: bool,
) -> ClipResult:
    sensor_index = [BODY_SEGMENTS.index(s) for s in sensors]
    output_index = [BODY_SEGMENTS.index(s) for s in outputs]
    covered = sorted(sensor_index + output_index)
    R_pred = whole_body(session.R_world_sensor_segment, R_root_out, sensor_index, output_index, hinges=hinges)
    Rz = Rotation.from_rotvec([0.0, 0.0, session.heading_rad]).as_matrix()
    R_true = np.einsum("ij,tsjk->tsik", Rz, clip.motion.R_world_segment)
    err = geodesic_deg(R_pred, R_true)  # (T, 21)
    body = clip_body(clip.motion)
    p_pred, p_true = body.forward(R_pred), body.forward(R_true)
    joints = [k for k in covered if k != 0]
    dist = np.linalg.norm(p_pred[:, joints] - p_true[:, joints], axis=-1)
    rate = clip.motion.sample_rate_hz

    def jitter(p: np.ndarray) -> float:
        if len(p) < 4:
            return float("nan")
        return float(np.linalg.norm(np.diff(p[:, joints], n=3, axis=0) * rate**3, axis=-1).mean())

    sip = [BODY_SEGMENTS.index(s) for s in SIP_SEGMENTS if BODY_SEGMENTS.index(s) in covered]
    major = [k for k in covered if BODY_SEGMENTS[k] not in MINOR_SEGMENTS]
    metrics = {
        "angle_all_deg": float(err[:, covered].mean()),
        "angle_major_deg": float(err[:, major].mean()) if major else float("nan"),
        "angle_unsensed_deg": float(err[:, output_index].mean()),
        "sip_deg": float(err[:, sip].mean()) if sip else float("nan"),
        "jpe_cm": float(dist.mean() * 100.0),
        "jitter_mps3": jitter(p_pred),
        "jitter_true_mps3": jitter(p_true),
    }
    root_true = clip.motion.origin_m[:, 0] @ Rz.T  # the pelvis in the session's world
    metrics |= translation_metrics(body, R_pred, R_true, pelvis_free_acc(session), root_true, rate)
    per_segment = {BODY_SEGMENTS[k]: float(err[:, k].mean()) for k in covered}
    constant = {
        BODY_SEGMENTS[k]: float(
            np.degrees(Rotation.from_matrix(np.einsum("tji,tjk->tik", R_true[:, k], R_pred[:, k])).mean().magnitude())
        )
        for k in covered
    }
    answered = answered_joints({BODY_SEGMENTS[k] for k in covered})
    diff = angle_difference_deg(joint_angles_deg(R_pred, answered), joint_angles_deg(R_true, answered))
    names = [f"{j}_{c}" for j in answered for c in JOINT_COMPONENTS]
    per_joint = dict(zip(names, np.abs(diff).mean(axis=0).ravel().tolist(), strict=True))
    bias = dict(zip(names, diff.mean(axis=0).ravel().tolist(), strict=True))
    return ClipResult(
        clip.path, clip.activity, clip.group, clip.motion.n_frames, metrics, per_segment, constant, per_joint, bias
    )


def pelvis_free_acc(session: Session) -> np.ndarray:
    """The simulated pelvis sensor's free acceleration in the world ``(T, 3)``, as the service computes it
    (``calibration.segment_readings``), read back from the features (the root's own acceleration, eq. 3)."""
    own = session.features[:, 3:6].astype(np.float64) * ACC_SCALE_MPS2
    return np.einsum("tij,tj->ti", session.R_world_sensor_segment[:, 0], own)


def translation_metrics(
    body: Body, R_pred: np.ndarray, R_true: np.ndarray, acc: np.ndarray, root_true: np.ndarray, rate: float
) -> dict[str, float]:
    """``trans_*`` of the module docstring for one clip (NaN where the clip is shorter than the window)."""

    def track(R: np.ndarray) -> np.ndarray:
        return RootTracker(feet_of(body), rate).advance(body.forward(R), acc)[0]

    def error(p: np.ndarray, seconds: float) -> float:
        n = int(round(seconds * rate))
        if len(p) <= n:
            return float("nan")
        return float(np.linalg.norm((p[n:] - p[:-n]) - (root_true[n:] - root_true[:-n]), axis=-1).mean() * 100.0)

    p_pred = track(R_pred)
    return {
        "trans_1s_cm": error(p_pred, 1.0),
        "trans_5s_cm": error(p_pred, 5.0),
        "trans_truth_1s_cm": error(track(R_true), 1.0),
        "trans_still_1s_cm": error(np.zeros_like(root_true), 1.0),
    }


def evaluate_clips(
    predict: Callable[[np.ndarray], np.ndarray],
    clips: list[MotionClip],
    sessions: list[Session],
    sensors: Sequence[str],
    outputs: Sequence[str],
    *,
    hinges: bool,
) -> list[ClipResult]:
    """Each clip's figures with the answer assembled as the service assembles it: ``hinges`` as the model's
    ``hinge_joints`` (by its frames; False for the mean-pose baseline)."""
    return [
        clip_metrics(c, s, predict(s.features), sensors, outputs, hinges) for c, s in zip(clips, sessions, strict=True)
    ]


def summarise(results: list[ClipResult]) -> dict[str, dict[str, dict[str, float]]]:
    """Frame-weighted means: ``{"overall": {"all": m}, "activity": {walk: m, …}, "subject": {cmu_07: m, …}}``
    where each m holds the metrics and ``frames``."""

    def mean(rs: list[ClipResult]) -> dict[str, float]:
        w = np.array([r.frames for r in rs], dtype=np.float64)
        out = {}
        for k in METRICS:
            v = np.array([r.metrics[k] for r in rs])
            ok = np.isfinite(v)
            out[k] = float((v[ok] * w[ok]).sum() / w[ok].sum()) if ok.any() else float("nan")
        out["frames"] = float(w.sum())
        return out

    by_activity, by_group = defaultdict(list), defaultdict(list)
    for r in results:
        by_activity[r.activity].append(r)
        by_group[r.group].append(r)
    return {
        "overall": {"all": mean(results)},
        "activity": {k: mean(v) for k, v in sorted(by_activity.items())},
        "subject": {k: mean(v) for k, v in sorted(by_group.items())},
    }


def draws_mean(draws: list[list[ClipResult]]) -> list[ClipResult]:
    """Each clip's figures averaged over its simulated sessions: ``draws[k][i]`` is clip i scored on its k-th
    session (the same clips in the same order in every draw). Since a clip's frames are the same in every draw, the
    frame-weighted summaries of the result equal those of all draws pooled."""
    if len(draws) == 1:
        return draws[0]
    out = []
    for same in zip(*draws, strict=True):
        first = same[0]
        if any(r.path != first.path for r in same):
            raise ValueError("draws_mean needs the same clips in the same order in every draw")

        def mean(key: str, field: str, rs: tuple[ClipResult, ...] = same) -> float:
            v = np.array([getattr(r, field)[key] for r in rs], dtype=np.float64)
            return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")

        out.append(
            ClipResult(
                first.path,
                first.activity,
                first.group,
                first.frames,
                {k: mean(k, "metrics") for k in first.metrics},
                {k: mean(k, "per_segment_deg") for k in first.per_segment_deg},
                {k: mean(k, "per_segment_constant_deg") for k in first.per_segment_constant_deg},
                {k: mean(k, "per_joint_deg") for k in first.per_joint_deg},
                {k: mean(k, "per_joint_bias_deg") for k in first.per_joint_bias_deg},
            )
        )
    return out


def clip_intervals(
    results: list[ClipResult], metric: str = "angle_all_deg", level: float = 0.95, resamples: int = 4000
) -> dict[str, tuple[float, float]]:
    """Percentile bootstrap intervals over clips of the frame-weighted mean of ``metric``, per motion type and
    overall (``"all"``): each motion type's clips resampled with replacement, ``resamples`` times (seeded: the same
    interval on every run), and the overall mean taken over the resampled types together, so that every resample
    keeps the test set's mix of motion types. It measures how much the figure owes to which clips were recorded, not
    to which people: clips of one person are not independent, so the interval is, if anything, too narrow."""
    rng = np.random.default_rng(0)
    tail = 100.0 * (1.0 - level) / 2.0

    def interval(sums: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
        means = sums / weights
        return float(np.percentile(means, tail)), float(np.percentile(means, 100.0 - tail))

    out, total_sum, total_w = {}, np.zeros(resamples), np.zeros(resamples)
    for activity in sorted({r.activity for r in results}):
        rs = [r for r in results if r.activity == activity]
        v = np.array([r.metrics[metric] for r in rs], dtype=np.float64)
        w = np.array([r.frames for r in rs], dtype=np.float64)
        ok = np.isfinite(v)
        v, w = v[ok], w[ok]
        if not len(v):
            continue
        pick = rng.integers(0, len(v), (resamples, len(v)))
        sums, weights = (v[pick] * w[pick]).sum(axis=1), w[pick].sum(axis=1)
        out[activity] = interval(sums, weights)
        total_sum, total_w = total_sum + sums, total_w + weights
    if out:
        out = {"all": interval(total_sum, total_w)} | out
    return out


def per_segment_mean(results: list[ClipResult], constant: bool = False) -> dict[str, float]:
    """Frame-weighted mean per segment of the error (or, ``constant``, of its constant part per clip)."""
    acc, w = defaultdict(float), defaultdict(float)
    for r in results:
        for s, v in (r.per_segment_constant_deg if constant else r.per_segment_deg).items():
            acc[s] += v * r.frames
            w[s] += r.frames
    return {s: acc[s] / w[s] for s in BODY_SEGMENTS if s in acc}


def per_joint_mean(results: list[ClipResult], bias: bool = False) -> dict[str, dict[str, float]]:
    """Frame-weighted mean absolute error (``bias``: mean signed error) of each answered joint angle, per motion type
    and over all clips (``"all"``): ``{"all": {"LeftKnee_flexion": degrees, …}, "walk": {…}, …}``."""

    def mean(rs: list[ClipResult]) -> dict[str, float]:
        acc, w = defaultdict(float), defaultdict(float)
        for r in rs:
            for k, v in (r.per_joint_bias_deg if bias else r.per_joint_deg).items():
                acc[k] += v * r.frames
                w[k] += r.frames
        return {k: acc[k] / w[k] for k in acc}

    return {"all": mean(results)} | {
        a: mean([r for r in results if r.activity == a]) for a in sorted({r.activity for r in results})
    }


def mean_pose_predictor(train_sessions: list[Session]) -> Callable[[np.ndarray], np.ndarray]:
    """Vlutters 2016 §IV-F: the average of every output over the training set, whatever the input."""
    targets = np.concatenate([s.targets for s in train_sessions]).astype(np.float64)  # (N, S, 3, 3)
    M = targets.mean(axis=0)
    U, _, Vt = np.linalg.svd(M)
    D = np.ones((len(M), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    mean_R = np.einsum("sij,sj,sjk->sik", U, D, Vt).astype(np.float32)

    def predict(features: np.ndarray) -> np.ndarray:
        return np.broadcast_to(mean_R, (len(features),) + mean_R.shape).copy()

    return predict


# the joints a gait lab reads (hip, knee, ankle), whose flexion errors a run logs and a manifest records
GAIT_JOINTS = ("LeftHip", "RightHip", "LeftKnee", "RightKnee", "LeftAnkle", "RightAnkle")


def joint_flexion_metrics(per_joint: dict[str, dict[str, float]], prefix: str = "test") -> dict[str, float]:
    """``per_joint_mean``'s flexion errors of the answered ``GAIT_JOINTS`` as metric names:
    ``test_LeftKnee_flexion_deg`` over every clip, ``test_walk_LeftKnee_flexion_deg`` per motion type."""
    out = {}
    for key, errors in per_joint.items():
        stem = prefix if key == "all" else f"{prefix}_{key}"
        out |= {f"{stem}_{j}_flexion_deg": errors[f"{j}_flexion"] for j in GAIT_JOINTS if f"{j}_flexion" in errors}
    return out


def flat_metrics(summary: dict, prefix: str = "test") -> dict[str, float]:
    """MLflow metric names: ``test_walk_angle_unsensed_deg``, ``test_subject_cmu_07_jpe_cm``, ``test_angle_all_deg``."""
    out = {f"{prefix}_{k}": v for k, v in summary["overall"]["all"].items() if k != "frames"}
    for a, m in summary["activity"].items():
        out.update({f"{prefix}_{a}_{k}": v for k, v in m.items() if k != "frames"})
    for g, m in summary["subject"].items():
        out.update({f"{prefix}_subject_{g}_{k}": v for k, v in m.items() if k != "frames"})
    return {k: float(v) for k, v in out.items() if np.isfinite(v)}
