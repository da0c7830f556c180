"""FK on every real BVH file of the three CMU sources, and Bandai-Namco walks (skeletons, units and rates differ)."""

from pathlib import Path

import numpy as np
import pytest

from service.core.bvh import BvhFormatError, read_bvh
from service.core.kinematics import forward_kinematics
from service.core.skeleton import segment_trajectories, skeleton_map_for
from training.data.catalog import METRES_PER_UNIT, read_catalog

WALK_FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "cmu_02_01_walk_2s.bvh"


def _all_bvh(data_dir: Path):
    return [e for e in read_catalog(data_dir) if e.path.endswith(".bvh")]


def test_every_bvh_file_parses_and_keeps_bone_lengths(data_dir: Path) -> None:
    entries = _all_bvh(data_dir)
    assert len(entries) == 161
    for e in entries:
        bvh = read_bvh(data_dir / e.path)
        assert np.isclose(bvh.sample_rate_hz, e.fps, rtol=1e-3), f"{e.path}: {bvh.sample_rate_hz} Hz"
        poses = forward_kinematics(bvh, METRES_PER_UNIT[e.source])
        sk = skeleton_map_for(e.source, poses.names)
        for joints in (sk.left, sk.right):
            for parent, child in zip(joints[:-1], joints[1:], strict=True):
                length = np.linalg.norm(
                    poses.positions_m[:, poses.index(child)] - poses.positions_m[:, poses.index(parent)], axis=1
                )
                assert np.ptp(length) < 1e-6, f"{e.path}: {parent}->{child} length varies by {np.ptp(length)}"
                assert 0.03 < length.mean() < 0.6, f"{e.path}: {parent}->{child} is {length.mean():.3f} m"


@pytest.mark.parametrize(
    "path",
    [
        "mocap/cmu_li2018/walking/train_walking_1.bvh",
        "mocap/cmu_iclone/05_01.bvh",
        "mocap/cmu_iclone/07_05.bvh",
        "mocap/cmu_raw/01_01.bvh",
        "mocap/bandai_namco/dataset-2/dataset-2_walk_active_001.bvh.gz",
    ],
)
def test_walking_is_plausible_in_the_project_frame(data_dir: Path, path: str) -> None:
    entry = next(e for e in read_catalog(data_dir) if e.path == path)
    poses = forward_kinematics(read_bvh(data_dir / path), METRES_PER_UNIT[entry.source])
    traj = segment_trajectories(poses, skeleton_map_for(entry.source, poses.names))
    skip = entry.tpose_frames
    pelvis, feet = traj.origin_m[skip:, 3], traj.origin_m[skip:, [0, 6]]
    assert np.all(feet[..., 2] < pelvis[:, None, 2]), "ankles must stay below the pelvis"
    assert 0.7 < np.median(pelvis[:, 2]) - np.median(feet[..., 2]) < 1.1  # Bandai-Namco actors: 0.73 m
    # Segment frames: z superior, pelvis x along the direction of travel (x forward, y left).
    assert np.median(traj.R_world_segment[skip:, :, 2, 2]) > 0.85
    if "walk" in entry.activity:
        v = np.diff(pelvis[:, :2], axis=0) * traj.sample_rate_hz
        speed = np.linalg.norm(v, axis=1)
        assert 0.5 < np.median(speed) < 2.0, f"walking speed {np.median(speed):.2f} m/s"
        heading = traj.R_world_segment[skip + 1 :, 3, :2, 0]
        cos = np.sum(heading * v, axis=1) / (np.linalg.norm(heading, axis=1) * speed + 1e-9)
        assert np.median(cos) > 0.9


def test_the_walk_fixture_is_plausible_in_the_project_frame() -> None:
    """The same checks on the 2 s fixture (CMU 02_01 at 60 Hz), which needs no data directory."""
    poses = forward_kinematics(read_bvh(WALK_FIXTURE), METRES_PER_UNIT["cmu_li2018"])
    assert poses.positions_m.shape[0] == 120 and np.isclose(poses.sample_rate_hz, 60.0, rtol=1e-6)
    traj = segment_trajectories(poses, skeleton_map_for("cmu_li2018", poses.names))
    pelvis, feet = traj.origin_m[:, 3], traj.origin_m[:, [0, 6]]
    assert np.all(feet[..., 2] < pelvis[:, None, 2])
    assert 0.7 < np.median(pelvis[:, 2]) - np.median(feet[..., 2]) < 1.1
    v = np.diff(pelvis[:, :2], axis=0) * traj.sample_rate_hz
    assert 0.9 < np.median(np.linalg.norm(v, axis=1)) < 1.5  # CMU 02_01 walks at about 1.2 m/s


def test_truncated_file_is_a_clear_error(tmp_path: Path) -> None:
    text = WALK_FIXTURE.read_text()
    bad = tmp_path / "bad.bvh"
    bad.write_text(text[: len(text) // 2])
    with pytest.raises(BvhFormatError, match="expected .* values"):
        read_bvh(bad)


def _hinge_trajectories(axis: np.ndarray, n: int = 1200, rate: float = 60.0):
    """Seven segments swinging about ``axis`` (segment frame) like legs in gait, the pelvis walking along x."""
    from scipy.spatial.transform import Rotation

    from service.core.skeleton import SegmentTrajectories

    t = np.arange(n) / rate
    swing = 0.5 * np.sin(2 * np.pi * 0.9 * t) + 0.05 * np.sin(2 * np.pi * 2.7 * t)  # rad
    wobble = 0.03 * np.sin(2 * np.pi * 1.8 * t)  # a little rotation about z, as real gait has
    R_seg = Rotation.from_rotvec(swing[:, None] * axis) * Rotation.from_rotvec(wobble[:, None] * np.array([0, 0, 1.0]))
    R = np.repeat(R_seg.as_matrix()[:, None], 7, axis=1)
    R[:, 3] = Rotation.from_rotvec(wobble[:, None] * np.array([0, 0, 1.0])).as_matrix()
    origin = np.zeros((n, 7, 3))
    origin[:, :, 0] = 1.2 * t[:, None]  # 1.2 m/s along world x
    return SegmentTrajectories(R, origin, origin.copy(), rate)


def test_functional_frames_find_a_known_flexion_axis_and_direction_of_travel() -> None:
    """Segments that flex about an axis 12° off the geometric y get y on that axis; the pelvis, whose geometric
    frame is turned 8° from the direction of travel, gets x along it."""
    from scipy.spatial.transform import Rotation

    from service.core.skeleton import SegmentTrajectories, functional_correction

    turn = Rotation.from_euler("z", 12, degrees=True).as_matrix()
    axis = turn[:, 1]  # the hinge in the geometric segment frame
    traj = _hinge_trajectories(axis)
    pelvis_off = Rotation.from_euler("z", 8, degrees=True).as_matrix()
    R = traj.R_world_segment.copy()
    R[:, 3] = R[:, 3] @ pelvis_off  # geometric pelvis frame turned 8° about z from the body
    corr = functional_correction(SegmentTrajectories(R, traj.origin_m, traj.midpoint_m, traj.sample_rate_hz))
    for k in (1, 2, 4, 5):  # the legs: y onto the hinge, z kept
        np.testing.assert_allclose(corr.R_geometric_functional[k][:, 1], axis, atol=2e-3)
        np.testing.assert_allclose(corr.R_geometric_functional[k][:, 2], [0, 0, 1], atol=1e-9)
    for k in (0, 6):  # the feet: y onto the hinge too (the flat-foot up is ~z here)
        assert abs(corr.R_geometric_functional[k][:, 1] @ axis) > 0.999
    np.testing.assert_allclose(corr.angle_deg[3], 8.0, atol=0.1)
    x_pelvis_world = np.einsum("tij,j->ti", R[:, 3] @ corr.R_geometric_functional[3], [1.0, 0.0, 0.0])
    assert np.median(x_pelvis_world[:, 0]) > 0.9995  # along the direction of travel


@pytest.mark.parametrize("path", ["mocap/cmu_iclone/07_05.bvh", "mocap/cmu_li2018/walking/train_walking_1.bvh"])
def test_functional_frames_on_real_walking_are_small_turns_and_a_fixed_point(data_dir: Path, path: str) -> None:
    """On real walking the functional frames sit within 25° of the geometric ones (measured 0-19°, the feet
    most), and computing them again from the corrected frames changes nothing for the legs and the pelvis."""
    from service.core.skeleton import functional_correction, functional_frames
    from training.i2s.data.mocap import geometric_trajectories

    entry = next(e for e in read_catalog(data_dir) if e.path == path)
    corrected, corr = functional_frames(geometric_trajectories(data_dir / path, entry))
    assert np.all(corr.angle_deg < 25.0), corr.angle_deg
    assert np.any(corr.angle_deg > 1.0), "the geometric frames are not already functional"
    again = functional_correction(corrected)
    np.testing.assert_allclose(again.angle_deg[1:6], 0.0, atol=1e-6)


@pytest.mark.parametrize(
    "path",
    ["mocap/cmu_li2018/walking/train_walking_1.bvh", "mocap/bandai_namco/dataset-2/dataset-2_walk_active_001.bvh.gz"],
)
def test_the_header_alone_is_the_file_s_skeleton(data_dir: Path, path: str) -> None:
    from service.core.bvh import read_bvh_header

    whole, (header, frames) = read_bvh(data_dir / path), read_bvh_header(data_dir / path)
    assert [j.name for j in header.joints] == [j.name for j in whole.joints] and len(header.motion) == 0
    assert frames == len(whole.motion) and header.frame_time_s == whole.frame_time_s
    for a, b in zip(header.joints, whole.joints, strict=True):
        assert a.parent == b.parent and a.channels == b.channels and np.array_equal(a.offset, b.offset)
    assert header.end_sites.keys() == whole.end_sites.keys()


def test_a_written_file_reads_back_as_it_was(tmp_path: Path) -> None:
    """``format_bvh`` of the CMU walk fixture (root with six channels, end sites) reads back to the same skeleton
    and frames, to the four decimals it writes."""
    from service.core.bvh import format_bvh

    bvh = read_bvh(WALK_FIXTURE)
    (tmp_path / "again.bvh").write_text(format_bvh(bvh))
    again = read_bvh(tmp_path / "again.bvh")
    assert [(j.name, j.parent, j.channels) for j in again.joints] == [
        (j.name, j.parent, j.channels) for j in bvh.joints
    ]
    np.testing.assert_allclose([j.offset for j in again.joints], [j.offset for j in bvh.joints], atol=5e-5)
    assert again.end_sites.keys() == bvh.end_sites.keys()
    assert again.frame_time_s == pytest.approx(bvh.frame_time_s, abs=1e-8)
    np.testing.assert_allclose(again.motion, bvh.motion, atol=5e-5)
    a, b = forward_kinematics(again, 0.0254), forward_kinematics(bvh, 0.0254)
    np.testing.assert_allclose(a.positions_m, b.positions_m, atol=1e-5)


def test_euler_angles_rebuild_every_rotation_also_where_they_lock() -> None:
    from scipy.spatial.transform import Rotation

    from service.core.bvh import euler_zyx_deg

    R = Rotation.random(200, random_state=3).as_matrix()
    locked = Rotation.from_euler("ZYX", [[30.0, 90.0, 50.0], [-120.0, -90.0, 10.0], [0.0, 90.0, 0.0]], degrees=True)
    R = np.concatenate([R, locked.as_matrix()])
    angles = euler_zyx_deg(R)
    np.testing.assert_allclose(Rotation.from_euler("ZYX", angles, degrees=True).as_matrix(), R, atol=1e-6)
    assert np.all(np.abs(angles[:, 1]) <= 90.0) and np.all(angles[-3:, 2] == 0.0)


def test_a_skeleton_out_of_file_order_is_refused() -> None:
    from service.core.bvh import Bvh, BvhJoint, format_bvh

    joints = (
        BvhJoint("r", -1, np.zeros(3), ("Zrotation",), 0),
        BvhJoint("a", 0, np.ones(3), ("Zrotation",), 1),
        BvhJoint("b", 0, np.ones(3), ("Zrotation",), 2),
        BvhJoint("a1", 1, np.ones(3), ("Zrotation",), 3),  # the file would list it before b
    )
    with pytest.raises(ValueError, match="depth-first"):
        format_bvh(Bvh(joints, {}, 0.01, np.zeros((2, 4))))
