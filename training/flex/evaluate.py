"""Chen et al. 2024 §4's metrics: mean tracking error (mean absolute joint-angle error, degrees) overall, per
motion type (Table 2) and per joint (Table 3), and jitter as the mean jerk of the predicted angles (°/s³, the
third derivative at the sensors' rate; Table 4 and 5 report it in 10⁴ °/s³)."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable

import numpy as np

from service.core.joint_angles import JOINT_COMPONENTS
from training.flex.data import WindowSet
from training.flex.simulate import FLEX_RATE_HZ

Predictor = Callable[[np.ndarray], np.ndarray]  # (B, window, S) counts → (B, J, 3) degrees


def predict_windows(
    predict: Predictor, ws: WindowSet, suit: int, latency: int, hop: int = 1, batch: int = 1024
) -> tuple[np.ndarray, np.ndarray]:
    """Answers for every ``hop``-th window of suit ``suit`` and the truth at the frame each one answers for
    (``latency`` samples before the window's last)."""
    ends = ws.ends[::hop]
    preds = []
    for i in range(0, len(ends), batch):
        e = ends[i : i + batch]
        x, _ = ws.batch(np.full(len(e), suit), e, 1)
        preds.append(predict(x))
    return np.concatenate(preds), ws.angles[ends - 1 - latency]


def clip_metrics(
    predict: Predictor, ws: WindowSet, suit: int, latency: int, joints: list[str], sensors: list[str]
) -> dict:
    """Per clip every frame answered (hop 1): errors per joint and the jitter."""
    pred, truth = predict_windows(predict, ws, suit, latency)
    signed = pred - truth  # (W, J, 3)
    err = np.abs(signed)
    rows = []
    sensed = [joints.index(j) for j in sensors if j in joints]
    for i, c in enumerate(ws.clips):
        m = ws.clip_of_end == i
        per_component = err[m].mean(axis=0)  # (J, 3)
        p = pred[m]
        jerk = np.abs(np.diff(p, n=3, axis=0)).mean() * FLEX_RATE_HZ**3 if len(p) > 3 else np.nan
        rows.append(
            {
                "clip": c.path,
                "activity": c.activity,
                "frames": int(m.sum()),
                "per_joint": per_component.mean(axis=1),
                "per_component": per_component,
                "bias": signed[m].mean(axis=0),
                # the error left once each angle's constant offset over the clip is taken out
                "offset_free": np.abs(signed[m] - signed[m].mean(axis=0)).mean(),
                "sensed_flexion": err[m][:, sensed, 0].mean() if sensed else np.nan,
                "jitter": jerk,
            }
        )
    return summarise(rows, joints)


def summarise(rows: list[dict], joints: list[str]) -> dict:
    """Frame-weighted means over clips: overall, per activity, per joint; and each clip's error and jitter
    (``clips``)."""
    w = np.array([r["frames"] for r in rows], float)

    def mean(key: str, sel: list[int]) -> float:
        vals = np.array([np.mean(rows[i][key]) for i in sel])
        ok = np.isfinite(vals)
        return float(np.average(vals[ok], weights=w[sel][ok])) if ok.any() else float("nan")

    everything = list(range(len(rows)))
    per_joint = np.average(np.stack([r["per_joint"] for r in rows]), axis=0, weights=w)

    def per_component(key: str) -> dict[str, dict[str, float]]:
        v = np.average(np.stack([r[key] for r in rows]), axis=0, weights=w)  # (J, components)
        names = JOINT_COMPONENTS[: v.shape[1]]  # a knee-flexion model has the first only
        return {j: dict(zip(names, v[k].round(4).tolist(), strict=True)) for k, j in enumerate(joints)}

    by_activity = defaultdict(list)
    for i, r in enumerate(rows):
        by_activity[r["activity"]].append(i)
    return {
        "mae_deg": mean("per_joint", everything),
        "sensed_flexion_mae_deg": mean("sensed_flexion", everything),
        "offset_free_mae_deg": mean("offset_free", everything),
        "jitter_deg_s3": mean("jitter", everything),
        "frames": int(w.sum()),
        "per_joint": dict(zip(joints, per_joint.round(4).tolist(), strict=True)),
        # each angle's error, and its mean signed error (answer − truth): a constant offset the sensors cannot see
        "per_component": per_component("per_component"),
        "bias": per_component("bias"),
        "per_activity": {
            a: {"mae_deg": mean("per_joint", s), "frames": int(w[s].sum())} for a, s in by_activity.items()
        },
        "clips": [
            {
                "clip": r["clip"],
                "activity": r["activity"],
                "frames": r["frames"],
                "mae_deg": round(float(np.mean(r["per_joint"])), 4),
                "jitter_deg_s3": round(float(r["jitter"]), 1),
            }
            for r in rows
        ],
    }


def mean_pose_predictor(mean_deg: np.ndarray) -> Predictor:
    """The training set's mean angles whatever the input: the floor every model must beat."""
    return lambda x: np.broadcast_to(mean_deg, (len(x), *mean_deg.shape)).copy()


def flat_metrics(summary: dict, prefix: str) -> dict[str, float]:
    keys = ("mae_deg", "sensed_flexion_mae_deg", "offset_free_mae_deg", "jitter_deg_s3")
    out = {f"{prefix}_{k}": summary[k] for k in keys}
    out |= {f"{prefix}_joint_{j}_deg": v for j, v in summary["per_joint"].items()}
    out |= {f"{prefix}_activity_{a}_deg": v["mae_deg"] for a, v in summary["per_activity"].items()}
    return {k: float(v) for k, v in out.items() if np.isfinite(v)}
