"""One canonical body for whole-body pose: 21 segments, their tree, anatomical frames, and forward kinematics.

Every mocap skeleton family is mapped onto these segments by a small declarative table (``SkeletonMapping``:
segment → the joint whose rotation drives it and the joint that ends it); a user's own BVH with an unknown
skeleton works the same way with a mapping file (``load_mapping``, JSON or YAML with the same fields).

Segment frames follow docs/conventions.md (as Xsens MVN): in neutral stance x anterior, y left, z superior, origin at
the proximal joint. They are built as ``service.core.skeleton`` builds the seven lower-body frames: a geometric
target per frame (long axis from the joints, anterior from the pelvis heading), then one constant offset per
clip and segment (the rotation mean of R_world_bone⁻¹ · target), so that each segment frame moves rigidly with
its bone and keeps the bone's axial twist.

Forward kinematics (``Body.forward``): each segment's origin is its parent's origin plus the parent's
orientation applied to a constant bone vector expressed in the parent's frame (``Body.offsets_m``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from service.core.bvh import Bvh, rotations_bvh
from service.core.kinematics import C_PROJECT_BVH, GlobalPoses
from service.core.translation import Feet

# Canonical segments in tree order (a parent precedes its children); Xsens MVN names (L5 lower spine, T8 upper).
BODY_SEGMENTS: tuple[str, ...] = (
    "Pelvis",
    "L5",
    "T8",
    "Neck",
    "Head",
    "LeftShoulder",
    "LeftUpperArm",
    "LeftForeArm",
    "LeftHand",
    "RightShoulder",
    "RightUpperArm",
    "RightForeArm",
    "RightHand",
    "LeftUpperLeg",
    "LeftLowerLeg",
    "LeftFoot",
    "LeftToe",
    "RightUpperLeg",
    "RightLowerLeg",
    "RightFoot",
    "RightToe",
)
BODY_PARENT: dict[str, str | None] = {
    "Pelvis": None,
    "L5": "Pelvis",
    "T8": "L5",
    "Neck": "T8",
    "Head": "Neck",
    "LeftShoulder": "T8",
    "LeftUpperArm": "LeftShoulder",
    "LeftForeArm": "LeftUpperArm",
    "LeftHand": "LeftForeArm",
    "RightShoulder": "T8",
    "RightUpperArm": "RightShoulder",
    "RightForeArm": "RightUpperArm",
    "RightHand": "RightForeArm",
    "LeftUpperLeg": "Pelvis",
    "LeftLowerLeg": "LeftUpperLeg",
    "LeftFoot": "LeftLowerLeg",
    "LeftToe": "LeftFoot",
    "RightUpperLeg": "Pelvis",
    "RightLowerLeg": "RightUpperLeg",
    "RightFoot": "RightLowerLeg",
    "RightToe": "RightFoot",
}


def other_side(segment: str) -> str:
    """A segment's counterpart on the other side of the body (itself on the midline)."""
    return segment.replace("Left", "#").replace("Right", "Left").replace("#", "Right")


PARENT_INDEX: tuple[int, ...] = tuple(
    -1 if BODY_PARENT[s] is None else BODY_SEGMENTS.index(BODY_PARENT[s]) for s in BODY_SEGMENTS
)

# How the geometric target frame of each segment is read off its joints (proximal p, distal d):
#   trunk: z from the segment's origin to the neck's (rigs curve the lumbar bones 20-40° forward; the MVN frames
#   of the spine are upright in stance);  up: z along d − p (neck);
#   down: z along p − d (limbs hang in neutral stance, z superior);
#   left / right: y along ±(d − p) (shoulders run sideways);  foot: level with the ground while the foot stands
#   flat (``_flat_stance``), x the ankle → toe heading, z up: rigs put the toe joint at different heights, so a
#   fixed ankle → toe pitch (Zimmermann et al. 2018 §2.4.1's, which the I2S frames keep) tilts one rig's feet
#   against another's (Bandai-Namco's flat feet read 16° toes-down with it, CMU's 5-15° toes-up);
#   parent: the parent's target (head, hands, toes: their end points are not reliable across rigs; Bandai-Namco's
#   end sites have zero length).
_AXIS_RULE: dict[str, str] = {
    "L5": "trunk",
    "T8": "trunk",
    "Neck": "up",
    "Head": "parent",
    "LeftShoulder": "left",
    "RightShoulder": "right",
    "LeftToe": "parent",
    "RightToe": "parent",
    "LeftHand": "parent",
    "RightHand": "parent",
}
for _s in BODY_SEGMENTS:
    if _s.endswith("Foot"):
        _AXIS_RULE[_s] = "foot"
    _AXIS_RULE.setdefault(_s, "down")
_AXIS_RULE.pop("Pelvis")
# trunk_axes "thorax": the upper trunk's frames from landmarks every rig places alike (the hip and shoulder joint
# centres) instead of where each rig puts its spine and neck joints; li2018 and iClone read the same CMU trial
# 18° apart on T8 and 14-17° on the shoulders with the spine's joints, 5° and 1° with these (docs/pose.md). T8: z
# from the hip centre to the shoulder centre; the shoulders, neck and head: T8's target (as the head and hands
# take their parent's), so that in the rig's walks each is, on average, as upright as the thorax.
_TRUNK_RULES = {
    "spine": {},
    "thorax": {"T8": "thorax", "LeftShoulder": "parent", "RightShoulder": "parent", "Neck": "parent"},
}
TRUNK_AXES: tuple[str, ...] = tuple(_TRUNK_RULES)


def check_trunk_axes(trunk_axes: str) -> str:
    """``trunk_axes`` if it names a rule, else a ValueError that lists them (a typo must not fall back to frames
    of another rule without a word)."""
    if trunk_axes not in _TRUNK_RULES:
        raise ValueError(f"trunk_axes is one of {list(TRUNK_AXES)}, got {trunk_axes!r}")
    return trunk_axes


# Flat stance: ankle and toe slower than this and within STANCE_HEIGHT_M of their lowest in the clip
STANCE_SPEED_M_S = 0.2
STANCE_HEIGHT_M = 0.03
MIN_STANCE_FRAMES = 10
# The head rises at least this far above the feet in a clip's upright frames (``_check_upright``)
UPRIGHT_RISE_M = 0.5


class MappingError(ValueError):
    """A skeleton mapping that does not fit the skeleton or the canonical body; the message says what."""


class NoStanceError(MappingError):
    """A clip whose feet never stand flat, so it cannot define the foot frames; its rig's other clips can."""


@dataclass(frozen=True)
class SkeletonMapping:
    """Declarative map of one skeleton family onto ``BODY_SEGMENTS``.

    segments: segment → (driving joint, distal joint or None); the driving joint's position is the segment origin
    and its rotation moves the segment. hips: left and right hip joints (the pelvis's lateral axis).
    metres_per_unit: the length unit of the BVH files. up_axis: the BVH world's vertical, "y" as the format has it
    or "z" as some exporters write it.
    """

    name: str
    segments: dict[str, tuple[str, str | None]]
    hips: tuple[str, str]
    metres_per_unit: float
    up_axis: str = "y"

    def check(self, joint_names: tuple[str, ...]) -> None:
        missing = [s for s in BODY_SEGMENTS if s not in self.segments]
        extra = [s for s in self.segments if s not in BODY_SEGMENTS]
        if missing or extra:
            raise MappingError(
                f"mapping {self.name!r}: expected every segment of {list(BODY_SEGMENTS)}; "
                f"missing {missing}, unknown {extra}"
            )
        names = set(joint_names)
        used = {j for joint, distal in self.segments.values() for j in (joint, distal) if j} | set(self.hips)
        used.discard(END_SITE)
        absent = sorted(used - names)
        if absent:
            raise MappingError(f"mapping {self.name!r}: joints {absent} are not in the skeleton {sorted(names)}")
        for s in BODY_SEGMENTS:
            if _AXIS_RULE.get(s, "pelvis") not in ("parent", "pelvis") and self.segments[s][1] is None:
                raise MappingError(f"mapping {self.name!r}: segment {s} needs a distal joint")


def _side_table(prefix_l: str, prefix_r: str, names: dict[str, tuple[str, str | None]]) -> dict:
    out = {}
    for seg, (joint, distal) in names.items():
        for side, pre in (("Left", prefix_l), ("Right", prefix_r)):
            out[f"{side}{seg}"] = (joint.format(s=pre), None if distal is None else distal.format(s=pre))
    return out


def _mapping(name: str, axial: dict, sided: dict, sides: tuple[str, str], hips: tuple[str, str], mpu: float):
    return SkeletonMapping(name, {**axial, **_side_table(*sides, sided)}, hips, mpu)


SKELETON_MAPPINGS: dict[str, SkeletonMapping] = {
    "cmu_li2018": _mapping(
        "cmu_li2018",
        {
            "Pelvis": ("root", None),
            "L5": ("lowerback", "upperback"),
            "T8": ("upperback", "thorax"),
            "Neck": ("lowerneck", "head"),
            "Head": ("head", None),
        },
        {
            "Shoulder": ("{s}clavicle", "{s}humerus"),
            "UpperArm": ("{s}humerus", "{s}radius"),
            "ForeArm": ("{s}radius", "{s}wrist"),
            "Hand": ("{s}hand", "{s}fingers"),  # the palm: lwrist's bone has no length and only twists
            "UpperLeg": ("{s}femur", "{s}tibia"),
            "LowerLeg": ("{s}tibia", "{s}foot"),
            "Foot": ("{s}foot", "{s}toes"),
            "Toe": ("{s}toes", None),
        },
        ("l", "r"),
        ("lfemur", "rfemur"),
        1.0,
    ),
    "cmu_iclone": _mapping(
        "cmu_iclone",
        {
            "Pelvis": ("CC_Base_Pelvis", None),
            "L5": ("CC_Base_Waist", "CC_Base_Spine01"),
            "T8": ("CC_Base_Spine02", "CC_Base_NeckTwist01"),
            "Neck": ("CC_Base_NeckTwist01", "CC_Base_Head"),
            "Head": ("CC_Base_Head", None),
        },
        {
            "Shoulder": ("CC_Base_{s}_Clavicle", "CC_Base_{s}_Upperarm"),
            "UpperArm": ("CC_Base_{s}_Upperarm", "CC_Base_{s}_Forearm"),
            "ForeArm": ("CC_Base_{s}_Forearm", "CC_Base_{s}_Hand"),
            "Hand": ("CC_Base_{s}_Hand", "CC_Base_{s}_Mid1"),
            "UpperLeg": ("CC_Base_{s}_Thigh", "CC_Base_{s}_Calf"),
            "LowerLeg": ("CC_Base_{s}_Calf", "CC_Base_{s}_Foot"),
            "Foot": ("CC_Base_{s}_Foot", "CC_Base_{s}_ToeBase"),
            "Toe": ("CC_Base_{s}_ToeBase", None),
        },
        ("L", "R"),
        ("CC_Base_L_Thigh", "CC_Base_R_Thigh"),
        0.01,
    ),
    "cmu_raw_mb": _mapping(
        "cmu_raw_mb",
        {
            "Pelvis": ("Hips", None),
            "L5": ("LowerBack", "Spine"),
            "T8": ("Spine", "Spine1"),  # Spine1 -> Neck has zero length
            "Neck": ("Neck", "Head"),
            "Head": ("Head", None),
        },
        {
            "Shoulder": ("{s}Shoulder", "{s}Arm"),
            "UpperArm": ("{s}Arm", "{s}ForeArm"),
            "ForeArm": ("{s}ForeArm", "{s}Hand"),
            "Hand": ("{s}Hand", "{s}FingerBase"),
            "UpperLeg": ("{s}UpLeg", "{s}Leg"),
            "LowerLeg": ("{s}Leg", "{s}Foot"),
            "Foot": ("{s}Foot", "{s}ToeBase"),
            "Toe": ("{s}ToeBase", None),
        },
        ("Left", "Right"),
        ("LeftUpLeg", "RightUpLeg"),
        0.0254 / 0.45,
    ),
    # cmu_raw 131_*: the same skeleton as cmu_raw_mb under 3ds Max names, one joint name per position.
    "cmu_raw_3dsmax": SkeletonMapping(
        "cmu_raw_3dsmax",
        {
            "Pelvis": ("Hips", None),
            "L5": ("lowerback", "Chest"),
            "T8": ("Chest", "Chest2"),  # Chest2 -> lowerneck has zero length
            "Neck": ("lowerneck", "Head"),
            "Head": ("Head", None),
            **{
                f"{side}{seg}": (joint.format(s=side), None if distal is None else distal.format(s=side))
                for side in ("Left", "Right")
                for seg, (joint, distal) in {
                    "Shoulder": ("{s}Collar", "{s}Shoulder"),
                    "UpperArm": ("{s}Shoulder", "{s}Elbow"),
                    "ForeArm": ("{s}Elbow", "{s}Wrist"),
                    "UpperLeg": ("{s}Hip", "{s}Knee"),
                    "LowerLeg": ("{s}Knee", "{s}Ankle"),
                    "Foot": ("{s}Ankle", "{s}Toe"),
                    "Toe": ("{s}Toe", None),
                }.items()
            },
            "LeftHand": ("LeftWrist", "lhand"),
            "RightHand": ("RightWrist", "rhand"),
        },
        ("LeftHip", "RightHip"),
        0.0254 / 0.45,
    ),
    "bandai_namco": _mapping(
        "bandai_namco",
        {
            "Pelvis": ("Hips", None),
            "L5": ("Spine", "Chest"),
            "T8": ("Chest", "Neck"),
            "Neck": ("Neck", "Head"),
            "Head": ("Head", None),
        },
        {
            "Shoulder": ("Shoulder_{s}", "UpperArm_{s}"),
            "UpperArm": ("UpperArm_{s}", "LowerArm_{s}"),
            "ForeArm": ("LowerArm_{s}", "Hand_{s}"),
            "Hand": ("Hand_{s}", None),
            "UpperLeg": ("UpperLeg_{s}", "LowerLeg_{s}"),
            "LowerLeg": ("LowerLeg_{s}", "Foot_{s}"),
            "Foot": ("Foot_{s}", "Toes_{s}"),
            "Toe": ("Toes_{s}", None),
        },
        ("L", "R"),
        ("UpperLeg_L", "UpperLeg_R"),
        0.01,
    ),
}
# "end" as a distal joint: the driving joint's BVH end site.
END_SITE = "end"


def mapping_for_source(source: str, joint_names: tuple[str, ...]) -> SkeletonMapping:
    """The mapping of a data source (index.csv ``source``); cmu_raw comes in two naming schemes."""
    if source == "cmu_raw":
        return SKELETON_MAPPINGS["cmu_raw_mb" if "LeftUpLeg" in joint_names else "cmu_raw_3dsmax"]
    if source.startswith("bandai_namco"):
        return SKELETON_MAPPINGS["bandai_namco"]
    try:
        return SKELETON_MAPPINGS[source]
    except KeyError:
        raise MappingError(f"no skeleton mapping for source {source!r}; pass a mapping file") from None


def detect_mapping(joint_names: tuple[str, ...]) -> SkeletonMapping:
    """The known family whose joints a skeleton has; else a ``MappingError`` asking for a mapping file."""
    names = set(joint_names)
    for mapping in SKELETON_MAPPINGS.values():
        used = {j for joint, distal in mapping.segments.values() for j in (joint, distal) if j and j != END_SITE}
        if used | set(mapping.hips) <= names:
            return mapping
    raise MappingError(
        f"the skeleton (joints {sorted(names)[:12]}…) is none of the known families {sorted(SKELETON_MAPPINGS)}; "
        "write a mapping file (service.core.body.load_mapping) and pass it with --mapping"
    )


def load_mapping(path: str | Path) -> SkeletonMapping:
    """A user's mapping file (JSON, or YAML when PyYAML is installed)::

        {"name": "my_rig", "metres_per_unit": 0.01, "hips": ["LeftUpLeg", "RightUpLeg"],
         "segments": {"Pelvis": {"joint": "Hips"}, "L5": {"joint": "Spine", "distal": "Spine1"}, ...}}

    Every segment of ``BODY_SEGMENTS`` is required; ``distal`` may be ``"end"`` (the joint's end site) and is not
    needed for Pelvis, Head and the toes.
    """
    text = Path(path).read_text()
    if Path(path).suffix in (".yaml", ".yml"):
        import yaml  # the service installs PyYAML; plain numpy users can write JSON

        try:
            raw = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise MappingError(f"{path}: not valid YAML: {exc}") from None
    else:
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MappingError(f"{path}: not valid JSON: {exc}") from None
    try:
        segments = {s: (v["joint"], v.get("distal")) for s, v in raw["segments"].items()}
        hips = raw["hips"]
        if not isinstance(hips, list | tuple) or len(hips) != 2:
            raise TypeError(f"'hips' must be a list of the two hip joints [left, right], got {hips!r}")
        try:
            scale = float(raw["metres_per_unit"])
        except (TypeError, ValueError):
            raise TypeError(
                f"'metres_per_unit' must be a number (0.01 for centimetres), got {raw['metres_per_unit']!r}"
            ) from None
        if not np.isfinite(scale) or scale <= 0:
            raise TypeError(f"'metres_per_unit' must be positive (0.01 for centimetres), got {scale}")
        mapping = SkeletonMapping(
            str(raw.get("name", Path(path).stem)),
            segments,
            (hips[0], hips[1]),
            scale,
            str(raw.get("up_axis", "y")).lower(),
        )
    except (KeyError, TypeError, IndexError, AttributeError) as exc:
        raise MappingError(
            f"{path}: a mapping needs 'metres_per_unit', 'hips' [left, right] and 'segments' "
            f"{{segment: {{'joint': ..., 'distal': ...}}}}; missing or malformed: {exc}"
        ) from None
    if mapping.up_axis not in ("y", "z"):
        raise MappingError(f'{path}: \'up_axis\' is the BVH world\'s vertical, "y" or "z"; got {raw["up_axis"]!r}')
    shared: dict[str, list[str]] = {}
    for segment, (joint, _) in mapping.segments.items():
        shared.setdefault(joint, []).append(segment)
    doubled = {j: s for j, s in shared.items() if len(s) > 1}
    if doubled:  # each segment turns with its own joint (a copy-paste slip would score one side as the other)
        raise MappingError(f"{path}: each segment needs its own joint; these share one: {doubled}")
    return mapping


@dataclass(frozen=True)
class BodyMotion:
    """One clip on the canonical body: R_world_segment (T, S, 3, 3), origin_m (T, S, 3) proximal joints,
    midpoint_m (T, S, 3) where a sensor is nominally placed, at ``sample_rate_hz``."""

    R_world_segment: np.ndarray
    origin_m: np.ndarray
    midpoint_m: np.ndarray
    sample_rate_hz: float

    @property
    def n_frames(self) -> int:
        return self.R_world_segment.shape[0]

    def crop(self, start: int, stop: int | None = None) -> BodyMotion:
        s = slice(start, stop)
        return BodyMotion(self.R_world_segment[s], self.origin_m[s], self.midpoint_m[s], self.sample_rate_hz)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _frame_z_x(z: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    z = _unit(z)
    x = _unit(x_hint - np.sum(x_hint * z, -1, keepdims=True) * z)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def _frame_y_x(y: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    y = _unit(y)
    x = _unit(x_hint - np.sum(x_hint * y, -1, keepdims=True) * y)
    return np.stack([x, y, np.cross(x, y)], axis=-1)


def _flat_stance(ankle: np.ndarray, toe: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Frames ``(T,)`` bool where the foot stands flat: ankle and toe still and both near their lowest; in a clip
    where that never happens (a dance on tiptoe), the frames where both are still."""
    still, low = np.ones(len(ankle), dtype=bool), np.ones(len(ankle), dtype=bool)
    for p in (ankle, toe):
        speed = np.linalg.norm(np.gradient(p, 1.0 / sample_rate_hz, axis=0), axis=-1) if len(p) > 1 else np.zeros(1)
        still &= speed < STANCE_SPEED_M_S
        low &= p[:, 2] <= np.percentile(p[:, 2], 2) + STANCE_HEIGHT_M
    return still & low if (still & low).sum() >= MIN_STANCE_FRAMES else still


def _slowest_frames(ankle: np.ndarray, toe: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Frames ``(T,)`` bool where ankle and toe together move slowest (5 % of the clip, at least
    ``MIN_STANCE_FRAMES``): the foot's contact in a clip where it never stands flat long enough (a sprint)."""
    if len(ankle) < 2:
        return np.ones(len(ankle), dtype=bool)
    speed = sum(np.linalg.norm(np.gradient(p, 1.0 / sample_rate_hz, axis=0), axis=-1) for p in (ankle, toe))
    keep = np.zeros(len(ankle), dtype=bool)
    keep[np.argsort(speed)[: max(MIN_STANCE_FRAMES, len(ankle) // 20)]] = True
    return keep


def _foot_frame(ankle: np.ndarray, toe: np.ndarray) -> np.ndarray:
    """Level foot frames: x the horizontal ankle → toe heading, z up (meaningful where the foot stands flat)."""
    up = np.broadcast_to([0.0, 0.0, 1.0], ankle.shape)
    return _frame_z_x(up, toe - ankle)


def _rigid_offset(R_bone: np.ndarray, target: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Constant R_bone_segment: the rotation mean of R_bone⁻¹ · target over the frames where the target is
    well defined (``weight`` > 0: the long axis not along the anterior hint)."""
    rel = np.einsum("tji,tjk->tik", R_bone, target)
    keep = weight > 0.2
    if keep.sum() < 1:
        keep = np.ones_like(keep)
    return Rotation.from_matrix(rel[keep]).mean(weights=weight[keep]).as_matrix()


def body_motion(
    poses: GlobalPoses,
    mapping: SkeletonMapping,
    end_sites_m: dict[str, np.ndarray],
    offsets: np.ndarray | None = None,
) -> BodyMotion:
    """The canonical segments of one clip from its global joint poses.

    ``end_sites_m``: joint name → the end-site offset in the joint's local frame, metres (``bvh_end_sites``).
    ``offsets``: the rig's R_bone_segment per segment ``(S, 3, 3)`` (``rig_offsets``); without them each clip
    fits its own (``clip_offsets``, the spine rule), which moves with what the clip does (an arm's twist in a clip of
    raised arms).
    """
    R_offset = clip_offsets(poses, mapping, end_sites_m) if offsets is None else offsets
    P, R = poses.positions_m, poses.R_world_joint
    R_out = np.empty((len(P), len(BODY_SEGMENTS), 3, 3))
    for k, s in enumerate(BODY_SEGMENTS):
        R_out[:, k] = R[:, poses.index(mapping.segments[s][0])] @ R_offset[k]
    origin, mid = _segment_points(poses, mapping, end_sites_m)
    return BodyMotion(R_out, origin, mid, poses.sample_rate_hz)


def _segment_points(
    poses: GlobalPoses, mapping: SkeletonMapping, end_sites_m: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Segment origins and midpoints ``(T, S, 3)``."""
    P = poses.positions_m
    hip_centre = (P[:, poses.index(mapping.hips[0])] + P[:, poses.index(mapping.hips[1])]) / 2.0
    origin, mid = [], []
    for s in BODY_SEGMENTS:
        joint, distal = mapping.segments[s]
        p = P[:, poses.index(joint)]
        origin.append(p)
        if s == "Pelvis":
            mid.append((p + hip_centre) / 2.0)  # between the root joint and the hip centre
        elif distal is None or distal == END_SITE:
            mid.append(p)
        else:
            mid.append((p + P[:, poses.index(distal)]) / 2.0)
    return np.stack(origin, axis=1), np.stack(mid, axis=1)


def rig_offsets(per_clip: list[np.ndarray]) -> np.ndarray:
    """One R_bone_segment per segment for all clips of a rig ``(S, 3, 3)``: the rotation mean of the clips'
    own offsets, re-taken over the clips no farther from it than the median (a clip of raised arms cannot pull it).
    The bones of one rig are the same in every clip, so one offset gives every clip the same segment frames."""
    stack = np.stack(per_clip)  # (C, S, 3, 3)
    out = np.empty(stack.shape[1:])
    for k in range(stack.shape[1]):
        rot = Rotation.from_matrix(stack[:, k])
        mean = rot.mean()
        for _ in range(3):
            angle = (mean.inv() * rot).magnitude()
            mean = rot[angle <= np.median(angle) + 1e-12].mean()
        out[k] = mean.as_matrix()
    return out


def clip_offsets(
    poses: GlobalPoses,
    mapping: SkeletonMapping,
    end_sites_m: dict[str, np.ndarray],
    feet_at_slowest: bool = False,
    trunk_axes: str = "spine",
) -> np.ndarray:
    """Each segment's R_bone_segment ``(S, 3, 3)`` fitted on one clip: the rotation mean of R_bone⁻¹ · target.
    A foot that never stands flat raises ``NoStanceError``, or with ``feet_at_slowest`` is taken level where it
    moves slowest (its contact: an approximation for rigs of which no clip stands flat). ``trunk_axes`` names the
    upper trunk's targets (``_TRUNK_RULES``): "spine" from the rig's own spine and clavicle joints, "thorax" from
    the hip and shoulder joint centres."""
    mapping.check(poses.names)
    rules = {**_AXIS_RULE, **_TRUNK_RULES[check_trunk_axes(trunk_axes)]}
    P, R = poses.positions_m, poses.R_world_joint

    def pos(name: str, owner: str) -> np.ndarray:
        if name == END_SITE:
            if owner not in end_sites_m:
                raise MappingError(f"mapping {mapping.name!r}: joint {owner!r} has no end site")
            return P[:, poses.index(owner)] + R[:, poses.index(owner)] @ end_sites_m[owner]
        return P[:, poses.index(name)]

    l_hip, r_hip = P[:, poses.index(mapping.hips[0])], P[:, poses.index(mapping.hips[1])]
    up = np.broadcast_to([0.0, 0.0, 1.0], l_hip.shape)
    y_pelvis = _unit(l_hip - r_hip)
    heading = _unit(np.cross(y_pelvis, up))
    targets: dict[str, np.ndarray] = {"Pelvis": _frame_z_x(np.cross(heading, y_pelvis), heading)}
    weights: dict[str, np.ndarray] = {"Pelvis": np.ones(len(P))}
    hip_centre = (l_hip + r_hip) / 2.0
    shoulders = [P[:, poses.index(mapping.segments[f"{side}UpperArm"][0])] for side in ("Left", "Right")]
    shoulder_centre = (shoulders[0] + shoulders[1]) / 2.0
    for s in BODY_SEGMENTS:
        joint, distal = mapping.segments[s]
        p = pos(joint, joint)
        d = pos(distal, joint) if distal else None
        if s == "Pelvis":
            continue
        rule = rules[s]
        if rule == "parent":
            parent = BODY_PARENT[s]
            targets[s], weights[s] = targets[parent], weights[parent]
            continue
        length = np.median(np.linalg.norm(d - p, axis=-1))
        if length < 1e-3:
            raise MappingError(
                f"mapping {mapping.name!r}: segment {s} runs from {joint!r} to {distal!r}, which are "
                f"{length * 1000:.1f} mm apart; map it to joints a bone apart"
            )
        if rule == "trunk":
            d = P[:, poses.index(mapping.segments["Neck"][0])]
        elif rule == "thorax":
            p, d, rule = hip_centre, shoulder_centre, "trunk"
        axis = {"trunk": d - p, "up": d - p, "down": p - d, "left": d - p, "right": p - d, "foot": d - p}[rule]
        align = np.abs(np.sum(_unit(axis) * heading, -1))
        weights[s] = 1.0 - align
        if rule in ("trunk", "up", "down"):
            targets[s] = _frame_z_x(axis, heading)
        elif rule in ("left", "right"):
            targets[s] = _frame_y_x(axis, heading)
        else:  # foot: level while it stands flat
            flat = _flat_stance(p, d, poses.sample_rate_hz)
            if flat.sum() < MIN_STANCE_FRAMES and feet_at_slowest:
                flat = _slowest_frames(p, d, poses.sample_rate_hz)
            elif flat.sum() < MIN_STANCE_FRAMES:
                raise NoStanceError(
                    f"mapping {mapping.name!r}: segment {s} stands flat in {flat.sum()} frames of {len(P)} "
                    f"(at least {MIN_STANCE_FRAMES} define its frame); fit the frames on clips with standing or walking"
                )
            targets[s] = _foot_frame(p, d)
            weights[s] = flat.astype(float)
    out = np.empty((len(BODY_SEGMENTS), 3, 3))
    for k, s in enumerate(BODY_SEGMENTS):
        out[k] = _rigid_offset(R[:, poses.index(mapping.segments[s][0])], targets[s], weights[s])
    return out


def resample_motion(motion: BodyMotion, sample_rate_hz: float) -> BodyMotion:
    """Resample: orientations by slerp, positions by cubic spline (smooth second derivative: the accelerations
    of 30 fps Bandai-Namco clips are differentiated after this, ``../shared/data/README.md``)."""
    if np.isclose(motion.sample_rate_hz, sample_rate_hz):
        return motion
    n = motion.n_frames
    t_old = np.arange(n) / motion.sample_rate_hz
    # Frame times are rounded in the files (0.0333333 s): a last frame within 1e-3 of a sample is kept, at the end
    n_new = int(np.floor(t_old[-1] * sample_rate_hz + 1e-3)) + 1
    t_new = np.minimum(np.arange(n_new) / sample_rate_hz, t_old[-1])
    S = len(BODY_SEGMENTS)
    R = np.stack(
        [Slerp(t_old, Rotation.from_matrix(motion.R_world_segment[:, s]))(t_new).as_matrix() for s in range(S)], 1
    )
    spline = lambda a: CubicSpline(t_old, a, axis=0)(t_new)  # noqa: E731
    return BodyMotion(R, spline(motion.origin_m), spline(motion.midpoint_m), sample_rate_hz)


def segment_origins(R_world_segment: np.ndarray, offsets_m: np.ndarray, root_m: np.ndarray | None = None) -> np.ndarray:
    """Segment origins ``(T, S, 3)`` from orientations ``(T, S, 3, 3)`` and each segment's offset from its parent's
    origin in the parent's frame: one body ``(S, 3)``, or one per frame ``(T, S, 3)`` (several live sessions' frames
    computed together). The root at ``root_m`` or 0."""
    T = R_world_segment.shape[0]
    offsets = np.broadcast_to(offsets_m, (T, *np.shape(offsets_m)[-2:]))
    p = np.zeros((T, offsets.shape[1], 3))
    if root_m is not None:
        p[:, 0] = root_m
    for k in range(1, offsets.shape[1]):
        parent = PARENT_INDEX[k]
        p[:, k] = p[:, parent] + np.einsum("tij,tj->ti", R_world_segment[:, parent], offsets[:, k])
    return p


@dataclass(frozen=True)
class Body:
    """A skeleton for forward kinematics: per segment, its origin in its parent's frame (metres).

    offsets_m: (S, 3); the root's entry is unused. ``height_m`` is the standing height it implies
    (``standing_height``), so that a client's own height scales the body (``scaled``).
    """

    offsets_m: np.ndarray
    segments: tuple[str, ...] = field(default=BODY_SEGMENTS)

    def forward(self, R_world_segment: np.ndarray, root_m: np.ndarray | None = None) -> np.ndarray:
        """Segment origins ``(T, S, 3)`` from orientations ``(T, S, 3, 3)``; the root at ``root_m`` or 0."""
        return segment_origins(R_world_segment, self.offsets_m, root_m)

    def neutral_joints(self) -> np.ndarray:
        """Segment origins ``(S, 3)`` of the neutral stance (every segment frame = identity), the pelvis at 0."""
        return self.forward(np.broadcast_to(np.eye(3), (1, len(self.segments), 3, 3)))[0]

    @property
    def height_m(self) -> float:
        return standing_height(self)

    def scaled(self, height_m: float) -> Body:
        return Body(self.offsets_m * (height_m / self.height_m), self.segments)

    def to_json(self) -> dict:
        return {"segments": list(self.segments), "offsets_m": np.round(self.offsets_m, 5).tolist()}

    @classmethod
    def from_json(cls, d: dict) -> Body:
        if tuple(d["segments"]) != BODY_SEGMENTS:
            raise MappingError(f"a body lists the segments {list(BODY_SEGMENTS)}, got {d['segments']}")
        return cls(np.asarray(d["offsets_m"], dtype=np.float64))


def clip_body(motion: BodyMotion) -> Body:
    """The clip's own skeleton: each bone vector in its parent's frame, the median over frames (constant up to
    the rigs' intermediate joints, which the canonical body lumps into their segment)."""
    off = np.zeros((len(BODY_SEGMENTS), 3))
    for k in range(1, len(BODY_SEGMENTS)):
        parent = PARENT_INDEX[k]
        d = motion.origin_m[:, k] - motion.origin_m[:, parent]
        off[k] = np.median(np.einsum("tji,tj->ti", motion.R_world_segment[:, parent], d), axis=0)
    return Body(off)


def feet_of(body: Body) -> Feet:
    """The body's feet for its translation (``service.core.translation``): the ankles are the feet's origins, the
    balls the toes', and the ankle stands over the ball by their height difference in the neutral stance."""
    rest = body.neutral_joints()
    ankles = (body.segments.index("LeftFoot"), body.segments.index("RightFoot"))
    balls = (body.segments.index("LeftToe"), body.segments.index("RightToe"))
    height = float(np.mean([rest[a, 2] - rest[b, 2] for a, b in zip(ankles, balls, strict=True)]))
    return Feet(ankles, balls, max(height, 0.0))


def body_bvh(R_world_segment: np.ndarray, body: Body, sample_rate_hz: float, root_m: np.ndarray | None = None) -> Bvh:
    """Orientations ``(T, S, 3, 3)`` of the body's segments as a BVH clip that other tools open
    (``service.core.bvh.rotations_bvh``): one joint per segment (``BODY_SEGMENTS``' names and tree), its OFFSET the
    body's bone in centimetres. The world is the format's usual one, Y up (``service.core.kinematics.C_PROJECT_BVH``:
    the answers' x, y, z are the file's Z, X, Y), with the heading of the world the orientations are given in; each
    joint's frame is its segment's frame in those axes, so all angles 0 is the neutral stance, facing +Z. The root
    moves along ``root_m`` ``(T, 3)`` (the answers' translation, ``service.core.translation``), or without one
    stands still at the neutral pelvis height above the lowest segment origin (the toes); a leaf segment (head,
    hands, toes) ends half the length of the bone into it further on."""
    C = C_PROJECT_BVH  # project = C @ bvh
    R = np.einsum("ji,tsjk,kl->tsil", C, R_world_segment, C)  # each frame's axes in the BVH world
    offsets_cm = body.offsets_m @ C * 100.0  # C.T @ offset per segment
    if root_m is None:
        root_cm = np.array([0.0, -body.neutral_joints()[:, 2].min() * 100.0, 0.0])
    else:
        root_cm = np.asarray(root_m) @ C * 100.0  # C.T @ position per frame
    leaves = sorted(set(range(len(body.segments))) - set(PARENT_INDEX))
    ends = {k: 0.5 * offsets_cm[k] for k in leaves}
    return rotations_bvh(body.segments, PARENT_INDEX, offsets_cm, R, root_cm, 1.0 / sample_rate_hz, ends)


def standing_height(body: Body) -> float:
    """Height of the neutral pose (every segment frame = identity): head origin above the lowest toe origin,
    plus a head length of 0.12 of that span (anthropometric ratio, assumed)."""
    p = body.neutral_joints()
    span = p[BODY_SEGMENTS.index("Head"), 2] - p[:, 2].min()
    return float(span * 1.12)


def read_rig(path: str | Path, mapping: SkeletonMapping | None = None, source: str = ""):
    """A BVH file (plain or ``.gz``) as (global joint poses, mapping, end sites in metres)."""
    from service.core.bvh import read_bvh
    from service.core.kinematics import forward_kinematics

    bvh = read_bvh(path)
    names = tuple(j.name for j in bvh.joints)
    mapping = mapping or (mapping_for_source(source, names) if source else detect_mapping(names))
    mapping.check(names)
    poses = forward_kinematics(bvh, mapping.metres_per_unit, mapping.up_axis)
    _check_upright(poses, mapping, path)
    ends = {bvh.joints[j].name: off * mapping.metres_per_unit for j, off in bvh.end_sites.items()}
    return poses, mapping, ends


def _check_upright(poses: GlobalPoses, mapping: SkeletonMapping, path: str | Path) -> None:
    """The head well above the feet somewhere in the clip (in 5 % of its frames), else the clip's world has another
    vertical than the mapping says: a Z-up export read as Y-up would simulate gravity sideways and score nonsense
    without a word. (A clip lying down throughout cannot show its vertical and is refused too.)"""
    head = poses.positions_m[:, poses.index(mapping.segments["Head"][0])]
    feet = [poses.positions_m[:, poses.index(mapping.segments[f"{side}Foot"][0])] for side in ("Left", "Right")]
    rise = head[:, 2] - (feet[0][:, 2] + feet[1][:, 2]) / 2.0
    if np.percentile(rise, 95) < UPRIGHT_RISE_M:
        other = "z" if mapping.up_axis == "y" else "y"
        raise MappingError(
            f"{path}: read with {mapping.up_axis.upper()} up, the head is at most {np.percentile(rise, 95):+.2f} m "
            f"above the feet in 95 % of the frames; expected about 1.4 m where the person stands. If the file's "
            f'world is {other.upper()}-up, give a mapping file with "up_axis": "{other}" '
            "(service.core.body.load_mapping)"
        )


def read_body_motion(
    path: str | Path, mapping: SkeletonMapping | None = None, source: str = "", offsets: np.ndarray | None = None
) -> BodyMotion:
    """A BVH file on the canonical body, at its own rate; ``mapping`` or the source's; the rig's ``offsets``
    (``rig_offsets``) or the clip's own."""
    poses, mapping, ends = read_rig(path, mapping, source)
    return body_motion(poses, mapping, ends, offsets)


def read_clip_offsets(
    path: str | Path,
    mapping: SkeletonMapping | None = None,
    source: str = "",
    feet_at_slowest: bool = False,
    trunk_axes: str = "spine",
) -> np.ndarray:
    """The clip's own R_bone_segment per segment, the input of ``rig_offsets`` (``clip_offsets``)."""
    poses, mapping, ends = read_rig(path, mapping, source)
    return clip_offsets(poses, mapping, ends, feet_at_slowest, trunk_axes)
