"""Training data for one scenario, selected from every training clip to match a small reference set
(Zheng et al. 2021 §5, eq. 4–13).

Step 1, similar data (§5.2, eq. 5): each clip is cut into units of ``unit_s`` (0.5 s); a unit is similar when its
mean per-frame cosine with some reference unit reaches η0 (0.8); runs of similar units at least one training
sequence long (``min_frames``, 300 frames) form D_B.

Step 2, optimal data (§5.3, eq. 4 and 6–13): starting from D = D_B, the run of eq. 12 (the lowest score on its own)
is deleted, then, again and again, the run whose deletion raises the score most (eq. 13), until no deletion raises
it. The score is eq. 4, f(D) = α H(D) − β d_KL(D, D_ref) − γ log N(D), with per-feature histograms of 20 intervals
between each feature's extremes (eq. 6–10).

The features θ of a frame are the orientations of the segments relative to the pelvis as rotation matrices (eq. 2,
the paper's input format): 20 segments × 9. Each frame's vector has the same norm (√60), so the per-frame cosine of
eq. 5 is the mean over segments of (1 + 2 cos φ) / 3, φ the segment's angle between the two frames: η0 = 0.8 asks
for a mean cos φ of 0.7, poses about 45° apart at most.

Where this departs from the paper: eq. 9 as printed (Σ P log P) is the negative entropy, and maximising it would
favour concentrated data where the text wants "preferably uniformly distributed" data, so H is the entropy
−Σ P log P; α = β = γ = 1 (the paper gives no values); the reference histogram Q gets one count added to every
interval, so that d_KL is finite where the reference has an empty interval. The reference clips are left out of
D_A (they would select themselves) and trained on whole, as §5.1 trains on "the selected training data and
reference data".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from training.pose.data import MotionClip

log = logging.getLogger(__name__)

BINS = 20  # Zheng et al. 2021 §5.3: "20 intervals"


def pose_features(clip: MotionClip) -> np.ndarray:
    """(T, 180): every segment but the pelvis, its rotation relative to the pelvis (eq. 2), row-major."""
    R = clip.motion.R_world_segment
    rel = np.einsum("tji,tsjk->tsik", R[:, 0], R[:, 1:])
    return rel.reshape(len(R), -1).astype(np.float32)


def _units(features: np.ndarray, n: int) -> np.ndarray:
    """(U, n·F): consecutive non-overlapping units of ``n`` frames (a shorter tail is dropped)."""
    u = len(features) // n
    return features[: u * n].reshape(u, -1)


@dataclass(frozen=True)
class Run:
    """Frames [start, stop) of ``clips[clip]``: consecutive similar units, one candidate segment S_k of D_B."""

    clip: int
    start: int
    stop: int

    @property
    def frames(self) -> int:
        return self.stop - self.start


def similar_runs(
    clips: list[MotionClip],
    reference: list[MotionClip],
    unit_frames: int,
    eta0: float,
    min_frames: int,
    chunk: int = 2048,
) -> list[Run]:
    """Step 1 (eq. 5): runs of units whose best cosine with a reference unit is at least ``eta0``."""
    ref = np.concatenate([_units(pose_features(c), unit_frames) for c in reference])
    if not len(ref):
        raise ValueError(f"the reference clips hold no unit of {unit_frames} frames")
    frame_norm2 = float(np.sum(pose_features(reference[0])[0] ** 2))  # 60: 20 rotation matrices of norm √3
    scale = 1.0 / (frame_norm2 * unit_frames)
    runs: list[Run] = []
    for k, c in enumerate(tqdm(clips, desc="similar units", unit="clip", mininterval=5.0)):
        u = _units(pose_features(c), unit_frames)
        if not len(u):
            continue
        best = np.concatenate([(u[i : i + chunk] @ ref.T).max(axis=1) for i in range(0, len(u), chunk)]) * scale
        similar = np.concatenate([[False], best >= eta0, [False]])
        edges = np.flatnonzero(np.diff(similar.astype(np.int8)))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            if (b - a) * unit_frames >= min_frames:
                runs.append(Run(k, int(a) * unit_frames, int(b) * unit_frames))
    return runs


def _histograms(features: np.ndarray, lo: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(F, BINS) counts of each feature over the 20 intervals of eq. 7–8."""
    idx = np.clip(((features - lo) / width).astype(np.int64), 0, BINS - 1)
    F = features.shape[1]
    flat = idx + np.arange(F)[None, :] * BINS
    return np.bincount(flat.ravel(), minlength=F * BINS).reshape(F, BINS).astype(np.float64)


def _xlogx(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x * np.log(np.maximum(x, 1e-300)), 0.0)


@dataclass
class Selection:
    runs: list[Run]  # the selected segments, D
    candidates: list[Run]  # D_B
    trace: list[float]  # f(D) after each deletion, starting with D_B
    reference_frames: int
    kept: list[bool]  # per candidate: in D
    labels: list[str]  # per candidate: "<source>/<activity>" of its clip

    def frames_by_label(self) -> dict[str, tuple[int, int]]:
        """Per source and activity, frames in D_B and in D."""
        out: dict[str, tuple[int, int]] = {}
        for r, keep, label in zip(self.candidates, self.kept, self.labels, strict=True):
            similar, chosen = out.get(label, (0, 0))
            out[label] = (similar + r.frames, chosen + r.frames * keep)
        return out


def score(counts: np.ndarray, n: np.ndarray, log_q: np.ndarray, weights: tuple[float, float, float]) -> np.ndarray:
    """Eq. 4 for histograms ``counts`` (..., F, BINS) of ``n`` frames: α H − β d_KL(P, Q) − γ log N, H and d_KL
    averaged over the features (eq. 6 and 9)."""
    alpha, beta, gamma = weights
    n = np.asarray(n, dtype=np.float64)
    F = counts.shape[-2]
    # with P = C / n: Σ P log P = Σ C log C / n − log n, and Σ P log Q = Σ C log Q / n
    sum_plogp = _xlogx(counts).sum(axis=(-1, -2)) / (n * F) - np.log(n)
    sum_plogq = (counts * log_q).sum(axis=(-1, -2)) / (n * F)
    entropy = -sum_plogp
    kl = sum_plogp - sum_plogq
    return alpha * entropy - beta * kl - gamma * np.log(n)


def greedy_deletion(
    counts: np.ndarray, frames: np.ndarray, log_q: np.ndarray, weights: tuple[float, float, float]
) -> tuple[np.ndarray, list[float]]:
    """Eq. 12, then eq. 13 until no deletion raises the score: which of the segments (histograms ``counts``
    (K, F, BINS), ``frames`` (K,)) stay, and the score after each deletion (the first entry: all of them)."""
    alive = np.ones(len(frames), dtype=bool)
    total, n = counts.sum(axis=0), float(frames.sum())
    trace = [float(score(total, n, log_q, weights))]

    def delete(k: int) -> None:
        nonlocal total, n
        alive[k] = False
        total, n = total - counts[k], n - frames[k]
        trace.append(float(score(total, n, log_q, weights)))

    if len(frames) < 2:
        return alive, trace
    # eq. 12: the first deletion is the segment that scores lowest on its own
    delete(int(np.argmin(score(counts, frames, log_q, weights))))
    while alive.sum() > 1:
        idx = np.flatnonzero(alive)
        after = score(total[None] - counts[idx], n - frames[idx], log_q, weights)  # eq. 13 for every candidate
        best = int(np.argmax(after))
        if after[best] <= trace[-1]:
            break  # a local maximum: no deletion raises f
        delete(int(idx[best]))
    return alive, trace


def select(
    clips: list[MotionClip],
    reference: list[MotionClip],
    unit_frames: int,
    eta0: float,
    min_frames: int,
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0),
    optimise: bool = True,
) -> Selection:
    """Both steps of Zheng et al. 2021 §5 over ``clips`` (D_A) for the ``reference`` clips (D_ref); without
    ``optimise`` step 1 only (every similar run is kept; the trace still holds D_B's score)."""
    candidates = similar_runs(clips, reference, unit_frames, eta0, min_frames)
    ref_features = np.concatenate([pose_features(c) for c in reference])
    if not candidates:
        return Selection([], [], [], len(ref_features), [], [])
    run_features = [pose_features(clips[r.clip])[r.start : r.stop] for r in candidates]
    everything = np.concatenate([ref_features, *run_features])
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    width = np.maximum(hi - lo, 1e-6) / BINS
    q = _histograms(ref_features, lo, width) + 1.0  # add-one: d_KL stays finite (module docstring)
    log_q = np.log(q / q.sum(axis=1, keepdims=True))
    counts = np.stack([_histograms(f, lo, width) for f in run_features])  # (K, F, BINS)
    frames = np.array([r.frames for r in candidates], dtype=np.float64)
    if optimise:
        alive, trace = greedy_deletion(counts, frames, log_q, weights)
    else:
        alive, trace = (
            np.ones(len(frames), dtype=bool),
            [float(score(counts.sum(axis=0), frames.sum(), log_q, weights))],
        )
    chosen = [r for r, keep in zip(candidates, alive, strict=True) if keep]
    log.info(
        "data selection: %d of %d similar runs kept (%d of %d frames), reference %d frames",
        len(chosen),
        len(candidates),
        sum(r.frames for r in chosen),
        int(frames.sum()),
        len(ref_features),
    )
    labels = [f"{clips[r.clip].source}/{clips[r.clip].activity}" for r in candidates]
    return Selection(chosen, candidates, trace, len(ref_features), [bool(k) for k in alive], labels)


def selected_clips(clips: list[MotionClip], runs: list[Run]) -> list[MotionClip]:
    """The selected runs as clips of their own (path ``<clip>#<start>-<stop>``, the clip's digest and labels)."""
    out = []
    for r in runs:
        c = clips[r.clip]
        out.append(
            MotionClip(
                f"{c.path}#{r.start}-{r.stop}",
                c.source,
                c.subject,
                c.activity,
                c.motion.crop(r.start, r.stop),
                c.digest,
            )
        )
    return out
