"""Forward kinematics of a BVH skeleton into the project world frame (Z up, metres).

BVH worlds are Y up; the proper rotation (x, y, z)_project = (z, x, y)_bvh maps forward to +x,
left to +y and up to +z (``../shared/data/README.md``: a y/z swap would mirror left and right).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from service.core.bvh import Bvh

# Columns are the BVH axes expressed in the project frame: project = C @ bvh.
C_PROJECT_BVH = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# Some exporters write Z-up worlds (``SkeletonMapping.up_axis`` "z"): their axes are the project's already (the
# heading does not matter to any model: each session draws its world's heading)
C_PROJECT_BVH_Z_UP = np.eye(3)


@dataclass(frozen=True)
class GlobalPoses:
    """Global joint poses of one clip in the project world frame.

    positions_m: (T, J, 3); R_world_joint: (T, J, 3, 3); names: J joint names.
    """

    names: tuple[str, ...]
    positions_m: np.ndarray
    R_world_joint: np.ndarray
    sample_rate_hz: float

    def index(self, name: str) -> int:
        return self.names.index(name)


def _local_rotations(bvh: Bvh, joint_index: int) -> np.ndarray:
    """Local rotation matrices ``(T, 3, 3)``: intrinsic Euler angles in the CHANNELS order."""
    joint = bvh.joints[joint_index]
    axes, cols = [], []
    for k, channel in enumerate(joint.channels):
        if channel.endswith("rotation"):
            axes.append(channel[0].upper())
            cols.append(joint.channel_start + k)
    if not axes:
        return np.broadcast_to(np.eye(3), (bvh.motion.shape[0], 3, 3))
    angles = bvh.motion[:, cols]
    return Rotation.from_euler("".join(axes), angles, degrees=True).as_matrix()


def _local_translation(bvh: Bvh, joint_index: int) -> np.ndarray:
    """The joint's local translation ``(T, 3)`` in file units.

    The root's position channels add to its OFFSET (the iClone root: Y position about -1.9 on an OFFSET of
    105.2 cm). A non-root joint's position channels *replace* its OFFSET: Bandai-Namco writes 6 channels on every
    joint whose positions equal the OFFSET, and adding them would double every bone (``../shared/data/README.md``).
    """
    joint = bvh.joints[joint_index]
    t = np.broadcast_to(joint.offset, (bvh.motion.shape[0], 3)).copy()
    for k, channel in enumerate(joint.channels):
        if channel.endswith("position"):
            axis = "XYZ".index(channel[0].upper())
            values = bvh.motion[:, joint.channel_start + k]
            t[:, axis] = t[:, axis] + values if joint.parent < 0 else values
    return t


def forward_kinematics(bvh: Bvh, metres_per_unit: float, up_axis: str = "y") -> GlobalPoses:
    """Global positions and orientations of every joint, in the project world frame (the BVH world's up axis
    ``up_axis``: "y", as the format has it, or "z")."""
    C = {"y": C_PROJECT_BVH, "z": C_PROJECT_BVH_Z_UP}[up_axis]
    n_frames, n_joints = bvh.motion.shape[0], len(bvh.joints)
    R = np.empty((n_frames, n_joints, 3, 3))
    p = np.empty((n_frames, n_joints, 3))
    for j, joint in enumerate(bvh.joints):
        R_local = _local_rotations(bvh, j)
        t_local = _local_translation(bvh, j)
        if joint.parent < 0:
            R[:, j] = R_local
            p[:, j] = t_local
        else:
            R[:, j] = R[:, joint.parent] @ R_local
            p[:, j] = p[:, joint.parent] + np.einsum("tij,tj->ti", R[:, joint.parent], t_local)
    positions_m = np.einsum("ij,tkj->tki", C, p) * metres_per_unit
    R_world_joint = np.einsum("ij,tkjl->tkil", C, R)
    names = tuple(joint.name for joint in bvh.joints)
    return GlobalPoses(names, positions_m, R_world_joint, bvh.sample_rate_hz)


def body_rate_steps(R_world_body: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Forward body-frame increments log(R_tᵀ R_{t+1}) · rate, ``(T-1, 3)`` rad/s, from orientations ``(T, 3, 3)``."""
    rot = Rotation.from_matrix(R_world_body)
    return (rot[:-1].inv() * rot[1:]).as_rotvec() * sample_rate_hz


def body_angular_velocity(R_world_body: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Angular velocity in the body frame ``(T, 3)`` from orientations ``(T, 3, 3)``.

    Central estimate: the mean of the backward and forward body-frame increments
    log(R_{t-1}ᵀ R_t) and log(R_tᵀ R_{t+1}), divided by the sample interval.
    """
    step = body_rate_steps(R_world_body, sample_rate_hz)  # (T-1, 3) in the frame of t
    # Express the backward increment (in frame t-1) in frame t: the rotation vector of R_{t-1}ᵀR_t is
    # invariant under that rotation, so the same vector holds in both frames.
    return np.concatenate([step[:1], (step[:-1] + step[1:]) / 2.0, step[-1:]], axis=0)
