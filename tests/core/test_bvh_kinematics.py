"""FK on every real BVH file of the three mocap sources (skeletons, units and rates differ)."""

from pathlib import Path

import numpy as np
import pytest

from service.core.bvh import BvhFormatError, read_bvh
from service.core.kinematics import forward_kinematics
from service.core.skeleton import segment_trajectories, skeleton_map_for
from training.data.catalog import METRES_PER_UNIT, read_catalog


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
    ],
)
def test_walking_is_plausible_in_the_project_frame(data_dir: Path, path: str) -> None:
    entry = next(e for e in read_catalog(data_dir) if e.path == path)
    poses = forward_kinematics(read_bvh(data_dir / path), METRES_PER_UNIT[entry.source])
    traj = segment_trajectories(poses, skeleton_map_for(entry.source, poses.names))
    skip = entry.tpose_frames
    pelvis, feet = traj.origin_m[skip:, 3], traj.origin_m[skip:, [0, 6]]
    assert np.all(feet[..., 2] < pelvis[:, None, 2]), "ankles must stay below the pelvis"
    assert 0.8 < np.median(pelvis[:, 2]) - np.median(feet[..., 2]) < 1.1
    # Segment frames: z superior, pelvis x along the direction of travel (x forward, y left).
    assert np.median(traj.R_world_segment[skip:, :, 2, 2]) > 0.85
    if "walk" in entry.activity:
        v = np.diff(pelvis[:, :2], axis=0) * traj.sample_rate_hz
        speed = np.linalg.norm(v, axis=1)
        assert 0.5 < np.median(speed) < 2.0, f"walking speed {np.median(speed):.2f} m/s"
        heading = traj.R_world_segment[skip + 1 :, 3, :2, 0]
        cos = np.sum(heading * v, axis=1) / (np.linalg.norm(heading, axis=1) * speed + 1e-9)
        assert np.median(cos) > 0.9


def test_truncated_file_is_a_clear_error(tmp_path: Path, data_dir: Path) -> None:
    text = (data_dir / "mocap/cmu_raw/131_01.bvh").read_text()
    bad = tmp_path / "bad.bvh"
    bad.write_text(text[: len(text) // 2])
    with pytest.raises(BvhFormatError, match="expected .* values"):
        read_bvh(bad)
