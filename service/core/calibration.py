"""From raw sensor readings to segment readings: sensor-to-segment calibration and pelvis-relative pose features.

One module for training and serving (docs/conventions.md): the simulator feeds its virtual sensors' raw readings through
exactly these functions, and the service feeds a client's.

Raw readings per sensor: ``q_world_sensor`` (the sensor's own fusion output in its own world frame: ENU, NWU, …,
z up) and the accelerometer's specific force in the sensor frame (m/s², +9.81 up at rest).

Calibration gives ``q_segment_sensor`` per sensor (docs/conventions.md: v_segment = R_segment_sensor · v_sensor):

- ``declared``: the client states it (e.g. from ``/v1/imu/assign`` for the lower-body sensors): no pose needed;
- ``still_pose_calibration``: a still N-pose (arms down) or T-pose (arms sideways) of 2–3 s, as TransPose's live
  demo does. In that pose every segment's frame is known up to the body's heading (N-pose: all segment frames
  equal the body frame; T-pose: the upper arms, forearms and hands turned ±90° about x). The heading is read off
  the pelvis sensor: its axis that points out of the lower back (``back_axis``, default the sensor's +z, the
  skin normal of Zimmermann et al. 2018 eq. 8) is posterior, so the body's anterior is its horizontal opposite.

Features (Zheng et al. 2021 eq. 2–3): every sensor segment's orientation and free acceleration relative to the pelvis,
R_root_B = R_W_rootᵀ R_W_B and a_root_B = R_W_rootᵀ (a_W_B − a_W_root). Both are unchanged when the world frame
turns about the vertical, so no heading calibration between sessions or sensor brands is needed. The pelvis's
own tilt (world up in the pelvis frame) and free acceleration in the pelvis frame are added: both are
heading-free too, and without them a bent-over and an upright pelvis would read alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from service.core.rotations import matrix_from_quat, quat_from_matrix
from service.core.units import GRAVITY_MPS2

FEATURE_VERSION = "pelvis_relative_v1"
ACC_SCALE_MPS2 = 30.0  # TransPose's acc_scale: free accelerations enter the network divided by this
STILL_GYRO_RADS = 0.35  # a still span: every sensor's angular rate below this (about 20 °/s) ...
STILL_ACC_STD_MPS2 = 0.6  # ... and its acceleration's standard deviation below this
_UP = np.array([0.0, 0.0, 1.0])


class CalibrationError(ValueError):
    """A calibration that cannot be computed from what was given; the message says what was expected."""


def features_per_frame(n_sensors: int) -> int:
    """Feature width: 12 per non-root sensor (R 9 + a 3), 6 for the root (up 3 + a 3)."""
    return 12 * (n_sensors - 1) + 6


def segment_readings(
    q_world_sensor: np.ndarray, acc_sensor_mps2: np.ndarray, q_segment_sensor: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Segment orientations ``(T, N, 3, 3)`` and free accelerations in the world frame ``(T, N, 3)``.

    R_W_segment = R_W_sensor · R_segment_sensorᵀ (Zheng et al. 2021 eq. 1); a_W = R_W_sensor · f_sensor − g_up.
    ``q_segment_sensor`` is one alignment per sensor ``(N, 4)``, or one per frame ``(T, N, 4)`` (several live
    sessions' frames computed together).
    """
    R_ws = matrix_from_quat(q_world_sensor)
    R_ss = matrix_from_quat(q_segment_sensor)  # (N, 3, 3) or (T, N, 3, 3) segment ← sensor
    R_w_seg = R_ws @ np.swapaxes(R_ss, -1, -2)
    acc_world = np.einsum("tnij,tnj->tni", R_ws, acc_sensor_mps2) - GRAVITY_MPS2 * _UP
    return R_w_seg, acc_world


def pose_features(R_world_segment: np.ndarray, acc_world_mps2: np.ndarray, root: int = 0) -> np.ndarray:
    """Pelvis-relative features ``(T, F)`` float32 (Zheng et al. 2021 eq. 2–3), sensors in the model's order.

    Per non-root sensor: R_root_B flattened row-major (9), then a_root_B / ``ACC_SCALE_MPS2`` (3); for the root:
    world up in the root frame (3), then its free acceleration in its own frame / ``ACC_SCALE_MPS2`` (3).
    """
    R_root = R_world_segment[:, root]  # (T, 3, 3)
    rel_R = np.einsum("tji,tnjk->tnik", R_root, R_world_segment)
    rel_a = np.einsum("tji,tnj->tni", R_root, acc_world_mps2 - acc_world_mps2[:, root : root + 1])
    own_a = np.einsum("tji,tj->ti", R_root, acc_world_mps2[:, root])
    up = R_root[:, 2, :]  # world z in the root frame: R_W_rootᵀ e_z, row 2 of R_W_root
    others = [k for k in range(R_world_segment.shape[1]) if k != root]
    parts = [up, own_a / ACC_SCALE_MPS2]
    for k in others:
        parts += [rel_R[:, k].reshape(-1, 9), rel_a[:, k] / ACC_SCALE_MPS2]
    return np.concatenate(parts, axis=1).astype(np.float32)


# The pelvis's heading from the legs (our addition). An alignment from ``/v1/imu/assign`` (Zimmermann et al. 2018's
# network and its functional axes) is found from each sensor's own walk: the leg segments' forward axes are pinned by
# their swing about the knee's hinge, the pelvis's only by how its sway and steps read, and on real people it comes
# out turned about the vertical by tens of degrees to a half turn (docs/pose.md, Calibration: "The pelvis's heading
# from the legs"). A turn of the pelvis about the vertical turns every pelvis-relative feature (Zheng et al. 2021 eq.
# 2-3), so the pose reads legs swinging sideways. In walking the pelvis faces where the legs swing: this turns the
# pelvis's alignment about its own z (the vertical, upright) to the mean heading of the leg segments' forward (x)
# axes. Each frame's horizontal forward axes are complex numbers h = x + iy; conj(h_pelvis) · h_leg, summed over legs
# and frames, weighs each frame by how level both axes are.
LEG_SEGMENTS = frozenset(f"{side}{part}" for side in ("Left", "Right") for part in ("UpperLeg", "LowerLeg", "Foot"))


def legs_heading_sum(R_world_segment: np.ndarray, segments: Sequence[str], root: int = 0) -> np.ndarray:
    """``(T, N, 3, 3)`` segment orientations in the model's sensor order → ``(T,)`` complex: per frame the sum over
    the leg segments (``LEG_SEGMENTS``) of conj(h_root) · h_leg; the angle of its sum over frames is the legs' mean
    heading relative to the root's. Zero where no leg segment is among ``segments``."""
    legs = [k for k, s in enumerate(segments) if s in LEG_SEGMENTS]
    x = R_world_segment[..., :2, 0]  # (T, N, 2): each segment's x axis in the world, horizontal part
    h = x[..., 0] + 1j * x[..., 1]
    return (np.conj(h[:, root : root + 1]) * h[:, legs]).sum(axis=1)


def turn_about_own_axis(R_world_segment: np.ndarray, angle_rad: np.ndarray, axis: int) -> np.ndarray:
    """``(T, 3, 3)`` orientations turned about their own axis ``axis`` (0 x, 1 y, 2 z) by ``(T,)`` angles:
    R · R_axis(angle), right-handed."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    i, j = (axis + 1) % 3, (axis + 2) % 3  # the plane the turn moves: i → j
    turn = np.zeros((len(c), 3, 3))
    turn[:, axis, axis] = 1.0
    turn[:, i, i], turn[:, i, j], turn[:, j, i], turn[:, j, j] = c, -s, s, c
    return R_world_segment @ turn


def turn_about_z(R_world_segment: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` orientations turned about their own z by ``(T,)`` angles: R · Rz(angle)."""
    return turn_about_own_axis(R_world_segment, angle_rad, 2)


def pelvis_heading_from_legs(
    q_world_sensor: np.ndarray, q_segment_sensor: np.ndarray, segments: Sequence[str], root: int = 0
) -> tuple[np.ndarray, float]:
    """Alignments ``(N, 4)`` with the root's turned about its z to the legs' mean heading over the frames of
    ``q_world_sensor`` ``(T, N, 4)`` (``legs_heading_sum``), and that turn in degrees (positive: anticlockwise
    seen from above)."""
    if not any(s in LEG_SEGMENTS for s in segments):
        raise CalibrationError(
            f"the pelvis's heading from the legs needs the pose to read a sensor on a thigh, shank or foot; it reads "
            f"{list(segments)}"
        )
    R_w_seg = matrix_from_quat(q_world_sensor) @ np.swapaxes(matrix_from_quat(q_segment_sensor), -1, -2)
    if R_w_seg[:, root, 2, 2].mean() < 0.0:  # turning about its own z would then turn the heading the other way
        raise CalibrationError("the pelvis's heading from the legs: the pelvis's z axis points down, not up")
    total = legs_heading_sum(R_w_seg, segments, root).sum()
    if abs(total) < 1e-9:
        raise CalibrationError("the pelvis's heading from the legs: no frame has a level pelvis and leg forward axis")
    angle = float(np.angle(total))
    R_seg_sensor = matrix_from_quat(q_segment_sensor[root])
    Rz = turn_about_z(np.eye(3)[None], np.array([angle]))[0]
    out = np.array(q_segment_sensor, dtype=np.float64, copy=True)
    out[root] = quat_from_matrix(Rz.T @ R_seg_sensor)  # R_W_seg' = R_W_sensor R_seg_sensorᵀ Rz
    return out, float(np.degrees(angle))


def is_still(
    gyr_rads: np.ndarray | None, acc_sensor_mps2: np.ndarray, names: Sequence[str] | None = None
) -> tuple[bool, str]:
    """Whether a span ``(T, N, 3)`` is still enough to calibrate on, and if not, which sensor moved how much."""
    name = (lambda k: names[k]) if names is not None else (lambda k: f"#{k}")  # noqa: E731
    acc_std = acc_sensor_mps2.std(axis=0).max(axis=-1)  # (N,)
    worst = int(np.argmax(acc_std))
    if acc_std[worst] > STILL_ACC_STD_MPS2:
        return False, (
            f"the sensor on {name(worst)} varies its acceleration by {acc_std[worst]:.2f} m/s^2 (std; still: "
            f"< {STILL_ACC_STD_MPS2})"
        )
    if gyr_rads is not None:
        rate = np.linalg.norm(gyr_rads, axis=-1).max(axis=0)  # (N,)
        worst = int(np.argmax(rate))
        if rate[worst] > STILL_GYRO_RADS:
            return (
                False,
                f"the sensor on {name(worst)} turns at up to {rate[worst]:.2f} rad/s (still: < {STILL_GYRO_RADS})",
            )
    return True, ""


# The still poses: R_body_segment of each segment in that pose (identity unless listed). In the T-pose the arms
# point sideways; an arm segment's z runs from its distal to its proximal end (superior when hanging), so it points
# to the body's -y for the left arm and +y for the right: Rx(+90°) and Rx(-90°).
_T_POSE_ARM_TURN_DEG = {"Left": 90.0, "Right": -90.0}  # about the body's x axis


def still_pose_segment_frames(segments: Sequence[str], pose: str) -> np.ndarray:
    """R_body_segment ``(N, 3, 3)`` of each segment in a still ``pose`` ("npose" or "tpose")."""
    if pose not in ("npose", "tpose"):
        raise CalibrationError(f"calibration pose must be 'npose' or 'tpose', got {pose!r}")
    out = np.broadcast_to(np.eye(3), (len(segments), 3, 3)).copy()
    if pose == "tpose":
        for k, s in enumerate(segments):
            for side, deg in _T_POSE_ARM_TURN_DEG.items():
                if s in (f"{side}UpperArm", f"{side}ForeArm", f"{side}Hand"):
                    a = np.radians(deg)
                    out[k] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    return out


def still_pose_calibration(
    q_world_sensor: np.ndarray,
    segments: Sequence[str],
    pose: str = "npose",
    root: int = 0,
    back_axis: Sequence[float] = (0.0, 0.0, 1.0),
) -> np.ndarray:
    """``q_segment_sensor`` ``(N, 4)`` from the sensors' orientations ``(T, N, 4)`` during a still pose.

    The body frame in the world is R_W_body = Rz(heading); heading from the root sensor's ``back_axis`` (a unit
    vector in that sensor's frame pointing posterior, out of the lower back). Then for each sensor
    R_segment_sensor = (R_W_body · R_body_segment)ᵀ · R_W_sensor, averaged over the span.
    """
    R_ws = matrix_from_quat(q_world_sensor)  # (T, N, 3, 3)
    R_mean = _mean_rotation(R_ws)  # (N, 3, 3)
    axis = np.asarray(back_axis, dtype=np.float64)
    length = float(np.linalg.norm(axis))
    if not np.isfinite(length) or length < 1e-6:
        raise CalibrationError(
            f"the pelvis sensor's back axis must be a finite non-zero vector, got {[float(v) for v in back_axis]}"
        )
    back_w = R_mean[root] @ (axis / length)
    forward = -back_w
    forward[2] = 0.0
    norm = np.linalg.norm(forward)
    if norm < 0.3:
        raise CalibrationError(
            f"the pelvis sensor's back axis {[float(v) for v in back_axis]} points "
            f"{np.degrees(np.arccos(np.clip(abs(back_w[2]), 0, 1))):.0f}° "
            "from vertical: expected it roughly horizontal (out of the lower back) to give the heading"
        )
    x = forward / norm
    R_w_body = np.stack([x, np.cross(_UP, x), _UP], axis=-1)
    R_body_seg = still_pose_segment_frames(segments, pose)
    R_w_seg = np.einsum("ij,njk->nik", R_w_body, R_body_seg)
    R_seg_sensor = np.einsum("nji,njk->nik", R_w_seg, R_mean)
    return quat_from_matrix(R_seg_sensor)


def _mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal mean over the first axis of ``(T, N, 3, 3)``: the nearest rotation to the mean matrix."""
    M = R.mean(axis=0)
    U, _, Vt = np.linalg.svd(M)
    D = np.ones((M.shape[0], 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    return np.einsum("nij,nj,njk->nik", U, D, Vt)
