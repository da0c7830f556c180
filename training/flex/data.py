"""Flex datasets from mocap: joint-angle targets and simulated sensor counts at 20 Hz, windows for the networks.

Each clip on the canonical body (``training.pose.data``: every mocap source, one set of segment frames per rig)
is taken to 20 Hz (every third 60 Hz frame; the mocap has next to nothing above 7 Hz), and ``window − 1``
copies of its first frame are put in front: the wearer stands in the clip's first pose for the few seconds the
calibration window needs before the motion starts, so every frame of the clip is answered and scored.
"""

from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass

import numpy as np

from service.core.flex import bend_angles_deg
from service.core.joint_angles import joint_angles_deg
from training.data.catalog import is_bandai_namco
from training.flex.simulate import FLEX_RATE_HZ, SensorParams, draw_suit, simulate_counts
from training.pose.data import MODEL_RATE_HZ, MotionClip

DECIMATE = int(round(MODEL_RATE_HZ / FLEX_RATE_HZ))


@dataclass
class FlexClip:
    path: str
    source: str
    group: str
    activity: str
    angles: np.ndarray  # (T, J, 3) degrees, the first ``pad`` frames a hold of the clip's first pose
    bend: np.ndarray  # (T, S) degrees, what each sensor's strip bends by
    pad: int

    @property
    def frames(self) -> int:
        return len(self.angles) - self.pad


def flex_clip(clip: MotionClip, joints: list[str], sensors: list[str], window: int) -> FlexClip:
    R = clip.motion.R_world_segment[::DECIMATE]
    R = np.concatenate([np.repeat(R[:1], window - 1, axis=0), R])
    return FlexClip(
        clip.path,
        clip.source,
        clip.group,
        clip.activity,
        joint_angles_deg(R, joints).astype(np.float32),
        bend_angles_deg(R, sensors).astype(np.float32),
        window - 1,
    )


def clip_seed(seed: int, path: str, k: int) -> int:
    return int.from_bytes(hashlib.sha256(f"{seed}|{path}|{k}".encode()).digest()[:8], "little")


def clip_suit(seed: int, path: str, k: int, n_sensors: int, **fixed: float) -> tuple[list[SensorParams], int]:
    """The ``k``-th suit of a clip: the same parameters for the same (seed, clip, k) on every machine."""
    s = clip_seed(seed, path, k)
    return draw_suit(np.random.default_rng(s), n_sensors, **fixed), s


@dataclass
class WindowSet:
    """Clips laid end to end: ``counts`` (suits, N, S), ``angles`` (N, J, 3); a window ends at an index of
    ``ends`` (exclusive) and spans ``window`` samples of one clip."""

    counts: np.ndarray
    angles: np.ndarray
    ends: np.ndarray  # (W,) window ends, one per scored frame
    clip_of_end: np.ndarray  # (W,) index into ``clips``
    weights: np.ndarray  # (W,) sampling weight (activity balance), sums to 1
    clips: list[FlexClip]
    window: int

    def batch(self, suit: np.ndarray, ends: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Inputs ``(B, window, S)`` and the targets of their last ``steps`` samples ``(B, steps, J·3)``."""
        idx = ends[:, None] + np.arange(-self.window, 0)[None]
        x = self.counts[suit[:, None], idx]
        y = self.angles[idx[:, -steps:]]
        return x, y.reshape(len(ends), steps, -1)

    def window_angles(self, ends: np.ndarray) -> np.ndarray:
        """The targets of every sample of the windows ending at ``ends``: ``(B, window, J·3)``."""
        idx = ends[:, None] + np.arange(-self.window, 0)[None]
        return self.angles[idx].reshape(len(ends), self.window, -1)


def window_set(
    clips: list[FlexClip],
    n_suits: int,
    seed: int,
    window: int,
    activity_cap_frames: int | None = None,
    counts_fn=None,
    bandai_share: float | None = None,
) -> WindowSet:
    """Simulate ``n_suits`` suits per clip (``counts_fn(clip, k) → (T, S)`` counts overrides the default draw).
    Windows are drawn by frames, less for activities beyond ``activity_cap_frames``; with ``bandai_share``,
    Bandai-Namco's windows together get that share of the draws and the others the rest (as pose's
    ``clip_weights``)."""
    lengths = [len(c.angles) for c in clips]
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)

    def simulated(c: FlexClip, k: int) -> np.ndarray:
        suit, s = clip_suit(seed, c.path, k, c.bend.shape[1])
        return simulate_counts(c.bend, suit, np.random.default_rng(s + 1))

    make = counts_fn or simulated
    counts = np.stack([np.concatenate([make(c, k) for c in clips]) for k in range(n_suits)]).astype(np.float32)
    ends = np.concatenate([starts[i] + np.arange(c.pad + 1, lengths[i] + 1) for i, c in enumerate(clips)])
    clip_of_end = np.concatenate([np.full(c.frames, i) for i, c in enumerate(clips)])
    per_activity = Counter()
    for c in clips:
        per_activity[c.activity] += c.frames
    cap = activity_cap_frames or max(per_activity.values())
    w = np.array([min(1.0, cap / per_activity[clips[i].activity]) for i in clip_of_end])
    if bandai_share is not None:
        bandai = np.array([is_bandai_namco(c.source) for c in clips])[clip_of_end]
        if bandai.any() and (~bandai).any():
            w[bandai] *= bandai_share / w[bandai].sum()
            w[~bandai] *= (1.0 - bandai_share) / w[~bandai].sum()
    return WindowSet(
        counts,
        np.concatenate([c.angles for c in clips]),
        ends,
        clip_of_end,
        w / w.sum(),
        clips,
        window,
    )
