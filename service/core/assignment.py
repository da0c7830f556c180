"""Joint sensor-to-segment assignment from per-window class probabilities, and motion detection.

Evidence of a sensor is the sum of log-probabilities over its windows; the one-to-one assignment
maximising the total is ``scipy.optimize.linear_sum_assignment`` (DESIGN.md §5: per-trial joint
assignment is right more often than single windows). ``window_joint_assignment`` applies the same
constraint to each moment on its own: the windows that sensors worn together recorded at the same time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

# A window whose gyroscope norm stays under this mean carries no gait information (DESIGN.md §5).
STILL_GYR_MEAN_RADS = 0.35


def is_moving(windows: np.ndarray) -> np.ndarray:
    """``(N, T, 6)`` → ``(N,)`` bool: mean gyroscope norm above ``STILL_GYR_MEAN_RADS``."""
    return np.linalg.norm(windows[..., 3:6], axis=-1).mean(axis=-1) > STILL_GYR_MEAN_RADS


def turns_about_vertical(windows: np.ndarray, within_deg: float = 45.0) -> np.ndarray:
    """Per window ``(B, T, 6)``: is the dominant rotation axis (top eigenvector of Σ ω ωᵀ) within ``within_deg`` of
    the mean specific force, i.e. does the segment mostly twist or turn about the vertical rather than swing?

    A label-free description of what a window contains: in gait the legs and feet swing about their flexion axis,
    which is horizontal, and the training clips are gait, so a leg or foot window that turns about the vertical is
    outside what the models know. The service returns it per window; ``training.evaluate.evaluate_real`` reports
    the share per recording. (The pelvis turns about the vertical in gait too.)
    """
    if not len(windows):
        return np.zeros(0, dtype=bool)
    up = windows[..., :3].mean(axis=1).astype(np.float64)
    up /= np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-9)  # no specific force (free fall): False
    gyr = windows[..., 3:].astype(np.float64)
    axis = np.linalg.eigh(np.einsum("bti,btj->bij", gyr, gyr))[1][..., -1]
    return np.abs(np.einsum("bi,bi->b", axis, up)) > np.cos(np.radians(within_deg))


@dataclass(frozen=True)
class JointAssignment:
    segment: np.ndarray  # (S,) class index per sensor, -1 if unassigned (more sensors than segments)
    evidence: np.ndarray  # (S, K) summed log-probabilities
    confidence: np.ndarray  # (S,) softmax of the evidence at the chosen class
    margin: np.ndarray  # (S,) evidence of the assigned class minus the best other class (< 0: constraint overrode it)


def joint_assignment(log_probs: list[np.ndarray], allow_shared: bool = False) -> JointAssignment:
    """Assign S sensors (each ``(N_s, K)`` window log-probabilities) to K segments.

    One-to-one by default: with more sensors than segments the weakest are left unassigned (-1);
    with fewer, segments stay empty. ``allow_shared`` lets sensors share a segment (per-sensor argmax).
    """
    evidence = np.stack([lp.sum(axis=0) for lp in log_probs])
    n_sensors, n_classes = evidence.shape
    if allow_shared or n_sensors == 1:  # one sensor: the one-to-one optimum is its own best segment
        segment = evidence.argmax(axis=1)
    else:
        rows, cols = linear_sum_assignment(evidence, maximize=True)
        segment = np.full(n_sensors, -1)
        segment[rows] = cols
    post = np.exp(evidence - evidence.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)
    confidence = np.where(segment >= 0, post[np.arange(n_sensors), np.maximum(segment, 0)], 0.0)
    rows = np.arange(n_sensors)
    chosen = np.maximum(segment, 0)
    others = evidence.copy()
    others[rows, chosen] = -np.inf
    margin = evidence[rows, chosen] - others.max(axis=1) if n_classes > 1 else np.full(n_sensors, np.inf)
    margin = np.where(segment >= 0, margin, 0.0)
    return JointAssignment(segment, evidence, confidence, margin)


def window_joint_assignment(
    log_probs: list[np.ndarray], moving: list[np.ndarray], allow_shared: bool = False
) -> list[np.ndarray]:
    """One-to-one assignment per moment: window ``t`` of every sensor is assigned from those windows alone.

    ``log_probs[s]`` is ``(N_s, K)`` for sensor ``s`` and ``moving[s]`` its ``(N_s,)`` mask (``is_moving``);
    windows with the same index are taken as recorded at the same time. At each index the sensors whose window
    there moves share out the K segments one-to-one (the answer that maximises their summed log-probability);
    a still window, or one left over when more than K windows move, gets -1. Paper 000 classifies every window
    on its own (§2.2) and names the left/right switches that this leaves as future work (§5); the sensors of one
    body cannot sit on the same segment, so at one moment their windows constrain each other. ``allow_shared``
    (as in ``joint_assignment``) gives each moving window its own best class instead.

    Returns one ``(N_s,)`` int array per sensor.
    """
    if allow_shared:
        return [np.where(m, lp.argmax(axis=1), -1) for lp, m in zip(log_probs, moving, strict=True)]
    out = [np.full(len(lp), -1, dtype=np.int64) for lp in log_probs]
    for t in range(max((len(lp) for lp in log_probs), default=0)):
        present = [s for s, lp in enumerate(log_probs) if t < len(lp) and moving[s][t]]
        if not present:
            continue
        evidence = np.stack([log_probs[s][t] for s in present])
        rows, cols = linear_sum_assignment(evidence, maximize=True)
        for r, c in zip(rows, cols, strict=True):
            out[present[r]][t] = c
    return out


class MomentAssembler:
    """``window_joint_assignment`` for a live session, whose sensors' windows arrive one packet at a time.

    A moment is a window end time (seconds on the sensors' shared clock, rounded to the microsecond). Its windows
    wait until every sensor of the session has produced a window at or after that time, then the moment is
    answered from the windows it holds; a sensor that stalls, or never sends, holds up at most ``max_open``
    moments, after which the oldest are answered without it. ``flush`` answers all that wait (end of stream).
    With ``allow_shared`` each moving window keeps its own answer.
    """

    def __init__(self, n_sensors: int, allow_shared: bool = False, max_open: int = 32) -> None:
        self.allow_shared = allow_shared
        self.max_open = max_open
        self.latest = np.full(n_sensors, -np.inf)  # newest window end per sensor
        self.open: dict[float, dict[int, tuple[np.ndarray, bool]]] = {}

    def add(self, sensor: int, end_s: float, log_probs: np.ndarray, moving: bool) -> None:
        """One window of ``sensor``: its ``(K,)`` log-probabilities and whether it moves (``is_moving``)."""
        key = round(end_s, 6)
        self.open.setdefault(key, {})[sensor] = (log_probs, moving)
        self.latest[sensor] = max(self.latest[sensor], key)

    def ready(self) -> list[tuple[float, dict[int, int]]]:
        """The moments every sensor has reached (and the oldest beyond ``max_open``), oldest first:
        (end time, sensor → class index, -1 for a still or left-over window)."""
        horizon = self.latest.min()
        keys = sorted(self.open)
        n_done = sum(k <= horizon for k in keys)
        n_done = max(n_done, len(keys) - self.max_open)
        return [self._answer(k) for k in keys[:n_done]]

    def flush(self) -> list[tuple[float, dict[int, int]]]:
        return [self._answer(k) for k in sorted(self.open)]

    def _answer(self, key: float) -> tuple[float, dict[int, int]]:
        windows = self.open.pop(key)
        sensors = list(windows)
        log_probs = [windows[s][0][None] for s in sensors]
        moving = [np.array([windows[s][1]]) for s in sensors]
        answer = window_joint_assignment(log_probs, moving, self.allow_shared)
        return key, {s: int(a[0]) for s, a in zip(sensors, answer, strict=True)}
