"""The canonical body: every mocap family maps onto it with anatomical frames and constant bones."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.core.body import (
    BODY_SEGMENTS,
    PARENT_INDEX,
    SKELETON_MAPPINGS,
    MappingError,
    clip_body,
    detect_mapping,
    load_mapping,
    read_body_motion,
    resample_motion,
)
from service.core.bvh import read_bvh

# One walk (or the family's only clip type) per skeleton family, as the catalogue names them.
FAMILY_CLIPS = {
    "cmu_li2018": ("mocap/cmu_li2018/walking/train_walking_1.bvh", "cmu_li2018"),
    "cmu_iclone": ("mocap/cmu_iclone/07_01.bvh", "cmu_iclone"),
    "cmu_raw_mb": ("mocap/cmu_raw/01_01.bvh", "cmu_raw"),
    "cmu_raw_3dsmax": ("mocap/cmu_raw/131_01.bvh", "cmu_raw"),
    "bandai_namco_1": ("mocap/bandai_namco/dataset-1/dataset-1_walk_normal_001.bvh.gz", "bandai_namco_1"),
    "bandai_namco_2": ("mocap/bandai_namco/dataset-2/dataset-2_walk_normal_001.bvh.gz", "bandai_namco_2"),
}
MAJOR_BONES = ("LeftUpperLeg", "LeftLowerLeg", "RightUpperLeg", "RightLowerLeg", "LeftForeArm", "RightForeArm")


@pytest.mark.parametrize("family", sorted(FAMILY_CLIPS))
def test_every_family_keeps_its_bone_lengths_and_stands_like_a_person(data_dir: Path, family: str) -> None:
    path, source = FAMILY_CLIPS[family]
    motion = read_body_motion(data_dir / path, source=source)
    assert motion.R_world_segment.shape == (motion.n_frames, len(BODY_SEGMENTS), 3, 3)
    for name in MAJOR_BONES:
        k = BODY_SEGMENTS.index(name)
        child = PARENT_INDEX.index(k)
        length = np.linalg.norm(motion.origin_m[:, child] - motion.origin_m[:, k], axis=-1)
        assert 0.18 < np.median(length) < 0.55, (name, np.median(length))
        assert length.std() < 2e-3, (name, length.std())  # rigid: the Bandai doubled-offset bug would not be
    # forward kinematics with the clip's own bones reproduces the hips, knees and ankles
    body = clip_body(motion)
    p = body.forward(motion.R_world_segment, motion.origin_m[:, 0])
    legs = [BODY_SEGMENTS.index(s) for s in BODY_SEGMENTS if s.endswith(("UpperLeg", "LowerLeg", "Foot"))]
    assert np.abs(p[:, legs] - motion.origin_m[:, legs]).max() < 0.02
    # Bandai-Namco's position channels replace the offsets: the pelvis stands about 0.9 m high, not 1.8 m
    assert 0.75 < np.median(motion.origin_m[:, 0, 2] - motion.origin_m[:, :, 2].min(axis=1)) < 1.15
    assert 1.4 < body.height_m < 2.0


@pytest.mark.parametrize("family", ["cmu_li2018", "cmu_iclone", "bandai_namco_2"])
def test_segment_frames_are_anatomical_in_walking(data_dir: Path, family: str) -> None:
    """docs/conventions.md: z superior and x anterior in stance; walking keeps every major segment near that."""
    path, source = FAMILY_CLIPS[family]
    R = read_body_motion(data_dir / path, source=source).R_world_segment
    z_up = np.median(R[..., 2, 2], axis=0)  # world z of each segment's z axis
    x_fwd = np.median(np.einsum("tsi,ti->ts", R[..., 0], R[:, 0, :, 0]), axis=0)  # x against the pelvis's x
    for name in ("Pelvis", "L5", "T8", "Head", "LeftUpperLeg", "RightLowerLeg", "LeftUpperArm", "RightFoot"):
        k = BODY_SEGMENTS.index(name)
        assert z_up[k] > 0.85 and x_fwd[k] > 0.8, (name, z_up[k], x_fwd[k])


def test_a_mapping_file_maps_a_skeleton_like_the_built_in_table(data_dir: Path, tmp_path: Path) -> None:
    built_in = SKELETON_MAPPINGS["cmu_li2018"]
    spec = {
        "name": "my_li2018",
        "metres_per_unit": 1.0,
        "hips": list(built_in.hips),
        "segments": {s: {"joint": j, "distal": d} for s, (j, d) in built_in.segments.items()},
    }
    (tmp_path / "map.json").write_text(json.dumps(spec))
    path = data_dir / FAMILY_CLIPS["cmu_li2018"][0]
    a = read_body_motion(path, load_mapping(tmp_path / "map.json"))
    b = read_body_motion(path, source="cmu_li2018")
    np.testing.assert_allclose(a.R_world_segment, b.R_world_segment)
    del spec["segments"]["LeftHand"]
    (tmp_path / "bad.json").write_text(json.dumps(spec))
    with pytest.raises(MappingError, match="missing \\['LeftHand'\\]"):
        read_body_motion(path, load_mapping(tmp_path / "bad.json"))


def test_unknown_skeletons_ask_for_a_mapping_and_known_ones_are_detected(data_dir: Path) -> None:
    bvh = read_bvh(data_dir / FAMILY_CLIPS["cmu_iclone"][0])
    assert detect_mapping(tuple(j.name for j in bvh.joints)).name == "cmu_iclone"
    with pytest.raises(MappingError, match="--mapping"):
        detect_mapping(("Root", "Spine", "Arm"))


def test_resampling_bandai_to_60_hz_keeps_the_clip(data_dir: Path) -> None:
    path, source = FAMILY_CLIPS["bandai_namco_2"]
    m30 = read_body_motion(data_dir / path, source=source)
    m60 = resample_motion(m30, 60.0)
    assert round(m30.sample_rate_hz) == 30 and m60.n_frames == 2 * m30.n_frames - 1
    # the spline passes through the samples (to the files' rounding of the frame time, 0.0333333 s)
    np.testing.assert_allclose(m60.origin_m[::2], m30.origin_m, atol=1e-4)
    np.testing.assert_allclose(m60.R_world_segment[::2], m30.R_world_segment, atol=1e-3)


def test_the_clips_of_one_rig_share_their_segment_frames(data_dir: Path) -> None:
    """Fitted per clip, an arm's twist follows what the clip does (raised arms, a dance); one offset per rig
    gives every clip the same segment frame on the same bone."""
    from service.core.body import read_clip_offsets, read_rig, rig_offsets

    paths = [data_dir / "mocap/cmu_iclone" / n for n in ("05_02.bvh", "06_04.bvh", "07_01.bvh", "02_01.bvh")]
    per_clip = [read_clip_offsets(p, source="cmu_iclone") for p in paths]
    rig = rig_offsets(per_clip)
    arm = BODY_SEGMENTS.index("LeftUpperArm")
    spread = [np.degrees(np.arccos(np.clip((np.trace(rig[arm].T @ o[arm]) - 1) / 2, -1, 1))) for o in per_clip]
    assert max(spread) > 3.0  # the clips disagree on their own ...
    for p in paths[:2]:
        poses, mapping, _ = read_rig(p, source="cmu_iclone")
        motion = read_body_motion(p, source="cmu_iclone", offsets=rig)
        R_bone = poses.R_world_joint[:, poses.index(mapping.segments["LeftUpperArm"][0])]
        np.testing.assert_allclose(
            np.einsum("tji,tjk->tik", R_bone, motion.R_world_segment[:, arm]),
            rig[arm][None].repeat(len(R_bone), 0),
            atol=1e-9,
        )


def _flat_foot_pitch_deg(motion, side: str) -> float:
    """Median pitch of the foot's x axis over the frames where the foot stands flat (toe still and at its lowest)."""
    k, toe = BODY_SEGMENTS.index(f"{side}Foot"), BODY_SEGMENTS.index(f"{side}Toe")
    p = motion.origin_m[:, toe]
    speed = np.linalg.norm(np.gradient(p, 1.0 / motion.sample_rate_hz, axis=0), axis=-1)
    flat = (speed < 0.1) & (p[:, 2] < np.percentile(p[:, 2], 5) + 0.02)
    assert flat.sum() > 10
    return float(np.degrees(np.median(np.arcsin(np.clip(motion.R_world_segment[flat, k, 2, 0], -1, 1)))))


def test_feet_are_level_when_they_stand_flat_on_every_rig(data_dir: Path) -> None:
    """Rigs put the toe joint at different heights: with a fixed ankle → toe pitch Bandai-Namco's flat feet read
    about 16° toes-down and CMU's 5-15° toes-up. The foot frame is level in flat stance (conventions.md) on the rig's
    frames fitted on some of its walks, and on another walk of the same rig."""
    from service.core.body import read_clip_offsets, rig_offsets

    rigs = {
        "bandai_namco_2": [f"mocap/bandai_namco/dataset-2/dataset-2_walk_normal_00{i}.bvh.gz" for i in (1, 2, 3, 4)],
        "cmu_iclone": [f"mocap/cmu_iclone/{n}.bvh" for n in ("07_01", "07_02", "06_01", "05_01")],
    }
    for source, paths in rigs.items():
        rig = rig_offsets([read_clip_offsets(data_dir / p, source=source) for p in paths[:3]])
        motion = read_body_motion(data_dir / paths[3], source=source, offsets=rig)
        for side in ("Left", "Right"):
            assert abs(_flat_foot_pitch_deg(motion, side)) < 6.0, (source, side)


def test_a_z_up_file_reads_upright_through_its_mapping_and_is_refused_read_as_y_up(
    data_dir: Path, tmp_path: Path
) -> None:
    """An iClone walk turned into a Z-up world (as some exporters write BVH): read with ``up_axis`` "z" its heights
    are the Y-up file's; read as Y-up it is refused with the fix in the message, not scored sideways."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    from service.core.body import _check_upright
    from service.core.kinematics import forward_kinematics

    bvh = read_bvh(data_dir / "mocap/cmu_iclone/07_01.bvh")
    M = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # the Y-up world's y becomes z
    root = bvh.joints[0]
    assert [c for c in root.channels if c.endswith("position")] == ["Xposition", "Yposition", "Zposition"]
    motion = bvh.motion.copy()
    pos = [root.channel_start + k for k, c in enumerate(root.channels) if c.endswith("position")]
    rot = [root.channel_start + k for k, c in enumerate(root.channels) if c.endswith("rotation")]
    order = "".join(c[0].upper() for c in root.channels if c.endswith("rotation"))
    motion[:, pos] = motion[:, pos] @ M.T
    R = Rotation.from_euler(order, motion[:, rot], degrees=True).as_matrix()
    motion[:, rot] = Rotation.from_matrix(M @ R).as_euler(order, degrees=True)
    z_up = replace(bvh, joints=(replace(root, offset=M @ root.offset), *bvh.joints[1:]), motion=motion)

    mapping = SKELETON_MAPPINGS["cmu_iclone"]
    as_made = forward_kinematics(bvh, mapping.metres_per_unit)
    read = forward_kinematics(z_up, mapping.metres_per_unit, "z")
    # the same world turned a quarter about the vertical (a proper rotation: left stays left)
    Rz = Rotation.from_euler("z", -90, degrees=True).as_matrix()
    np.testing.assert_allclose(read.positions_m, as_made.positions_m @ Rz.T, atol=1e-6)
    _check_upright(read, replace(mapping, up_axis="z"), "z_up.bvh")
    with pytest.raises(MappingError, match='"up_axis": "z"'):
        _check_upright(forward_kinematics(z_up, mapping.metres_per_unit), mapping, "z_up.bvh")

    raw = {"metres_per_unit": 0.01, "hips": ["a", "b"], "segments": {}, "up_axis": "Z"}
    (tmp_path / "z.json").write_text(json.dumps(raw))
    assert load_mapping(tmp_path / "z.json").up_axis == "z"
    (tmp_path / "x.json").write_text(json.dumps(raw | {"up_axis": "x"}))
    with pytest.raises(MappingError, match="'x'"):
        load_mapping(tmp_path / "x.json")


def test_a_pose_as_bvh_reads_back_as_the_same_segment_frames_and_joint_positions(tmp_path: Path) -> None:
    """``body_bvh``: any orientations (a joint turned 90° about its Y included, where Euler angles lock), written and
    read back by the BVH reader and forward kinematics, are the same frames (in the BVH world's axes) and origins;
    the neutral stance stands upright on the lowest origin."""
    from scipy.spatial.transform import Rotation

    from service.core.body import Body, body_bvh
    from service.core.bvh import format_bvh, read_bvh
    from service.core.kinematics import C_PROJECT_BVH, forward_kinematics

    rng = np.random.default_rng(0)
    S = len(BODY_SEGMENTS)
    offsets = rng.uniform(-0.05, 0.05, size=(S, 3))
    offsets[:, 2] += np.array([-0.2 if "Leg" in s or "Foot" in s or "Arm" in s else 0.1 for s in BODY_SEGMENTS])
    body = Body(offsets)
    R = Rotation.random(30 * S, random_state=1).as_matrix().reshape(30, S, 3, 3)
    R[0] = np.eye(3)
    R[1, 5] = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    R[2, 7] = R[2, 6] @ Rotation.from_euler("y", -90, degrees=True).as_matrix()  # its parent-relative turn locks
    (tmp_path / "pose.bvh").write_text(format_bvh(body_bvh(R, body, 60.0)))
    bvh = read_bvh(tmp_path / "pose.bvh")
    assert [j.name for j in bvh.joints] == list(BODY_SEGMENTS) and bvh.sample_rate_hz == pytest.approx(60.0)
    assert set(bvh.end_sites) == {
        BODY_SEGMENTS.index(s) for s in ("Head", "LeftHand", "RightHand", "LeftToe", "RightToe")
    }
    poses = forward_kinematics(bvh, 0.01, "y")
    np.testing.assert_allclose(poses.R_world_joint @ C_PROJECT_BVH.T, R, atol=1e-5)
    p = poses.positions_m
    np.testing.assert_allclose(p - p[:, :1], body.forward(R), atol=1e-5)
    assert p[0, :, 2].min() == pytest.approx(0.0, abs=1e-5) and p[0, 0, 2] > 0.1  # upright on the lowest origin


def test_li2018_hands_bend_at_the_wrist() -> None:
    """In li2018's skeleton (CMU's ASF) the wrist joint's bone has no length and turns only about the forearm's
    axis; the palm is the hand joint's bone, to the fingers. Read so, a walk's hands turn against the forearms
    about more than one axis (the wrist's flexion and deviation, not only the twist) and their sensors sit on the
    palm, not at the wrist."""
    from scipy.spatial.transform import Rotation

    motion = read_body_motion(
        Path(__file__).resolve().parents[1] / "fixtures" / "cmu_02_01_walk_2s.bvh", None, "cmu_li2018"
    )
    for side in ("Left", "Right"):
        forearm, hand = BODY_SEGMENTS.index(f"{side}ForeArm"), BODY_SEGMENTS.index(f"{side}Hand")
        rel = Rotation.from_matrix(
            np.einsum("tji,tjk->tik", motion.R_world_segment[:, forearm], motion.R_world_segment[:, hand])
        )
        turns = (rel.mean().inv() * rel).as_rotvec(degrees=True)
        spread = np.linalg.svd(turns - turns.mean(0), compute_uv=False) / np.sqrt(len(turns))
        assert spread[1] > 0.5, spread  # one axis only: 1e-15
        palm = np.linalg.norm(motion.midpoint_m[:, hand] - motion.origin_m[:, hand], axis=1)
        assert np.all(palm > 0.01), palm.min()
