"""Mapping of each mocap skeleton onto Zimmermann et al. 2018's seven segments, with anatomical segment frames.

Segment frames follow docs/conventions.md: x anterior, y left, z superior in neutral stance, origin at the
proximal joint. Bone-local axes are not anatomical in every source (iClone rigs; 20° tilted rest
legs in li2018/cmu_raw), so each segment frame is built in two steps:

1. a geometric target frame per frame: the long axis from the distal to the proximal joint, the
   anterior axis from the pelvis heading (hip-to-hip axis × world up), made orthogonal;
2. one constant offset R_bone_segment per clip, the rotation mean of R_world_bone⁻¹ · target, so
   that the segment frame moves rigidly with the bone (keeping axial twist) while matching the
   anatomical target on average.

Feet: x is tilted so that the ankle→toe vector reads (0.9, 0, -0.4) in the foot frame, the axis
Zimmermann et al. 2018 (§2.4.1) gives for the second metatarsal head.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from service.core.kinematics import GlobalPoses, body_rate_steps
from service.core.resample import interp_along_time
from service.core.segments import SEGMENTS

FOOT_AXIS_IN_SEGMENT = np.array([0.9, 0.0, -0.4]) / np.linalg.norm([0.9, 0.0, -0.4])


@dataclass(frozen=True)
class SkeletonMap:
    """Joint names of one skeleton: pelvis bone and, per side, hip, knee, ankle and toe joints."""

    pelvis: str
    left: tuple[str, str, str, str]  # hip, knee, ankle, toe
    right: tuple[str, str, str, str]


SKELETON_MAPS: dict[str, SkeletonMap] = {
    "cmu_li2018": SkeletonMap("root", ("lfemur", "ltibia", "lfoot", "ltoes"), ("rfemur", "rtibia", "rfoot", "rtoes")),
    "cmu_iclone": SkeletonMap(
        "CC_Base_Pelvis",
        ("CC_Base_L_Thigh", "CC_Base_L_Calf", "CC_Base_L_Foot", "CC_Base_L_ToeBase"),
        ("CC_Base_R_Thigh", "CC_Base_R_Calf", "CC_Base_R_Foot", "CC_Base_R_ToeBase"),
    ),
    "cmu_raw_mb": SkeletonMap(
        "Hips",
        ("LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"),
        ("RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"),
    ),
    "cmu_raw_3dsmax": SkeletonMap(
        "Hips", ("LeftHip", "LeftKnee", "LeftAnkle", "LeftToe"), ("RightHip", "RightKnee", "RightAnkle", "RightToe")
    ),
    "bandai_namco": SkeletonMap(
        "Hips", ("UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L"), ("UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R")
    ),
}


def skeleton_map_for(source: str, joint_names: tuple[str, ...]) -> SkeletonMap:
    """The map for a data source; cmu_raw files come in two naming schemes, the Bandai-Namco sets share one."""
    if source == "cmu_raw":
        return SKELETON_MAPS["cmu_raw_mb" if "LeftUpLeg" in joint_names else "cmu_raw_3dsmax"]
    if source.startswith("bandai_namco"):  # both Bandai-Namco sets share one skeleton
        return SKELETON_MAPS["bandai_namco"]
    try:
        return SKELETON_MAPS[source]
    except KeyError:
        raise KeyError(f"no skeleton map for source {source!r}; known: {sorted(SKELETON_MAPS)}") from None


@dataclass(frozen=True)
class SegmentTrajectories:
    """Global poses of the seven segments (class order of ``SEGMENTS``).

    R_world_segment: (T, 7, 3, 3); origin_m: (T, 7, 3) proximal joint; midpoint_m: (T, 7, 3) the
    middle of the segment axis, where Zimmermann et al. 2018 places the simulated sensor.
    """

    R_world_segment: np.ndarray
    origin_m: np.ndarray
    midpoint_m: np.ndarray
    sample_rate_hz: float


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _frame_from_z_and_x(z: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    """Right-handed frames ``(T, 3, 3)`` (columns x, y, z) with z exact and x from the hint."""
    z = _unit(z)
    x = _unit(x_hint - np.sum(x_hint * z, axis=-1, keepdims=True) * z)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def _foot_target(ankle: np.ndarray, toe: np.ndarray, y_hint: np.ndarray) -> np.ndarray:
    """Foot frames in which ankle→toe reads ``FOOT_AXIS_IN_SEGMENT``, y close to the hint."""
    u = _unit(toe - ankle)
    y = _unit(y_hint - np.sum(y_hint * u, axis=-1, keepdims=True) * u)
    w = np.cross(u, y)
    c, s = FOOT_AXIS_IN_SEGMENT[0], -FOOT_AXIS_IN_SEGMENT[2]
    x = c * u + s * w
    z = c * w - s * u
    return np.stack([x, y, z], axis=-1)


def _rigid_offset(R_world_bone: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Constant ``R_bone_segment`` (3, 3): rotation mean of R_world_bone⁻¹ · target over frames."""
    rel = np.einsum("tji,tjk->tik", R_world_bone, target)
    return Rotation.from_matrix(rel).mean().as_matrix()


def segment_trajectories(poses: GlobalPoses, skeleton: SkeletonMap) -> SegmentTrajectories:
    """Seven anatomical segment trajectories from global joint poses."""
    P, R = poses.positions_m, poses.R_world_joint
    pos = {name: P[:, poses.index(name)] for name in (skeleton.pelvis, *skeleton.left, *skeleton.right)}
    l_hip, r_hip = pos[skeleton.left[0]], pos[skeleton.right[0]]
    up = np.broadcast_to([0.0, 0.0, 1.0], l_hip.shape)
    # Pelvis target: y from right to left hip, x = y × up (anterior), z = x × y.
    y_pelvis = _unit(l_hip - r_hip)
    x_heading = _unit(np.cross(y_pelvis, up))
    targets: dict[str, tuple[np.ndarray, str, np.ndarray, np.ndarray]] = {
        "Pelvis": (
            _frame_from_z_and_x(np.cross(x_heading, y_pelvis), x_heading),
            skeleton.pelvis,
            pos[skeleton.pelvis],
            (l_hip + r_hip) / 2.0,
        ),
    }
    for side, joints in (("Left", skeleton.left), ("Right", skeleton.right)):
        hip, knee, ankle, toe = (pos[j] for j in joints)
        upper = _frame_from_z_and_x(hip - knee, x_heading)
        lower = _frame_from_z_and_x(knee - ankle, x_heading)
        foot = _foot_target(ankle, toe, lower[..., 1])
        targets[f"{side}UpperLeg"] = (upper, joints[0], hip, (hip + knee) / 2.0)
        targets[f"{side}LowerLeg"] = (lower, joints[1], knee, (knee + ankle) / 2.0)
        targets[f"{side}Foot"] = (foot, joints[2], ankle, (ankle + toe) / 2.0)
    R_out, origin, mid = [], [], []
    for name in SEGMENTS:
        target, bone, proximal, midpoint = targets[name]
        R_bone = R[:, poses.index(bone)]
        R_out.append(R_bone @ _rigid_offset(R_bone, target))
        origin.append(proximal)
        mid.append(midpoint)
    return SegmentTrajectories(np.stack(R_out, 1), np.stack(origin, 1), np.stack(mid, 1), poses.sample_rate_hz)


def resample_segments(traj: SegmentTrajectories, sample_rate_hz: float) -> SegmentTrajectories:
    """Resample to a new rate: positions linearly, orientations by slerp; ``(T', 7, ...)``."""
    n = traj.R_world_segment.shape[0]
    t_old = np.arange(n) / traj.sample_rate_hz
    t_new = np.arange(0.0, t_old[-1] + 1e-9, 1.0 / sample_rate_hz)
    if np.isclose(traj.sample_rate_hz, sample_rate_hz):
        return traj
    ratio = traj.sample_rate_hz / sample_rate_hz
    if np.isclose(ratio, round(ratio)):  # integer decimation: exact samples, no interpolation
        step = int(round(ratio))
        return SegmentTrajectories(
            traj.R_world_segment[::step], traj.origin_m[::step], traj.midpoint_m[::step], sample_rate_hz
        )
    R_new = np.stack(
        [Slerp(t_old, Rotation.from_matrix(traj.R_world_segment[:, s]))(t_new).as_matrix() for s in range(7)], 1
    )
    return SegmentTrajectories(
        R_new,
        interp_along_time(t_new, t_old, traj.origin_m),
        interp_along_time(t_new, t_old, traj.midpoint_m),
        sample_rate_hz,
    )


# --- Functional segment frames -------------------------------------------------------------------------------


@dataclass(frozen=True)
class FunctionalCorrection:
    """Per-clip rotations ``R_geometric_functional`` (7, 3, 3), one per segment."""

    R_geometric_functional: np.ndarray

    @property
    def angle_deg(self) -> np.ndarray:
        """How far each functional frame is turned from the geometric one, degrees (7,)."""
        return np.degrees(Rotation.from_matrix(self.R_geometric_functional).magnitude())


def _principal_axis(w: np.ndarray, normal: np.ndarray, sign_hint: np.ndarray) -> np.ndarray:
    """Dominant axis of the rates ``w`` (N, 3) in the plane normal to ``normal``, signed towards ``sign_hint``.

    The top eigenvector of Σ w wᵀ over the rates projected onto that plane (as ``CanonicalFrame`` does per
    window). The fastest 1 % of samples are dropped first, so that a single mocap glitch cannot set the axis.
    """
    w = w - np.outer(w @ normal, normal)
    speed = np.linalg.norm(w, axis=1)
    kept = w[speed <= np.quantile(speed, 0.99)]
    axis = np.linalg.eigh(kept.T @ kept)[1][:, -1]
    return axis if axis @ sign_hint >= 0 else -axis


def _frame_with_z(z: np.ndarray, y_hint: np.ndarray) -> np.ndarray:
    """Columns x, y, z of a right-handed frame with z exact and y the hint made orthogonal to it."""
    return _frame_from_z_and_x(z, np.cross(y_hint, z))


def functional_correction(
    traj: SegmentTrajectories, foot_flat: bool = True, min_speed_mps: float = 0.5
) -> FunctionalCorrection:
    """The rotation from each geometric segment frame to the frame that the clip's motion defines.

    docs/conventions.md wants x anterior, y left and z superior in neutral stance; ``segment_trajectories`` builds that
    from joint positions, which every mocap fit places a little differently per person (toe-out, the ankle→toe
    line, the hip line). Functional calibration (Zimmermann et al. 2018 refs. 14-15) reads the same axes off the motion:

    - upper and lower legs: z stays the long axis; y is the dominant axis of the segment's angular velocity
      (the flexion axis in gait), made orthogonal to z; x = y × z;
    - feet: z is "up" while the foot is flat on the ground (the slowest quarter of its samples, the neutral
      stance of docs/conventions.md), its pitch only; y is the flexion axis made orthogonal to it; x = y × z;
    - pelvis: z stays; x is the direction of travel (mean horizontal velocity direction in the pelvis frame, over
      samples faster than ``min_speed_mps``), made orthogonal to z; y = z × x.

    Each correction is one constant rotation per clip and segment, so the frames stay rigid on their bones.
    Clips must be locomotion (the activities the alignment trains on); the pelvis keeps its geometric frame
    where a clip has fewer than 60 moving samples. ``foot_flat=False`` is for clips whose feet are never flat
    (running lands on the forefoot: the slowest samples read the toes 25-45° down); their feet keep the
    geometric z and take only the functional y.
    """
    R, rate = traj.R_world_segment, traj.sample_rate_hz
    _, ey, ez = np.eye(3)
    out = np.empty((7, 3, 3))
    for k, name in enumerate(SEGMENTS):
        Rk = R[:, k]
        if name == "Pelvis":
            v = np.diff(traj.origin_m[:, k], axis=0) * rate
            v[:, 2] = 0.0
            speed = np.linalg.norm(v, axis=1)
            moving = speed > min_speed_mps
            if moving.sum() < 60:
                out[k] = np.eye(3)
                continue
            d = np.einsum("tji,tj->ti", Rk[:-1][moving], v[moving] / speed[moving, None])  # R⁻¹ v̂
            out[k] = _frame_from_z_and_x(ez, d.mean(axis=0))
            continue
        w = body_rate_steps(Rk, rate)
        if name.endswith("Foot") and foot_flat:
            slow = np.linalg.norm(w, axis=1) <= np.quantile(np.linalg.norm(w, axis=1), 0.25)
            up = Rk[:-1][slow][:, 2, :].mean(axis=0)  # world z in the segment frame: row 2 of R
            up[1] = 0.0  # pitch only: the roll of a flat foot varies with the floor and the person, not the gait
            up /= np.linalg.norm(up)
            out[k] = _frame_with_z(up, _principal_axis(w, up, ey))
        else:
            out[k] = _frame_with_z(ez, _principal_axis(w, ez, ey))
    return FunctionalCorrection(out)


def functional_frames(
    traj: SegmentTrajectories, foot_flat: bool = True
) -> tuple[SegmentTrajectories, FunctionalCorrection]:
    """``traj`` with every segment frame turned onto its functional axes (``functional_correction``)."""
    corr = functional_correction(traj, foot_flat)
    R = np.einsum("tkij,kjl->tkil", traj.R_world_segment, corr.R_geometric_functional)
    return SegmentTrajectories(R, traj.origin_m, traj.midpoint_m, traj.sample_rate_hz), corr
