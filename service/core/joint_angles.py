"""Joint angles of the canonical body: the joints, the one angle convention that flex models, pose answers and
their evaluations share (``joint_angles_deg``).

A joint is a (parent, child) pair of canonical body segments (``service.core.body``, frames as docs/conventions.md: x
anterior, y left, z superior in neutral stance). Its rotation R = R_world_parent⁻¹ · R_world_child is decomposed as
intrinsic Cardan angles y-x'-z'' (R = R_y(a) R_x(b) R_z(c), the flexion axis first, as ISB recommends for the lower
limb) and reported with anatomical signs (``JOINTS``):

- ``flexion``: s · a, about the parent's y (left) axis; s makes flexion positive for hip, knee, shoulder and elbow
  and for forward bending of the spine (the knee's a is positive when the shank turns back; the hip's and elbow's
  a is negative when they flex);
- ``abduction``: b about the x axis, positive away from the midline for both sides (right-side b is negated);
  for the spine joints, lateral bending to the left;
- ``rotation``: c about the child's z (long) axis, internal rotation positive for both sides; for the spine,
  axial rotation to the left.

The ankle (the foot on the shank) reads the same way: ``flexion`` is dorsiflexion (toes up), ``abduction``
eversion (the sole turned away from the midline), ``rotation`` internal rotation (toes turned in).

All in degrees. In neutral stance every angle is zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.core.body import BODY_SEGMENTS

JOINT_COMPONENTS: tuple[str, ...] = ("flexion", "abduction", "rotation")
# the convention in a sentence, for manifests and answers
ANGLE_CONVENTION = (
    "service.core.joint_angles: joint = R_world_parent^-1 R_world_child as intrinsic y-x'-z'' Cardan angles in "
    "degrees; flexion positive for hip, knee, shoulder, elbow, ankle dorsiflexion and forward spine bending; "
    "abduction positive away from the midline (ankle: eversion; spine: bending left); rotation internal positive "
    "(spine: turning left); zero in neutral stance"
)


@dataclass(frozen=True)
class Joint:
    parent: str
    child: str
    flexion_sign: float  # on a (about y)
    abduction_sign: float  # on b (about x)
    rotation_sign: float  # on c (about z)


# The joints of Chen et al. 2024 Table 3 that the canonical body has (its three spine joints become our two:
# lumbar, L5 against the pelvis; thoracic, T8 against L5; its Shoulder/Arm/ForeArm/UpLeg/Leg are the
# sternoclavicular, shoulder, elbow, hip and knee joints).
JOINTS: dict[str, Joint] = {
    "LumbarSpine": Joint("Pelvis", "L5", 1.0, -1.0, 1.0),
    "ThoracicSpine": Joint("L5", "T8", 1.0, -1.0, 1.0),
    "LeftSternoclavicular": Joint("T8", "LeftShoulder", 1.0, 1.0, -1.0),
    "RightSternoclavicular": Joint("T8", "RightShoulder", 1.0, -1.0, 1.0),
    "LeftShoulder": Joint("LeftShoulder", "LeftUpperArm", -1.0, 1.0, -1.0),
    "RightShoulder": Joint("RightShoulder", "RightUpperArm", -1.0, -1.0, 1.0),
    "LeftElbow": Joint("LeftUpperArm", "LeftForeArm", -1.0, 1.0, -1.0),
    "RightElbow": Joint("RightUpperArm", "RightForeArm", -1.0, -1.0, 1.0),
    "LeftHip": Joint("Pelvis", "LeftUpperLeg", -1.0, 1.0, -1.0),
    "RightHip": Joint("Pelvis", "RightUpperLeg", -1.0, -1.0, 1.0),
    "LeftKnee": Joint("LeftUpperLeg", "LeftLowerLeg", 1.0, 1.0, -1.0),
    "RightKnee": Joint("RightUpperLeg", "RightLowerLeg", 1.0, -1.0, 1.0),
    # not in Chen et al. 2024 Table 3; what a gait lab reads beside hip and knee (the foot frame's x is the ankle ->
    # toe heading, level in stance: R_y(a) with a > 0 turns the toes down, so dorsiflexion is -a)
    "LeftAnkle": Joint("LeftLowerLeg", "LeftFoot", -1.0, 1.0, -1.0),
    "RightAnkle": Joint("RightLowerLeg", "RightFoot", -1.0, -1.0, 1.0),
}


def answered_joints(segments: set[str] | frozenset[str]) -> list[str]:
    """The joints of ``JOINTS`` (in its order) whose two segments are both in ``segments``: those a pose answers
    with something other than a copy of a parent."""
    return [name for name, j in JOINTS.items() if j.parent in segments and j.child in segments]


def angle_difference_deg(pred_deg: np.ndarray, true_deg: np.ndarray) -> np.ndarray:
    """pred − true of angles in degrees, wrapped into [−180, 180) (179° against −179° is −2°)."""
    return (pred_deg - true_deg + 180.0) % 360.0 - 180.0


def _relative(R_world_segment: np.ndarray, joint: Joint) -> np.ndarray:
    p, c = BODY_SEGMENTS.index(joint.parent), BODY_SEGMENTS.index(joint.child)
    return np.einsum("...ji,...jk->...ik", R_world_segment[..., p, :, :], R_world_segment[..., c, :, :])


def joint_angles_deg(R_world_segment: np.ndarray, joints: list[str] | tuple[str, ...]) -> np.ndarray:
    """``(T, 21, 3, 3)`` segment orientations → ``(T, J, 3)`` flexion, abduction, rotation in degrees (module
    docstring), the one definition training targets and evaluation use."""
    out = np.empty((*R_world_segment.shape[:-3], len(joints), 3))
    for k, name in enumerate(joints):
        joint = JOINTS[name]
        rel = _relative(R_world_segment, joint)
        # intrinsic y-x'-z'': a = atan2(R02, R22), b = asin(-R12), c = atan2(R10, R11)
        a = np.arctan2(rel[..., 0, 2], rel[..., 2, 2])
        b = np.arcsin(np.clip(-rel[..., 1, 2], -1.0, 1.0))
        c = np.arctan2(rel[..., 1, 0], rel[..., 1, 1])
        signs = (joint.flexion_sign, joint.abduction_sign, joint.rotation_sign)
        out[..., k, :] = np.degrees(np.stack([a, b, c], axis=-1)) * np.array(signs)
    return out
