"""Flex-sensor pose (Chen et al. 2024): the joints it answers, the bend a strip sensor over a joint feels, a
functional knee angle from two IMU orientations, and the per-stream ring buffer. The joint-angle convention is
``service.core.joint_angles``'s."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.body import BODY_SEGMENTS
from service.core.joint_angles import JOINTS

# The joints of Chen et al. 2024 Table 3 that the canonical body has (``service.core.joint_angles.JOINTS``).
FLEX_JOINTS: tuple[str, ...] = (
    "LumbarSpine",
    "ThoracicSpine",
    "LeftSternoclavicular",
    "RightSternoclavicular",
    "LeftShoulder",
    "RightShoulder",
    "LeftElbow",
    "RightElbow",
    "LeftHip",
    "RightHip",
    "LeftKnee",
    "RightKnee",
)

# What the hinge frames (``limb_twist`` "hinge": each limb's turn about its long axis taken from its hinge,
# docs/pose.md "Hinge frames") hold at zero in the mocap: the knee is a hinge about y in every rig (within 0.7°), so
# its abduction and rotation; the forearm's long axis lies in the upper arm's x-z plane (CMU's rigs exactly,
# Bandai-Namco's within 6°), so the elbow's abduction. The elbow's rotation, the forearm's pronation, is left: a real
# forearm has it. A model in these frames answers them as zero (docs/flex.md "The hinges' zeros").
HINGE_ZEROS: dict[str, tuple[str, ...]] = {
    "LeftKnee": ("abduction", "rotation"),
    "RightKnee": ("abduction", "rotation"),
    "LeftElbow": ("abduction",),
    "RightElbow": ("abduction",),
}


def answer_mask(
    limb_twist: str | None, joints: list[str] | tuple[str, ...], components: list[str] | tuple[str, ...]
) -> np.ndarray | None:
    """What a model in the segment frames ``limb_twist`` (its manifest's or config's) is answered through:
    ``hinge_mask`` in the hinge frames, else None (its answer as it is)."""
    return hinge_mask(joints, components) if limb_twist == "hinge" else None


def hinge_mask(joints: list[str] | tuple[str, ...], components: list[str] | tuple[str, ...]) -> np.ndarray:
    """``(J, C)`` float32 factors for a model's answer: 0 where ``HINGE_ZEROS`` holds the angle at zero, else 1."""
    mask = np.ones((len(joints), len(components)), np.float32)
    for j, joint in enumerate(joints):
        for c, component in enumerate(components):
            if component in HINGE_ZEROS.get(joint, ()):
                mask[j, c] = 0.0
    return mask


# Four resistive strips, over both knees and both elbows (Chen et al. 2024 §3.2), in channel order.
FLEX_SENSOR_JOINTS: tuple[str, ...] = ("LeftKnee", "RightKnee", "LeftElbow", "RightElbow")


def bend_angles_deg(R_world_segment: np.ndarray, joints: list[str] | tuple[str, ...]) -> np.ndarray:
    """``(T, 21, 3, 3)`` → ``(T, J)`` the angle between the parent's and the child's long (z) axes in degrees:
    what a strip glued along both segments bends by, whatever the plane of the bend."""
    out = np.empty((*R_world_segment.shape[:-3], len(joints)))
    for k, name in enumerate(joints):
        joint = JOINTS[name]
        p, c = BODY_SEGMENTS.index(joint.parent), BODY_SEGMENTS.index(joint.child)
        cos = np.einsum("...i,...i->...", R_world_segment[..., p, :, 2], R_world_segment[..., c, :, 2])
        out[..., k] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


@dataclass(frozen=True)
class HingeCalibration:
    """A knee's functional frame, fitted from one recording and reused for others of the same session."""

    R_ref: np.ndarray  # (3, 3) relative sensor rotation taken as the reference posture
    axis: np.ndarray  # (3,) hinge axis in the proximal sensor's frame
    zero_deg: float  # the angle taken as full extension


def _relative_sensor(q_proximal: np.ndarray, q_distal: np.ndarray) -> Rotation:
    return Rotation.from_quat(q_proximal, scalar_first=True).inv() * Rotation.from_quat(q_distal, scalar_first=True)


def fit_hinge(q_proximal: np.ndarray, q_distal: np.ndarray, extension_percentile: float = 2.0) -> HingeCalibration:
    """Fit a hinge joint from the orientations (w, x, y, z, any common world) of a sensor on each side of it.

    The relative rotation of the distal sensor in the proximal sensor's frame moves, for a hinge, about one
    axis: the first principal axis of its rotation vectors about their mean is the hinge axis (a functional
    axis, as Seel et al. 2014 fit knee axes from gyroscopes). The sign makes the larger excursion positive
    (flexion in gait), and ``extension_percentile`` of the angles is taken as zero (full extension), so no
    mounting or static pose needs to be known.
    """
    rel = _relative_sensor(q_proximal, q_distal)
    R_ref = rel.mean()
    axis, angle = _principal_hinge((R_ref.inv() * rel).as_rotvec())
    return HingeCalibration(R_ref.as_matrix(), axis, float(np.degrees(np.percentile(angle, extension_percentile))))


def _principal_hinge(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors ``(T, 3)`` of a hinge's relative rotation against a reference → its axis (the first
    principal axis of the vectors about their mean, signed so that the larger excursion is positive: flexion) and
    each vector's angle along it (radians)."""
    axis = np.linalg.svd(v - v.mean(axis=0), full_matrices=False)[2][0]
    angle = v @ axis
    med = np.median(angle)
    if np.percentile(angle, 99) - med < med - np.percentile(angle, 1):
        axis, angle = -axis, -angle
    return axis, angle


def hinge_in_proximal(R_proximal: np.ndarray, R_distal: np.ndarray) -> tuple[np.ndarray, float]:
    """The hinge axis of a joint in the proximal segment's frame, from both segments' world orientations ``(T, 3,
    3)``, as ``fit_hinge`` finds it (the relative rotation composed on the left of its mean, so that the axis is the
    proximal frame's); and its range of motion (degrees, 1st to 99th percentile)."""
    rel = Rotation.from_matrix(np.einsum("tji,tjk->tik", R_proximal, R_distal))
    axis, angle = _principal_hinge((rel * rel.mean().inv()).as_rotvec())
    return axis, float(np.degrees(np.percentile(angle, 99) - np.percentile(angle, 1)))


def azimuth_elevation_deg(axis: np.ndarray) -> tuple[float, float]:
    """How far a hinge axis lies from the frame's y: its turn about z from ±y (positive anticlockwise seen from
    above, the sign of y taken so that the axis points left) and its elevation out of the x-y plane."""
    a = axis if axis[1] >= 0 else -axis
    return float(np.degrees(np.arctan2(-a[0], a[1]))), float(np.degrees(np.arcsin(np.clip(a[2], -1.0, 1.0))))


def hinge_angle_deg(q_proximal: np.ndarray, q_distal: np.ndarray, cal: HingeCalibration) -> np.ndarray:
    """The flexion (degrees, positive flexed) of a hinge fitted by ``fit_hinge``: the rotation vector of the
    relative sensor rotation against the reference posture, projected onto the hinge axis."""
    rel = _relative_sensor(q_proximal, q_distal)
    v = (Rotation.from_matrix(cal.R_ref).inv() * rel).as_rotvec()
    return np.degrees(v @ cal.axis) - cal.zero_deg


class FlexWindow:
    """The last ``window`` rows of one stream's channels: the state a flex model's dynamic calibration needs
    (Chen et al. 2024 eq. 2 works on the last 100 samples), kept per session."""

    def __init__(self, window: int, channels: int) -> None:
        self.window = window
        self.channels = channels
        self._rows: deque[np.ndarray] = deque(maxlen=window)

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def full(self) -> bool:
        return len(self._rows) == self.window

    def push(self, rows: np.ndarray) -> list[np.ndarray]:
        """Append ``(n, C)`` rows; the model inputs ``(window, C)`` that became complete, one per row once the
        buffer is full, oldest first."""
        out = []
        for row in rows:
            self._rows.append(np.asarray(row, np.float32))
            if self.full:
                out.append(np.stack(self._rows))
        return out


def block_windows(x: np.ndarray, window: int, hop: int = 1) -> np.ndarray:
    """``(T, C)`` → ``(n, window, C)`` every ``hop`` samples, the last ending at the block's last sample."""
    T = len(x)
    if T < window:
        raise ValueError(f"{T} samples, fewer than the window of {window}")
    ends = np.arange(T, window - 1, -hop)[::-1]
    return np.stack([x[e - window : e] for e in ends])


@dataclass(frozen=True)
class ReadoutFailure:
    row: int
    channel: int
    value: float
    reference: float


class ReadoutCheck:
    """A sensor read-out that has failed: a channel off its reference, the median of its first ``reference_s``
    seconds, by more than ``max_deviation`` of that reference (or not finite). On Sub01's sleeves the healthy
    channels stay within 11 % of it over a minute; its right sleeve, failing at 39.7 s of the baseline trial, passes
    50 % within two readings and climbs to 1e6-1e8 (``service.core.recordings.read_capacitive_sleeve``). One
    reference per stream: until ``reference_s`` of readings have come, the median of those so far."""

    def __init__(self, rate_hz: float, reference_s: float, max_deviation: float) -> None:
        self.reference_rows = max(1, int(round(reference_s * rate_hz)))
        self.max_deviation = max_deviation
        self._first: list[np.ndarray] = []
        self._seen = 0
        self.reference: np.ndarray | None = None

    def first_failure(self, rows: np.ndarray) -> ReadoutFailure | None:
        """The first failed reading of ``(n, C)`` rows, the next of the stream; ``None`` when all are healthy."""
        rows = np.asarray(rows, np.float64)
        if self.reference is None:
            take = rows[: self.reference_rows - self._seen]
            self._first.append(take)
            self._seen += len(take)
            first = np.concatenate(self._first)
            reference = np.median(first, axis=0)
            if self._seen >= self.reference_rows:
                self.reference, self._first = reference, []
        else:
            reference = self.reference
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(rows) | (np.abs(rows - reference) > self.max_deviation * np.abs(reference))
        if not bad.any():
            return None
        row, channel = np.argwhere(bad)[0]
        return ReadoutFailure(int(row), int(channel), float(rows[row, channel]), float(reference[channel]))
