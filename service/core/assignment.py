"""Joint sensor-to-segment assignment from per-window class probabilities, and motion detection.

Evidence of a sensor is the sum of log-probabilities over its windows; the one-to-one assignment
maximising the total is ``scipy.optimize.linear_sum_assignment`` (DESIGN.md §5: per-trial joint
assignment is right more often than single windows). ``window_joint_assignment`` applies the same
constraint to each moment on its own: the windows that sensors worn together recorded at the same time.

Both take ``worn``, the segments a user declares the sensors to be on (say both feet, not saying which is
which): the answers are then drawn from those segments only. That is the assignment conditioned on the
declaration: renormalising each window's probabilities over the declared segments adds a per-sensor constant to
every candidate's evidence, which changes neither the one-to-one optimum nor the margins, so restricting the
columns is enough.
"""

from __future__ import annotations

from collections.abc import Sequence
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


def worn_classes(worn: Sequence[int] | None, n_classes: int) -> np.ndarray:
    """The declared segments as sorted class indices (all ``n_classes`` when ``worn`` is None)."""
    if worn is None:
        return np.arange(n_classes)
    classes = np.asarray(sorted(worn), dtype=np.int64)
    if not len(classes) or len(set(classes.tolist())) != len(classes) or classes[0] < 0 or classes[-1] >= n_classes:
        raise ValueError(f"worn must be distinct class indices in [0, {n_classes}), at least one; got {list(worn)}")
    return classes


def _best(evidence: np.ndarray, classes: np.ndarray, allow_shared: bool) -> np.ndarray:
    """Per row of ``evidence`` ``(S, K)``, its class among ``classes``: the one-to-one optimum of the summed
    evidence (-1 for rows left over when there are more rows than classes), or each row's own best."""
    among = evidence[:, classes]
    if allow_shared or len(evidence) == 1:  # one row: the one-to-one optimum is its own best class
        return classes[among.argmax(axis=1)]
    rows, cols = linear_sum_assignment(among, maximize=True)
    segment = np.full(len(evidence), -1, dtype=np.int64)
    segment[rows] = classes[cols]
    return segment


def joint_assignment(
    log_probs: list[np.ndarray], allow_shared: bool = False, worn: Sequence[int] | None = None
) -> JointAssignment:
    """Assign S sensors (each ``(N_s, K)`` window log-probabilities) to K segments, or to the ``worn`` ones.

    One-to-one by default: with more sensors than segments the weakest are left unassigned (-1);
    with fewer, segments stay empty. ``allow_shared`` lets sensors share a segment (per-sensor argmax).
    With ``worn``, the evidence of the other segments is -inf and confidence and margin are over the worn ones.
    """
    evidence = np.stack([lp.sum(axis=0) for lp in log_probs])
    n_sensors, n_classes = evidence.shape
    classes = worn_classes(worn, n_classes)
    evidence[:, np.setdiff1d(np.arange(n_classes), classes)] = -np.inf
    segment = _best(evidence, classes, allow_shared)
    rows, chosen = np.arange(n_sensors), np.maximum(segment, 0)
    post = np.exp(evidence - evidence[:, classes].max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)
    confidence = np.where(segment >= 0, post[rows, chosen], 0.0)
    others = evidence.copy()
    others[rows, chosen] = -np.inf
    margin = evidence[rows, chosen] - others.max(axis=1) if len(classes) > 1 else np.full(n_sensors, np.inf)
    margin = np.where(segment >= 0, margin, 0.0)
    return JointAssignment(segment, evidence, confidence, margin)


def window_joint_assignment(
    log_probs: list[np.ndarray],
    moving: list[np.ndarray],
    allow_shared: bool = False,
    worn: Sequence[int] | None = None,
) -> list[np.ndarray]:
    """One-to-one assignment per moment: window ``t`` of every sensor is assigned from those windows alone.

    ``log_probs[s]`` is ``(N_s, K)`` for sensor ``s`` and ``moving[s]`` its ``(N_s,)`` mask (``is_moving``);
    windows with the same index are taken as recorded at the same time. At each index the sensors whose window
    there moves share out the K segments (or the ``worn`` ones) one-to-one (the answer that maximises their
    summed log-probability); a still window, or one left over when more windows move than there are segments,
    gets -1. Paper 000 classifies every window on its own (§2.2) and names the left/right switches that this
    leaves as future work (§5); the sensors of one body cannot sit on the same segment, so at one moment their
    windows constrain each other. ``allow_shared`` (as in ``joint_assignment``) gives each moving window its own
    best class instead.

    Returns one ``(N_s,)`` int array per sensor.
    """
    classes = worn_classes(worn, log_probs[0].shape[1]) if log_probs else np.zeros(0, dtype=np.int64)
    if allow_shared:
        return [
            np.where(m, classes[lp[:, classes].argmax(axis=1)], -1) for lp, m in zip(log_probs, moving, strict=True)
        ]
    out = [np.full(len(lp), -1, dtype=np.int64) for lp in log_probs]
    for t in range(max((len(lp) for lp in log_probs), default=0)):
        present = [s for s, lp in enumerate(log_probs) if t < len(lp) and moving[s][t]]
        if not present:
            continue
        answer = _best(np.stack([log_probs[s][t] for s in present]), classes, allow_shared=False)
        for s, c in zip(present, answer.tolist(), strict=True):
            out[s][t] = c
    return out


class MomentAssembler:
    """``window_joint_assignment`` for a live session, whose sensors' windows arrive one packet at a time.

    A moment is a window end time (seconds on the sensors' shared clock, rounded to the microsecond). Its windows
    wait until every sensor of the session has produced a window at or after that time, then the moment is
    answered from the windows it holds; a sensor that stalls, or never sends, holds up at most ``max_open``
    moments, after which the oldest are answered without it. ``flush`` answers all that wait (end of stream).
    With ``allow_shared`` each moving window keeps its own answer; with ``worn`` the answers are drawn from those
    segments only.
    """

    def __init__(
        self, n_sensors: int, allow_shared: bool = False, max_open: int = 32, worn: Sequence[int] | None = None
    ) -> None:
        self.allow_shared = allow_shared
        self.worn = None if worn is None else tuple(worn)
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
        answer = window_joint_assignment(log_probs, moving, self.allow_shared, self.worn)
        return key, {s: int(a[0]) for s, a in zip(sensors, answer, strict=True)}
