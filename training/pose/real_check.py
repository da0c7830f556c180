"""The only real pose check we have: a lower-body model on real sensors, against the other real sensors.

Recordings with each sensor's own orientation: the capacitive-study subject (Xsens on pelvis, femurs, tibias and
toes; ``OpenSim_*_Orientations.sto``) and MovingReality's eight people after stroke (lumbar, shanks, feet). Every
sensor is calibrated with no pose at all, by the served I2S alignment model's robust mean over its moving windows
(``q_segment_sensor`` as ``/v1/imu/assign`` gives it, for the segment the sensor is known to be on). The pose model
gets the pelvis and shank sensors; its thighs and feet are compared with the thigh and foot sensors' segment
orientations, and its knee flexion with the flexion between the thigh and shank sensors. Both sides carry the
alignment's error (about 2-4° on simulated gait, more on real data), so this bounds rather than measures the
pose error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.core.assignment import is_moving
from service.core.body import BODY_SEGMENTS
from service.core.calibration import pelvis_heading_from_legs, pose_features, segment_readings
from service.core.joint_angles import joint_angles_deg
from service.core.recordings import (
    CAPACITIVE_TRIALS,
    MOVINGREALITY_SEGMENTS,
    OrientedSensor,
    read_capacitive_oriented,
    read_movingreality_trial,
)
from service.core.resample import resample_pose_rows, resample_uniform
from service.core.segments import SEGMENTS
from service.core.windowing import sliding_windows
from service.inference.pose import PoseModel, whole_body
from service.inference.predict import mean_alignment
from service.inference.registry import LoadedModel
from training.pose.train import geodesic_deg


def i2s_alignment(sensor: OrientedSensor, segment: str, alignment: LoadedModel) -> np.ndarray:
    """``q_segment_sensor`` from the I2S alignment model: robust mean over the sensor's moving windows."""
    imu = resample_uniform(np.concatenate([sensor.acc, sensor.gyr], axis=1), sensor.rate_hz, 60.0)
    windows = sliding_windows(imu.astype(np.float32))
    moving = windows[is_moving(windows)]
    quats = np.concatenate([alignment.run(moving[i : i + 256]) for i in range(0, len(moving), 256)])
    return mean_alignment(quats[:, SEGMENTS.index(segment)])[0]


def knee_flexion_deg(R_thigh: np.ndarray, R_shank: np.ndarray) -> np.ndarray:
    """A knee's flexion (``service.core.joint_angles``; it reads alike on both sides) from thigh and shank
    orientations, degrees; positive: flexed."""
    R = np.tile(np.eye(3), (len(R_thigh), len(BODY_SEGMENTS), 1, 1))
    R[:, BODY_SEGMENTS.index("LeftUpperLeg")], R[:, BODY_SEGMENTS.index("LeftLowerLeg")] = R_thigh, R_shank
    return joint_angles_deg(R, ["LeftKnee"])[:, 0, 0]


def check_recording(
    sensors: dict[str, OrientedSensor], model: PoseModel, alignment: LoadedModel, pelvis_heading: str = "legs"
) -> dict[str, float]:
    q_ss = {seg: i2s_alignment(s, seg, alignment) for seg, s in sensors.items()}
    rows = {seg: resample_pose_rows(s.acc, s.gyr, s.q_world_sensor, s.rate_hz) for seg, s in sensors.items()}
    n = min(len(r) for r in rows.values())
    inputs = model.spec.sensors
    out: dict[str, float] = {"frames": float(n)}
    if pelvis_heading == "legs":  # as the service does with these alignments: from the model's own leg sensors
        q_in = np.stack([q_ss[s] for s in inputs])
        turned, out["pelvis_turn_deg"] = pelvis_heading_from_legs(
            np.stack([rows[s][:n, 6:10] for s in inputs], axis=1), q_in, inputs
        )
        q_ss["Pelvis"] = turned[inputs.index("Pelvis")]
    seg_R = {}
    for seg, r in rows.items():
        R_w_seg, a_w = segment_readings(r[:n, None, 6:10], r[:n, None, :3], q_ss[seg][None])
        seg_R[seg] = (R_w_seg[:, 0], a_w[:, 0])
    R_in = np.stack([seg_R[s][0] for s in inputs], axis=1)
    a_in = np.stack([seg_R[s][1] for s in inputs], axis=1)
    R_pred = whole_body(
        R_in,
        model.predict(pose_features(R_in, a_in)),
        model.sensor_index,
        model.output_index,
        hinges=model.hinge_joints,
    )
    for name in ("UpperLeg", "Foot"):
        errs = []
        for side in ("Left", "Right"):
            seg = f"{side}{name}"
            if seg in seg_R and seg in model.spec.output_segments:
                errs.append(geodesic_deg(R_pred[:, BODY_SEGMENTS.index(seg)], seg_R[seg][0]))
        if errs:
            out[f"{name.lower()}_angle_deg"] = float(np.mean(errs))
    flex_err, corr, rom, extended = [], [], [], []
    for side in ("Left", "Right"):
        if f"{side}UpperLeg" not in seg_R:
            continue
        ref = knee_flexion_deg(seg_R[f"{side}UpperLeg"][0], seg_R[f"{side}LowerLeg"][0])
        got = knee_flexion_deg(R_pred[:, BODY_SEGMENTS.index(f"{side}UpperLeg")], seg_R[f"{side}LowerLeg"][0])
        flex_err.append(np.abs(got - ref).mean())
        corr.append(np.corrcoef(got, ref)[0, 1])
        rom.append((np.percentile(ref, 95) - np.percentile(ref, 5), np.percentile(got, 95) - np.percentile(got, 5)))
        # the knee at its most extended (2nd percentile): a walking knee extends to about 0-5° at heel strike
        extended.append((np.percentile(ref, 2), np.percentile(got, 2)))
    if flex_err:
        out["knee_flexion_mae_deg"] = float(np.mean(flex_err))
        out["knee_flexion_correlation"] = float(np.mean(corr))
        out["knee_range_sensors_deg"] = float(np.mean([r[0] for r in rom]))
        out["knee_range_model_deg"] = float(np.mean([r[1] for r in rom]))
        out["knee_extended_sensors_deg"] = float(np.mean([e[0] for e in extended]))
        out["knee_extended_model_deg"] = float(np.mean([e[1] for e in extended]))
    return out


def real_pose_check(
    data_dir: Path, model: PoseModel, alignment: LoadedModel, pelvis_heading: str = "legs"
) -> dict[str, dict[str, float]]:
    results = {}
    for trial in CAPACITIVE_TRIALS:
        results[f"capacitive_sub01/{trial}"] = check_recording(
            read_capacitive_oriented(data_dir, trial), model, alignment, pelvis_heading
        )
    root = data_dir / "imu_real" / "movingreality"
    for folder in sorted(p for p in root.glob("pp*/*") if p.is_dir()):
        sensors = read_movingreality_trial(data_dir, folder.parent.name, folder.name)
        by_segment = {MOVINGREALITY_SEGMENTS[s.name]: s for s in sensors}
        results[f"movingreality/{folder.parent.name}/{folder.name}"] = check_recording(
            by_segment, model, alignment, pelvis_heading
        )
    return results


def pooled(results: dict[str, dict[str, float]], prefix: str) -> dict[str, float]:
    """Frame-weighted means over the recordings under ``prefix``; the pelvis's turn to the legs (a label-free check
    of the I2S alignment's pelvis heading) as the median of its size and the recordings where it passes 45°."""
    rows = [r for k, r in results.items() if k.startswith(prefix)]
    keys = sorted({k for r in rows for k in r if k not in ("frames", "pelvis_turn_deg")})
    w = {k: np.array([r["frames"] for r in rows if k in r]) for k in keys}
    out = {k: float(np.sum([r[k] * r["frames"] for r in rows if k in r]) / w[k].sum()) for k in keys}
    turns = np.abs([r["pelvis_turn_deg"] for r in rows if "pelvis_turn_deg" in r])
    if len(turns):
        out |= {
            "pelvis_turn_median_abs_deg": float(np.median(turns)),
            "pelvis_turned_over_45deg": float((turns > 45).sum()),
        }
    return out | {"recordings": float(len(rows))}
