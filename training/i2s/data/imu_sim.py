"""IMU simulation from segment trajectories, Zimmermann et al. 2018 §2.3–2.4.

Pipeline per clip (``segment_kinematics``): zero-lag Butterworth (order 8, 10 Hz) on the segment
trajectories, resampling to 60 Hz, numerical differentiation to linear and angular velocity and
acceleration, all expressed in the segment frame. These per-segment quantities are what the cache
stores; the readings of a sensor with alignment R_SI (eq. 8) and position offset r follow cheaply:

    acc_I = R_SIᵀ (a_S + α_S × r + ω_S × (ω_S × r) + up_S),   gyr_I = R_SIᵀ ω_S,

where up_S = R_WSᵀ (0, 0, 9.81) is the specific force of gravity (a resting sensor reads +9.81 along
world up). Quantisation mimics the Xsens MTw Awinda of Zimmermann et al. 2018 [57] (``SensorSpec``); the
accelerometer gets zero-mean Gaussian noise of variance 1 m²/s⁴ (§2.4.2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation

from service.core.kinematics import body_angular_velocity
from service.core.skeleton import FOOT_AXIS_IN_SEGMENT, SegmentTrajectories, resample_segments
from service.core.units import GRAVITY_MPS2


@dataclass(frozen=True)
class SensorSpec:
    """Range and resolution of the mimicked sensor: Xsens MTw Awinda (±16 g, ±2000 °/s, 16 bit)."""

    acc_range_mps2: float = 160.0
    gyr_range_rads: float = float(np.radians(2000.0))
    bits: int = 16


@dataclass(frozen=True)
class SegmentKinematics:
    """Segment-frame kinematics of one clip at ``sample_rate_hz``; arrays ``(T, 7, 3)``.

    lin_acc_mps2: acceleration of the segment midpoint; up_mps2: gravity's specific force;
    gyr_rads: angular velocity; ang_acc_rads2: angular acceleration; all in the segment frame.
    R_world_segment: (T, 7, 3, 3), the filtered orientations.
    """

    lin_acc_mps2: np.ndarray
    up_mps2: np.ndarray
    gyr_rads: np.ndarray
    ang_acc_rads2: np.ndarray
    R_world_segment: np.ndarray
    sample_rate_hz: float


def _continuous_quats(R: np.ndarray) -> np.ndarray:
    """Quaternions ``(T, 4)`` of ``(T, 3, 3)`` with signs chosen continuous in time."""
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    flips = np.cumsum(np.r_[0, np.sum(q[1:] * q[:-1], axis=1) < 0]) % 2
    return np.where(flips[:, None] == 1, -q, q)


class ClipTooShort(ValueError):
    """A clip too short for the zero-lag filter (some Bandai-Namco clips last under a second); it would hold no
    model window either."""


def lowpass_segments(traj: SegmentTrajectories, cutoff_hz: float = 10.0, order: int = 8) -> SegmentTrajectories:
    """Zero-lag Butterworth on positions and (sign-continuous) quaternions, Zimmermann et al. 2018 §2.4.2."""
    sos = butter(order, cutoff_hz, fs=traj.sample_rate_hz, output="sos")
    pad = 3 * (2 * len(sos) + 1)  # sosfiltfilt's default edge padding, which needs more frames than it pads
    if len(traj.R_world_segment) <= pad:
        raise ClipTooShort(f"{len(traj.R_world_segment)} frames; the order-{order} zero-lag filter needs over {pad}")
    R = np.empty_like(traj.R_world_segment)
    for s in range(traj.R_world_segment.shape[1]):
        q = sosfiltfilt(sos, _continuous_quats(traj.R_world_segment[:, s]), axis=0)
        R[:, s] = Rotation.from_quat(q, scalar_first=True).as_matrix()
    return SegmentTrajectories(
        R, sosfiltfilt(sos, traj.origin_m, axis=0), sosfiltfilt(sos, traj.midpoint_m, axis=0), traj.sample_rate_hz
    )


def segment_kinematics(
    traj: SegmentTrajectories, sample_rate_hz: float = 60.0, cutoff_hz: float = 10.0, order: int = 8
) -> SegmentKinematics:
    """Filtered, resampled, differentiated segment kinematics of one clip."""
    filtered = resample_segments(lowpass_segments(traj, cutoff_hz, order), sample_rate_hz)
    R = filtered.R_world_segment
    dt = 1.0 / sample_rate_hz
    acc_world = np.gradient(np.gradient(filtered.midpoint_m, dt, axis=0), dt, axis=0)
    up_world = np.array([0.0, 0.0, GRAVITY_MPS2])
    gyr = np.stack([body_angular_velocity(R[:, s], sample_rate_hz) for s in range(R.shape[1])], axis=1)
    return SegmentKinematics(
        lin_acc_mps2=np.einsum("tsji,tsj->tsi", R, acc_world),
        up_mps2=np.einsum("tsji,j->tsi", R, up_world),
        gyr_rads=gyr,
        ang_acc_rads2=np.gradient(gyr, dt, axis=0),
        R_world_segment=R,
        sample_rate_hz=sample_rate_hz,
    )


# Reflection through the sagittal plane (x–z) of every segment frame: y → −y.
_SAGITTAL = np.array([1.0, -1.0, 1.0])


def mirrored(kin: SegmentKinematics) -> SegmentKinematics:
    """The same clip performed by the mirror-image body: left and right legs swap (our addition, not Zimmermann et al.
    2018).

    Reflecting the whole scene through a vertical plane M = diag(1, −1, 1) is a valid motion under gravity,
    and turns each left segment into a right one whose frame (x anterior, y left, z up) is R' = M R M. In
    segment coordinates a polar vector (acceleration, gravity) maps to M v and an axial one (angular velocity
    and acceleration) to −M ω. Classes swap k ↔ 6 − k (``SEGMENTS`` is symmetric about the pelvis).
    """
    swap = np.arange(kin.gyr_rads.shape[1])[::-1]
    M = np.diag(_SAGITTAL)
    return SegmentKinematics(
        lin_acc_mps2=kin.lin_acc_mps2[:, swap] * _SAGITTAL,
        up_mps2=kin.up_mps2[:, swap] * _SAGITTAL,
        gyr_rads=-kin.gyr_rads[:, swap] * _SAGITTAL,
        ang_acc_rads2=-kin.ang_acc_rads2[:, swap] * _SAGITTAL,
        R_world_segment=M @ kin.R_world_segment[:, swap] @ M,
        sample_rate_hz=kin.sample_rate_hz,
    )


# A sensor frame reflected through its own x–z plane: the mirror-image body's sensor (``mirrored_readings``).
_SENSOR_MIRROR = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])


def mirrored_readings(imu: np.ndarray) -> np.ndarray:
    """Readings ``(..., 6)`` (accelerometer, gyroscope) as the mirror-image body's sensor reads them (our addition,
    not Zimmermann et al. 2018): what ``mirrored`` does to a clip, done to recorded windows whose segment motion is
    unknown.

    A sensor mounted R on a segment that moves with specific force a and angular velocity ω (segment frame) reads
    Rᵀa and Rᵀω. The mirror-image body (``mirrored``) moves the other side's segment with M a and −M ω; a sensor
    mounted there as M R S (S = diag(1, −1, 1) reflects the sensor's own y axis, so that M R S is a rotation) reads
    S Rᵀ a and −S Rᵀ ω: the accelerometer's y and the gyroscope's x and z change sign. Since the mounting is
    unknown anyway, these readings are a valid recording of the other side's segment (label k ↔ 6 − k).
    """
    return imu * _SENSOR_MIRROR


# Foot, shank and thigh of each leg, in ``SEGMENTS`` order.
LEG_CHAIN = {"left": (0, 1, 2), "right": (6, 5, 4)}


def stiffened_knee(traj: SegmentTrajectories, side: str, keep: float) -> SegmentTrajectories:
    """The clip with one knee braced: only ``keep`` (0–1) of its flexion is left (our addition, not Zimmermann et al.
    2018).

    Rehabilitation users walk with braced or stiff knees (the capacitive data set's ``walk_stiffknee`` trials);
    no CMU clip shows it. The shank's rotation relative to the thigh is scaled along its geodesic,
    R_shank' = R_thigh · exp(keep · log(R_thighᵀ R_shank)), about the knee, and the foot is carried rigidly
    with the shank. The pelvis, the thigh and the other leg are untouched, so each sensor's motion is
    self-consistent while the body's contact with the ground is not (no hip hiking or circumduction: the
    swing foot may pass below the floor).
    """
    if side not in LEG_CHAIN:
        raise ValueError(f"side must be one of {sorted(LEG_CHAIN)}, got {side!r}")
    if not 0.0 <= keep <= 1.0:
        raise ValueError(f"keep must be in [0, 1], got {keep}")
    foot, shank, thigh = LEG_CHAIN[side]
    R, origin, mid = traj.R_world_segment.copy(), traj.origin_m.copy(), traj.midpoint_m.copy()
    relative = np.einsum("tji,tjk->tik", R[:, thigh], R[:, shank])
    scaled = Rotation.from_rotvec(keep * Rotation.from_matrix(relative).as_rotvec()).as_matrix()
    new_shank = R[:, thigh] @ scaled
    turn = new_shank @ np.transpose(R[:, shank], (0, 2, 1))  # world-frame change of the shank's orientation
    knee = origin[:, shank]
    for points in (mid[:, shank], origin[:, foot], mid[:, foot]):
        points[:] = knee + np.einsum("tij,tj->ti", turn, points - knee)
    R[:, shank], R[:, foot] = new_shank, turn @ R[:, foot]
    return SegmentTrajectories(R, origin, mid, traj.sample_rate_hz)


# ---- alignments, eq. 8 ------------------------------------------------------------------------------


def _axis(v: np.ndarray | list[float]) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


# Rotation axis a of eq. 8 per class: z for the legs, y for the pelvis, (0.9, 0, -0.4) for the feet.
ALIGNMENT_AXES = np.stack(
    [
        FOOT_AXIS_IN_SEGMENT,
        _axis([0, 0, 1]),
        _axis([0, 0, 1]),
        _axis([0, 1, 0]),
        _axis([0, 0, 1]),
        _axis([0, 0, 1]),
        FOOT_AXIS_IN_SEGMENT,
    ]
)


def _base_alignment(segment: int) -> np.ndarray:
    """Initial R_SI of eq. 8: sensor z on the outward surface normal, sensor x along the axis a.

    Legs: on the front (z_I = x_S), x_I = z_S. Pelvis: on the back (z_I = -x_S), x_I = z_S.
    Feet: on the dorsum, z_I ⊥ a in the sagittal plane, x_I = a.
    """
    if segment == 3:
        x_i, z_i = np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.0, 0.0])
    elif segment in (0, 6):
        a = FOOT_AXIS_IN_SEGMENT
        x_i, z_i = a, np.array([-a[2], 0.0, a[0]])
    else:
        x_i, z_i = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    return np.stack([x_i, np.cross(z_i, x_i), z_i], axis=1)


def alignment(segment: int, theta1_rad: np.ndarray, theta2_rad: np.ndarray) -> np.ndarray:
    """Eq. 8: R̂_SI = R_a(θ₂) · R_SI · R_z(θ₁), vectorised over angles; returns ``(N, 3, 3)``."""
    theta1_rad, theta2_rad = np.atleast_1d(theta1_rad), np.atleast_1d(theta2_rad)
    R_a = Rotation.from_rotvec(theta2_rad[:, None] * ALIGNMENT_AXES[segment]).as_matrix()
    R_z = Rotation.from_rotvec(theta1_rad[:, None] * np.array([0.0, 0.0, 1.0])).as_matrix()
    return R_a @ _base_alignment(segment) @ R_z


def alignment_grid(segment: int, n_angles: int = 8) -> np.ndarray:
    """The N = n_angles² alignment variations of eq. 8 (paper: {0°, 45°, …, 315°}, N = 64)."""
    angles = np.arange(n_angles) * 2.0 * np.pi / n_angles
    t1, t2 = np.meshgrid(angles, angles, indexing="ij")
    return alignment(segment, t1.ravel(), t2.ravel())


# ---- readings ---------------------------------------------------------------------------------------


def imu_readings(
    lin_acc: np.ndarray,
    up: np.ndarray,
    gyr: np.ndarray,
    ang_acc: np.ndarray,
    R_segment_imu: np.ndarray,
    offset_m: np.ndarray | None = None,
) -> np.ndarray:
    """Ideal readings ``(B, T, 6)`` of sensors with alignments ``(B, 3, 3)`` on segment windows ``(B, T, 3)``.

    ``offset_m`` ``(B, 3)`` moves the sensor from the segment midpoint (segment frame), adding the
    tangential and centripetal terms α × r + ω × (ω × r).
    """
    acc_s = lin_acc + up
    if offset_m is not None:
        r = np.broadcast_to(offset_m[:, None, :], lin_acc.shape)
        acc_s = acc_s + np.cross(ang_acc, r) + np.cross(gyr, np.cross(gyr, r))
    acc_i = np.einsum("bji,btj->bti", R_segment_imu, acc_s)
    gyr_i = np.einsum("bji,btj->bti", R_segment_imu, gyr)
    return np.concatenate([acc_i, gyr_i], axis=-1)


# ---- soft-tissue artefact (our addition, not in Zimmermann et al. 2018) --------------------------------------------

# Share of the configured artefact each segment gets: skin and muscle move most over the thigh, less over the
# shank and pelvis, least over the foot (the pattern of the soft-tissue-artefact literature, e.g. Leardini et al.
# 2005, Gait & Posture 21, the review of soft-tissue artefacts: the thigh's is the largest of the lower limb).
# Class order of ``SEGMENTS``.
SOFT_TISSUE_SHARE = np.array([0.3, 0.6, 1.0, 0.6, 1.0, 0.6, 0.3])


@dataclass(frozen=True)
class SoftTissue:
    """One soft-tissue artefact per window: the sensor rides on tissue that a second-order resonance (natural
    frequency ``freq_hz``, damping ratio ``damping``) couples to the segment's own accelerations, mixed by a random
    ``mix`` ``(B, 6, 6)`` from (linear, angular) acceleration to (rotation, displacement) of the sensor on the
    segment; ``rot_rms_rad`` and ``disp_rms_m`` set each window's root-mean-square rotation and displacement."""

    freq_hz: np.ndarray  # (B,)
    damping: np.ndarray  # (B,)
    mix: np.ndarray  # (B, 6, 6)
    rot_rms_rad: np.ndarray  # (B,)
    disp_rms_m: np.ndarray  # (B,)


def soft_tissue_motion(
    lin_acc: np.ndarray, ang_acc: np.ndarray, sta: SoftTissue, rate_hz: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sensor's small rotation θ ``(B, T, 3)`` (rad), its rate θ̇ and its extra acceleration ü ``(B, T, 3)``
    relative to the segment (segment frame), driven by the segment's accelerations ``(B, T, 3)``.

    Each drive channel is scaled to unit RMS, mixed, and filtered by H(f) = f₀² / (f₀² − f² + 2iζf₀f) in the
    frequency domain (the window and its mirror image, so that the circular transform sees no jump); the time
    derivatives are the same filter times 2πif. θ and u are then scaled to the window's RMS targets.
    """
    drive = np.concatenate([lin_acc, ang_acc], axis=-1)
    drive = drive - drive.mean(axis=1, keepdims=True)
    drive = drive / (np.sqrt(np.mean(drive**2, axis=1, keepdims=True)) + 1e-9)
    mixed = np.einsum("bij,btj->bti", sta.mix, drive)
    n = mixed.shape[1]
    spectrum = np.fft.rfft(np.concatenate([mixed, mixed[:, ::-1]], axis=1), axis=1)
    f = np.fft.rfftfreq(2 * n, 1.0 / rate_hz)[None, :, None]
    f0, zeta = sta.freq_hz[:, None, None], sta.damping[:, None, None]
    response = spectrum * f0**2 / (f0**2 - f**2 + 2j * zeta * f0 * f)
    omega = 2j * np.pi * f

    def back(x: np.ndarray) -> np.ndarray:
        return np.fft.irfft(x, n=2 * n, axis=1)[:, :n]

    pos, vel, acc = back(response), back(response * omega), back(response * omega**2)

    def scale(x: np.ndarray, target: np.ndarray) -> np.ndarray:
        return target[:, None, None] / (np.sqrt(np.mean(np.sum(x**2, axis=-1), axis=1))[:, None, None] + 1e-12)

    k_rot, k_disp = scale(pos[..., :3], sta.rot_rms_rad), scale(pos[..., 3:], sta.disp_rms_m)
    return pos[..., :3] * k_rot, vel[..., :3] * k_rot, acc[..., 3:] * k_disp


def with_soft_tissue(
    acc_s: np.ndarray, gyr_s: np.ndarray, theta: np.ndarray, theta_rate: np.ndarray, u_acc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Segment-frame readings ``(B, T, 3)`` of a sensor that turns by θ(t) and moves by u(t) on its segment:
    the frame of the readings is exp(θ)·(segment frame), the body rate gains θ̇ (small angles), the specific force
    gains ü."""
    R = Rotation.from_rotvec(theta.reshape(-1, 3)).as_matrix().reshape(*theta.shape, 3)
    acc = np.einsum("btji,btj->bti", R, acc_s + u_acc)
    gyr = np.einsum("btji,btj->bti", R, gyr_s + theta_rate)
    return acc, gyr


def quantise(imu: np.ndarray, spec: SensorSpec) -> np.ndarray:
    """Clip to the sensor's range and round to its resolution; ``(..., 6)``."""
    ranges = np.array([spec.acc_range_mps2] * 3 + [spec.gyr_range_rads] * 3)
    lsb = 2.0 * ranges / (2**spec.bits)
    return np.round(np.clip(imu, -ranges, ranges) / lsb) * lsb
