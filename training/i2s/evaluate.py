"""Evaluation of an exported model the way Zimmermann et al. 2018 §3.3 does: on every window × segment × eq. 8
alignment of held-out subjects (LOSO), through onnxruntime, i.e. on the artefact that ships.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from service.core.assignment import (
    SWING_WEIGHT,
    gyro_norm,
    is_moving,
    joint_assignment,
    swing_per_moment,
    turns_about_vertical,
    window_joint_assignment,
)
from service.core.recordings import RealRecording
from service.core.segments import BODY_PART, SEGMENTS
from service.core.windowing import sliding_windows
from service.inference.predict import mean_alignment
from service.settings import Settings
from training.i2s.data.imu_sim import LEG_CHAIN
from training.i2s.data.mocap import Clip, as_recorded, braced_side
from training.i2s.data.windows import Augmentation, Batch, grid_batches
from training.i2s.metrics import alignment_metrics, assignment_metrics, confusion_matrix

Predict = Callable[[np.ndarray], np.ndarray]

# The simulated test data must not depend on the training seed: runs are compared on the same windows.
EVAL_SEED = 2018


def onnx_predictor(path: Path, threads: int = 2, batch: int = 1024) -> Predict:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])

    def predict(imu: np.ndarray) -> np.ndarray:
        return np.concatenate([session.run(None, {"imu": imu[i : i + batch]})[0] for i in range(0, len(imu), batch)])

    return predict


@dataclass
class SimEvaluation:
    metrics: dict[str, float]
    segment: np.ndarray  # (N,)
    predicted: np.ndarray  # (N,) class, or (N, 3) error angles in degrees
    confusion: np.ndarray | None
    digest: str  # identifies the evaluation data (clips, seed, simulation)


def evaluation_digest(clips: list[Clip], aug: Augmentation) -> str:
    key = "|".join(sorted(c.digest for c in clips)) + f"|{aug.acc_noise_std_mps2}|{EVAL_SEED}"
    return hashlib.sha256(key.encode()).hexdigest()[:20]


def evaluate_simulated(
    predict: Predict,
    task: str,
    clips: list[Clip],
    aug: Augmentation,
    max_windows: int | None = None,
    segments: list[tuple[int, ...]] | None = None,
) -> SimEvaluation:
    """All grid windows of ``clips`` (optionally the first ``max_windows``, for quick tests; ``segments``: only
    those segments of each clip)."""
    segs, preds, quats, bodies, log_probs = [], [], [], [], []
    total = 0
    batches = grid_batches(clips, aug, EVAL_SEED, segments=segments)
    for batch, body in tqdm(batches, desc=f"evaluate {task}", unit="batch", leave=False):
        out = predict(batch.imu)
        segs.append(batch.segment)
        if task == "assignment":
            preds.append(out.argmax(-1))
            bodies.append(body)
            log_probs.append(np.log(np.clip(out, 1e-12, 1.0)))
        else:
            preds.append(out[np.arange(len(batch.segment)), batch.segment])
            quats.append(batch.q_segment_imu)
        total += len(batch.segment)
        if max_windows is not None and total >= max_windows:
            break
    seg = np.concatenate(segs)
    digest = evaluation_digest(clips, aug) + (f"-first{max_windows}" if max_windows else "")
    if segments is not None:
        digest += "-segments" + hashlib.sha256(repr(segments).encode()).hexdigest()[:8]
    if task == "assignment":
        pred = np.concatenate(preds)
        metrics = assignment_metrics(seg, pred)
        if segments is None:  # every segment of a body is scored: one-to-one per body, as on real recordings
            joint = body_joint_assignment(np.concatenate(bodies), np.concatenate(log_probs))
            whole = joint >= -1  # -2: the body was cut short by max_windows
            metrics["window_joint_accuracy"] = float(np.mean(joint[whole] == seg[whole]))
        return SimEvaluation(metrics, seg, pred, confusion_matrix(seg, pred), digest)
    metrics, err = alignment_metrics(seg, np.concatenate(quats), np.concatenate(preds))
    return SimEvaluation(metrics, seg, err, None, digest)


def body_joint_assignment(body: np.ndarray, log_probs: np.ndarray) -> np.ndarray:
    """Per row, its class in the one-to-one assignment of its body's rows (``grid_batches``); -2 for the rows of
    a body that has fewer than all segments (cut short by ``max_windows``).

    A body's rows come in class order; they are shuffled first, so that rows with tied log-probabilities (one
    saturated favourite, clipped at 1e-12) are not resolved in the truth's favour.
    """
    out = np.full(len(body), -2, dtype=np.int64)
    order = np.argsort(body, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(body[order]) != 0])
    rng = np.random.default_rng(EVAL_SEED)
    for rows in np.split(order, starts[1:]):
        if len(rows) == log_probs.shape[1]:
            rows = rows[rng.permutation(len(rows))]
            moment = window_joint_assignment([log_probs[r][None] for r in rows], [np.ones(1, bool)] * len(rows))
            out[rows] = np.concatenate(moment)
    return out


def evaluate_braced_knees(
    predict: Predict, clips: list[Clip], aug: Augmentation, max_windows: int | None = None
) -> SimEvaluation:
    """Assignment of the braced leg's shank and foot in stiff-knee variants (``stiff_knee_variants``) of held-out
    clips: whether a model tells a shank that swings like a thigh from the thigh. Only those two segments
    change in a variant, so only they are scored, in every grid window and alignment as ``evaluate_simulated``."""
    segments = []
    for clip in clips:
        foot, shank, _ = LEG_CHAIN[braced_side(clip)]
        segments.append((shank, foot))
    return evaluate_simulated(predict, "assignment", clips, aug, max_windows, segments)


LEG_SEGMENTS = frozenset(SEGMENTS.index(n) for n in ("LeftUpperLeg", "LeftLowerLeg", "RightUpperLeg", "RightLowerLeg"))
FOOT_SEGMENTS = frozenset(SEGMENTS.index(n) for n in ("LeftFoot", "RightFoot"))
# Per class, the classes of its body part on either side (the pelvis: itself).
SIDES_OF = tuple([k for k, p in enumerate(BODY_PART) if p == part] for part in BODY_PART)


def evaluate_real(predict: Predict, recordings: list[RealRecording]) -> tuple[dict[str, float], np.ndarray]:
    """Assignment on real recordings: per moving window, and per recording jointly (one-to-one).

    Windows whose gyroscope is still (``is_moving``) are counted, not scored: they carry no gait
    information (docs/conventions.md). Per recording and per sensor (``accuracy/<recording>/<segment>``) too, and per
    recording the share of moving leg windows that turn about the vertical (``turns_about_vertical``).
    Two answers per moving window: the window's own (``real_accuracy``, Zimmermann et al. 2018's per-window figure) and
    the one-to-one answer of the windows the recording's sensors took at that moment (``real_window_joint_*``,
    ``window_joint_assignment``). ``real_window_joint_swing_*`` is that answer weighing also how the sensors swing
    together, which is what ``/v1/imu/assign`` returns per window (and ``real_joint_assignment_swing_*`` the answer
    over the whole recording that weighs it, as the session answer of a model calibrated with it). A third,
    ``real_window_joint_worn_*``, is that answer when the user declares which segments carry the sensors (the service's
    ``worn_segments``) but not which sensor is where: it differs from the second only for recordings with sensors on
    fewer than seven segments (gaitmap's two feet). A fourth, ``real_window_joint_part_*``, is that answer when each
    sensor declares its body part but not its side (the service's ``candidate_segments``: both feet, both shanks, both
    thighs, or the pelvis): it scores how well the left/right question alone is answered. Returns metrics and the
    confusion matrix of moving windows (the windows' own answers).
    """
    y_true, y_pred, y_joint, y_swing, y_worn, y_part, metrics = [], [], [], [], [], [], {}
    joint_correct = swing_correct = joint_total = still = 0
    for rec in recordings:
        sensors = [s for s in rec.sensors if s.segment is not None]
        log_probs, moving, twisting, norms = [], [], [], []
        for s in sensors:
            windows = sliding_windows(s.imu.astype(np.float32))
            moving.append(is_moving(windows))
            norms.append(gyro_norm(windows))
            still += int((~moving[-1]).sum())
            if s.segment in LEG_SEGMENTS:
                twisting.append(turns_about_vertical(windows[moving[-1]]))
            probs = np.zeros((len(windows), len(SEGMENTS)), dtype=np.float32)
            probs[moving[-1]] = predict(np.ascontiguousarray(windows[moving[-1]]))
            log_probs.append(np.log(np.clip(probs, 1e-12, 1.0)))
            y_true.append(np.full(int(moving[-1].sum()), s.segment))
            y_pred.append(probs[moving[-1]].argmax(-1))
            if len(y_pred[-1]):
                metrics[f"accuracy/{rec.name}/{SEGMENTS[s.segment]}"] = float(np.mean(y_pred[-1] == s.segment))
        y_joint += moving_per_moment(log_probs, moving)
        y_swing += moving_per_moment(log_probs, moving, gyro_norms=norms)
        y_worn += moving_per_moment(log_probs, moving, worn=sorted({s.segment for s in sensors}))
        y_part += moving_per_moment(log_probs, moving, candidates=[SIDES_OF[s.segment] for s in sensors])
        if not all(m.any() for m in moving):
            continue
        joint = joint_assignment([lp[m] for lp, m in zip(log_probs, moving, strict=True)])
        swung = joint_assignment(
            [lp[m] for lp, m in zip(log_probs, moving, strict=True)],
            swing=swing_per_moment(norms, moving).sum(axis=0, dtype=np.float64),
        )
        truth = np.array([s.segment for s in sensors])
        swing_correct += int((swung.segment == truth).sum())
        joint_correct += int((joint.segment == truth).sum())
        joint_total += len(sensors)
        metrics[f"joint_correct_fraction/{rec.name}"] = float(np.mean(joint.segment == truth))
        rec_true, rec_pred = np.concatenate(y_true[-len(sensors) :]), np.concatenate(y_pred[-len(sensors) :])
        metrics[f"accuracy/{rec.name}"] = float(np.mean(rec_true == rec_pred))
        metrics[f"window_joint_accuracy/{rec.name}"] = float(
            np.mean(rec_true == np.concatenate(y_joint[-len(sensors) :]))
        )
        metrics[f"window_joint_swing_accuracy/{rec.name}"] = float(
            np.mean(rec_true == np.concatenate(y_swing[-len(sensors) :]))
        )
        metrics[f"window_joint_worn_accuracy/{rec.name}"] = float(
            np.mean(rec_true == np.concatenate(y_worn[-len(sensors) :]))
        )
        metrics[f"window_joint_part_accuracy/{rec.name}"] = float(
            np.mean(rec_true == np.concatenate(y_part[-len(sensors) :]))
        )
        if twisting:
            metrics[f"leg_windows_turning_about_vertical/{rec.name}"] = float(np.mean(np.concatenate(twisting)))
        metrics[f"n_windows/{rec.name}"] = float(len(rec_true))
    yt, yp, yj, yg, yw, ys = (np.concatenate(y) for y in (y_true, y_pred, y_joint, y_swing, y_worn, y_part))
    overall = assignment_metrics(yt, yp)
    metrics.update({f"real_{k}": v for k, v in overall.items()})
    part = np.array(BODY_PART + ("unassigned",))  # index -1 (unassigned) reads as the last entry: never right
    metrics["real_window_joint_accuracy"] = float(np.mean(yt == yj))
    metrics["real_window_joint_accuracy_ignoring_side"] = float(np.mean(part[yt] == part[yj]))
    metrics["real_window_joint_swing_accuracy"] = float(np.mean(yt == yg))
    metrics["real_window_joint_swing_accuracy_ignoring_side"] = float(np.mean(part[yt] == part[yg]))
    metrics["real_window_joint_worn_accuracy"] = float(np.mean(yt == yw))
    metrics["real_window_joint_worn_accuracy_ignoring_side"] = float(np.mean(part[yt] == part[yw]))
    metrics["real_window_joint_part_accuracy"] = float(np.mean(yt == ys))
    metrics["real_joint_assignment_correct_fraction"] = joint_correct / max(joint_total, 1)
    metrics["real_joint_assignment_swing_correct_fraction"] = swing_correct / max(joint_total, 1)
    metrics["real_still_windows_skipped"] = float(still)
    return metrics, confusion_matrix(yt, yp)


def moving_per_moment(
    log_probs: list[np.ndarray],
    moving: list[np.ndarray],
    worn: list[int] | None = None,
    candidates: list[list[int]] | None = None,
    gyro_norms: list[np.ndarray] | None = None,
    swing_weight: float = SWING_WEIGHT,
    laterals: list[np.ndarray] | None = None,
    sway: tuple[np.ndarray, np.ndarray] | None = None,
    sway_weight: float = 0.0,
) -> list[np.ndarray]:
    """Per sensor, the per-moment answers (``window_joint_assignment``) of its moving windows. The sensors go in a
    random order, so that tied windows are not resolved by the order the reader lists them in."""
    order = np.random.default_rng(EVAL_SEED).permutation(len(log_probs))
    answer = window_joint_assignment(
        [log_probs[k] for k in order],
        [moving[k] for k in order],
        worn=worn,
        candidates=None if candidates is None else [candidates[k] for k in order],
        gyro_norms=None if gyro_norms is None else [gyro_norms[k] for k in order],
        swing_weight=swing_weight,
        laterals=None if laterals is None else [laterals[k] for k in order],
        sway=sway,
        sway_weight=sway_weight,
    )
    return [answer[k][moving[s]] for s, k in enumerate(np.argsort(order))]


def evaluate_real_alignment(predict: Predict, recordings: list[RealRecording]) -> dict[str, float]:
    """Alignment on real recordings, which carry no I2S ground truth: checks per sensor that need no labels.

    - Stability: a strapped sensor does not turn on its segment, so every moving window should give the same
      q_segment_imu. Reported: the angle of each window's prediction from the sensor's mean rotation.
    - Uprightness (upper and lower legs): over a 2 s window of gait the mean specific force is near the
      leg's long axis, so R_segment_imu · mean(acc) should point near the segment's +z. Reported: its angle
      from +z. The true alignment of a sensor simulated from CMU walking reads about 19° (the shank leans
      during gait; tests/training/i2s/test_evaluate.py), one 90° off about x reads about 97°. Rotation about z
      (the long axis) does not show here.
    - Foot flat (feet): the functional foot frame's z is "up" while the foot is flat (``functional_correction``:
      the slowest quarter of its samples, pitch only). The sensor's own up over its slowest quarter of samples
      (``foot_flat_up``) is read off its accelerometer, so R_segment_imu · that direction should be the segment's
      +z up to the flat foot's roll, which the frame ignores. Reported: its angle from +z, per moving window.
      Rotation about z (the heading) does not show here either.
    - Nominal frame (sensors whose dataset gives one, ``RealSensor.nominal_frame``: gaitmap's walk, both feet): the
      angle of R_segment_imu from the dataset's rotation onto its nominal foot frame (x toward the toe, y left,
      z up, fixed by the mounting), per moving window, and per sensor the mean difference's rotation about z (the
      heading, which no other check sees). The nominal frame is the shoe's, not the functional foot frame, so
      they differ by the toe-out angle and the mount's tilt even for a perfect model: this catches gross errors
      (half and quarter turns), not degrees.
    - Half turns: the share of a sensor's windows more than 90° from its mean rotation (the mean is the larger
      mode's when a minority of windows sits a half turn away), per body part over the sensors worn there
      (``real_half_turn_share/<part>``) and over all. A frame that flips between two answers a half turn apart
      about its long axis (the pelvis: forwards or backwards) shows here. And live: the share of a sensor's moving
      windows after which its settled alignment as a stream keeps it (``mean_alignment`` of its moving windows so
      far, at most ``stream_alignment_windows``) is more than 90° from the recording's (``real_live_half_turn_share``
      and per part): how often a stream's answer for the sensor faces the other way before it settles.
    All are necessary, not sufficient (a constant output is perfectly stable); the simulated LOSO is the
    accuracy measure. Predictions are for the sensor's known segment.
    """
    spreads, tilts, feet, nominal, metrics = [], [], [], [], {}
    half_turns: dict[str, list[np.ndarray]] = {}
    live_turns: dict[str, list[np.ndarray]] = {}
    capacity = Settings().stream_alignment_windows
    for rec in recordings:
        rec_spread = []
        for s in (s for s in rec.sensors if s.segment is not None):
            windows = sliding_windows(s.imu.astype(np.float32))
            windows = np.ascontiguousarray(windows[is_moving(windows)])
            if len(windows) < 2:
                continue
            rot = Rotation.from_quat(predict(windows)[:, s.segment].astype(np.float64), scalar_first=True)
            rec_spread.append(np.degrees((rot.mean().inv() * rot).magnitude()))
            half_turns.setdefault(BODY_PART[s.segment], []).append(rec_spread[-1] > 90.0)
            live_turns.setdefault(BODY_PART[s.segment], []).append(_live_half_turns(rot, capacity))
            if s.segment in LEG_SEGMENTS:
                up = rot.apply(windows[..., :3].mean(axis=1).astype(np.float64))
                tilts.append(np.degrees(np.arccos(np.clip(up[:, 2] / np.linalg.norm(up, axis=1), -1.0, 1.0))))
            if s.segment in FOOT_SEGMENTS:
                feet.append(np.degrees(np.arccos(np.clip(rot.apply(foot_flat_up(s.imu))[:, 2], -1.0, 1.0))))
            if s.nominal_frame is not None:
                off = rot * Rotation.from_matrix(s.nominal_frame).inv()  # R_segment_nominal per window
                nominal.append(np.degrees(off.magnitude()))
                heading = off.mean().as_euler("xyz", degrees=True)[2]
                metrics[f"nominal_frame_heading_deg/{rec.name}/{SEGMENTS[s.segment]}"] = float(heading)
        if rec_spread:
            spreads += rec_spread
            metrics[f"alignment_spread_median_deg/{rec.name}"] = float(np.median(np.concatenate(rec_spread)))
    metrics.update(
        {
            **_median_p90("real_alignment_spread", spreads),
            **_median_p90("real_leg_up_axis_angle", tilts),
            **_median_p90("real_foot_flat_up_angle", feet),
            **_median_p90("real_nominal_frame_angle", nominal),
            "real_alignment_n_windows": float(sum(len(x) for x in spreads)),
        }
    )
    for part, flags in sorted(half_turns.items()):
        metrics[f"real_half_turn_share/{part}"] = float(np.concatenate(flags).mean())
    if half_turns:
        metrics["real_half_turn_share"] = float(np.concatenate([f for v in half_turns.values() for f in v]).mean())
    for part, flags in sorted(live_turns.items()):
        metrics[f"real_live_half_turn_share/{part}"] = float(np.concatenate(flags).mean())
    if live_turns:
        metrics["real_live_half_turn_share"] = float(np.concatenate([f for v in live_turns.values() for f in v]).mean())
    return metrics


def settled_alignments(q_rows: np.ndarray, capacity: int) -> np.ndarray:
    """A sensor's moving windows' quaternions ``(N, 4)``, in order → ``(N, 4)``: after each, the settled alignment
    a stream holds (``service.inference.predict.RunningAlignment``: the robust mean, ``mean_alignment``, of the
    last ``capacity`` of them so far)."""
    q = np.asarray(q_rows, dtype=np.float64)
    return np.array([mean_alignment(q[max(0, i + 1 - capacity) : i + 1])[0] for i in range(len(q))])


def _live_half_turns(rot: Rotation, capacity: int) -> np.ndarray:
    """Per moving window (``rot``, in order), whether the settled alignment a stream holds after it
    (``settled_alignments``) is more than 90° from the whole recording's."""
    q = rot.as_quat(scalar_first=True)
    final = Rotation.from_quat(mean_alignment(q)[0], scalar_first=True)
    settled = Rotation.from_quat(settled_alignments(q, capacity), scalar_first=True)
    return np.degrees((final.inv() * settled).magnitude()) > 90.0


def foot_flat_up(imu: np.ndarray) -> np.ndarray:
    """A foot sensor's "up" while the foot is flat: the unit mean specific force over the slowest quarter of its
    samples by gyroscope norm, as ``functional_correction`` picks the flat-foot samples of a mocap foot."""
    speed = np.linalg.norm(imu[:, 3:], axis=1)
    up = imu[speed <= np.quantile(speed, 0.25), :3].astype(np.float64).mean(axis=0)
    return up / np.linalg.norm(up)


def _median_p90(name: str, angles: list[np.ndarray]) -> dict[str, float]:
    """``<name>_median_deg`` and ``<name>_p90_deg`` of the pooled angles; nothing if there are none."""
    if not angles:
        return {}
    pooled = np.concatenate(angles)
    return {f"{name}_median_deg": float(np.median(pooled)), f"{name}_p90_deg": float(np.percentile(pooled, 90))}


_HALF_TURN_Z = Rotation.from_euler("z", 180.0, degrees=True)


def _folded_mean(r: Rotation, rounds: int = 4) -> Rotation:
    """Robust mean of ``r`` with each rotation first turned by 180° about z where that brings it closer."""
    centre = r.mean()
    for _ in range(rounds):
        flip = (centre.inv() * r * _HALF_TURN_Z).magnitude() < (centre.inv() * r).magnitude()
        folded = Rotation.concatenate([r[~flip], r[flip] * _HALF_TURN_Z]) if flip.any() else r
        d = (centre.inv() * folded).magnitude()
        centre = folded[d <= np.median(d)].mean()
    return centre


def population_offset_baseline(
    train_clips: list[Clip], test_clips: list[Clip], aug: Augmentation, n_fit_windows: int = 28_000
) -> dict[str, float]:
    """The alignment error of a reference predictor that needs no training: q_pred = c_seg ⊗ q_canonical_imu.

    c_seg is the training subjects' robust mean of R_segment_canonical (``CanonicalFrame`` of each window) per
    segment, and the 180° turn about z_c is resolved by the truth (an oracle, so the reference is optimistic
    there). What is left is how far the held-out subject's segment frames sit from the training subjects'
    relative to its own motion. A network that reads the segment frame off the motion, as the canonical
    alignment model does, cannot be expected to get below this without learning subject-specific cues. Scored
    on exactly the windows of ``evaluate_simulated`` (same seed and noise), in the Table A10 layout.
    """
    import torch  # training-side only: the canonical frame is the graph's own torch code

    from training.i2s.data.windows import WindowSampler
    from training.i2s.models import CanonicalFrame

    def canonical(batch: Batch) -> np.ndarray:
        return CanonicalFrame()(torch.from_numpy(batch.imu).double()).numpy()

    fit_aug = Augmentation(alignment="grid", acc_noise_std_mps2=aug.acc_noise_std_mps2)
    # the reference is fitted on gait as recorded
    fit = WindowSampler(as_recorded(train_clips), fit_aug).sample(np.random.default_rng(EVAL_SEED), n_fit_windows)
    R_si = Rotation.from_quat(fit.q_segment_imu, scalar_first=True).as_matrix()
    r_fit = Rotation.from_matrix(R_si @ np.transpose(canonical(fit), (0, 2, 1)))  # R_segment_canonical
    centres = [_folded_mean(r_fit[fit.segment == k]).as_matrix() for k in range(len(SEGMENTS))]
    segs, q_true, q_pred = [], [], []
    for batch, _ in tqdm(grid_batches(test_clips, aug, EVAL_SEED), desc="offset baseline", unit="batch", leave=False):
        R_c = canonical(batch)
        C = np.stack([centres[s] for s in batch.segment])
        candidates = [Rotation.from_matrix(C @ turn @ R_c) for turn in (np.eye(3), _HALF_TURN_Z.as_matrix())]
        truth = Rotation.from_quat(batch.q_segment_imu, scalar_first=True)
        closer = (candidates[1] * truth.inv()).magnitude() < (candidates[0] * truth.inv()).magnitude()
        q0, q1 = (c.as_quat(scalar_first=True) for c in candidates)
        q = np.where(closer[:, None], q1, q0)
        segs.append(batch.segment)
        q_true.append(batch.q_segment_imu)
        q_pred.append(q.astype(np.float32))
    metrics, _ = alignment_metrics(np.concatenate(segs), np.concatenate(q_true), np.concatenate(q_pred))
    return metrics
