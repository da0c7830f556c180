"""Evaluation metrics of Zimmermann et al. 2018 §3.3."""

from __future__ import annotations

import numpy as np

from service.core.rotations import error_angles_xyz_deg
from service.core.segments import BODY_PART, SEGMENTS


def confusion_matrix(y_true: np.ndarray, y_pred: np.ndarray, n_classes: int = len(SEGMENTS)) -> np.ndarray:
    """Counts ``(n_classes, n_classes)``, rows true, columns predicted."""
    cm = np.zeros((n_classes, n_classes), dtype=np.int64)
    np.add.at(cm, (y_true, y_pred), 1)
    return cm


def assignment_metrics(y_true: np.ndarray, y_pred: np.ndarray) -> dict[str, float]:
    """Accuracy, per-class precision / recall / F1 (eq. 9–11), and accuracy ignoring left/right.

    F1 is the usual harmonic mean 2PR/(P+R); the paper's eq. 11 prints it without the factor 2 and
    eq. 10 has a typo in the recall denominator (TP + FN is meant).
    """
    cm = confusion_matrix(y_true, y_pred)
    tp = np.diag(cm).astype(np.float64)
    precision = tp / np.maximum(cm.sum(axis=0), 1)
    recall = tp / np.maximum(cm.sum(axis=1), 1)
    f1 = 2 * precision * recall / np.maximum(precision + recall, 1e-12)
    part = np.array(BODY_PART)
    out = {
        "accuracy": float(np.mean(y_true == y_pred)),
        "accuracy_ignoring_side": float(np.mean(part[y_true] == part[y_pred])),
        "macro_f1": float(np.mean(f1)),
        "n_windows": float(len(y_true)),
    }
    for k, name in enumerate(SEGMENTS):
        out[f"precision_{name}"], out[f"recall_{name}"], out[f"f1_{name}"] = precision[k], recall[k], f1[k]
    return {k: float(v) for k, v in out.items()}


def alignment_metrics(
    segment: np.ndarray, q_true: np.ndarray, q_pred: np.ndarray
) -> tuple[dict[str, float], np.ndarray]:
    """Table A10 layout: median / mean / max absolute XYZ error angle per segment and axis.

    Returns the metrics and the per-window error angles ``(N, 3)`` in degrees.
    """
    err = error_angles_xyz_deg(q_true, q_pred)
    out: dict[str, float] = {}
    for k, name in enumerate(SEGMENTS):
        e = err[segment == k]
        if len(e) == 0:
            continue
        for ax in range(3):
            out[f"{name}_ax{ax}_median_deg"] = float(np.median(e[:, ax]))
            out[f"{name}_ax{ax}_mean_deg"] = float(np.mean(e[:, ax]))
            out[f"{name}_ax{ax}_max_deg"] = float(np.max(e[:, ax]))
    out["mean_angle_error_deg"] = float(np.mean(err))
    out["median_angle_error_deg"] = float(np.median(err))
    out["max_angle_error_deg"] = float(np.max(err))
    return out, err
