"""Property tests of the Zimmermann et al. 2018 simulation that can fail: rest, known spin, gyro integration."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from service.core.skeleton import SegmentTrajectories
from training.i2s.data.imu_sim import (
    ALIGNMENT_AXES,
    ClipTooShort,
    SensorSpec,
    alignment_grid,
    body_angular_velocity,
    imu_readings,
    mirrored,
    mirrored_readings,
    quantise,
    segment_kinematics,
)

RATE = 60.0


def _trajectory(R: np.ndarray, pos: np.ndarray) -> SegmentTrajectories:
    """All seven segments share the same pose: (T, 3, 3) and (T, 3)."""
    Rs = np.repeat(R[:, None], 7, axis=1)
    p = np.repeat(pos[:, None], 7, axis=1)
    return SegmentTrajectories(Rs, p, p, RATE)


def test_a_clip_too_short_for_the_zero_lag_filter_is_refused_by_name_and_one_just_long_enough_is_simulated() -> None:
    """Some Bandai-Namco clips last under a second: at 30 fps the order-8 filter's edge padding needs 28 frames."""

    def still(n: int) -> SegmentTrajectories:
        R, p = np.repeat(np.eye(3)[None, None], n, axis=0).repeat(7, axis=1), np.zeros((n, 7, 3))
        return SegmentTrajectories(R, p, p, 30.0)

    with pytest.raises(ClipTooShort, match="27 frames"):
        segment_kinematics(still(27))
    kin = segment_kinematics(still(28))
    assert kin.R_world_segment.shape[1] == 7 and kin.sample_rate_hz == RATE


def _readings(kin, segment: int, R_si: np.ndarray) -> np.ndarray:
    take = lambda a: a[None, :, segment]  # noqa: E731
    return imu_readings(
        take(kin.lin_acc_mps2), take(kin.up_mps2), take(kin.gyr_rads), take(kin.ang_acc_rads2), R_si[None]
    )[0]


@given(st.lists(st.floats(-np.pi, np.pi), min_size=3, max_size=3))
@settings(max_examples=25, deadline=None)
def test_resting_sensor_reads_g_along_world_up(euler: list[float]) -> None:
    T = 200
    R_ws = np.repeat(Rotation.from_euler("xyz", euler).as_matrix()[None], T, 0)
    kin = segment_kinematics(_trajectory(R_ws, np.zeros((T, 3))), RATE)
    R_si = alignment_grid(2)[5]
    imu = _readings(kin, 2, R_si)
    up_in_sensor = (R_ws[0] @ R_si).T @ np.array([0, 0, 1.0])
    np.testing.assert_allclose(imu[:, :3], np.tile(9.81 * up_in_sensor, (T, 1)), atol=1e-6)
    np.testing.assert_allclose(imu[:, 3:], 0.0, atol=1e-9)


def test_sensor_spun_at_known_rate_reads_it() -> None:
    T, rate_rads = 300, 2.0
    t = np.arange(T) / RATE
    R_ws = Rotation.from_rotvec(np.outer(rate_rads * t, [0, 0, 1.0])).as_matrix()
    kin = segment_kinematics(_trajectory(R_ws, np.zeros((T, 3))), RATE)
    R_si = alignment_grid(1)[9]
    imu = _readings(kin, 1, R_si)
    expected = R_si.T @ np.array([0, 0, rate_rads])
    mid = slice(40, -40)  # away from the filter's edges
    np.testing.assert_allclose(imu[mid, 3:], np.tile(expected, (T - 80, 1)), atol=1e-3)


def test_integrating_the_gyroscope_reproduces_the_orientation() -> None:
    T = 240
    t = np.arange(T) / RATE
    rotvec = np.stack([0.6 * np.sin(2 * np.pi * 0.8 * t), 0.3 * np.sin(2 * np.pi * 1.3 * t), 0.5 * t], axis=1)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    gyr = body_angular_velocity(R, RATE)
    est = Rotation.from_matrix(R[0])
    for k in range(T - 1):  # midpoint rule: the mean of the rates at both ends of the step
        est = est * Rotation.from_rotvec((gyr[k] + gyr[k + 1]) / 2 / RATE)
    err = np.degrees((est.inv() * Rotation.from_matrix(R[-1])).magnitude())
    assert err < 0.5, f"integrated orientation off by {err:.3f} deg after 4 s"


def test_alignment_grid_follows_eq8() -> None:
    for seg in range(7):
        grid = alignment_grid(seg)
        assert grid.shape == (64, 3, 3)
        np.testing.assert_allclose(np.linalg.det(grid), 1.0, atol=1e-9)
        quats = Rotation.from_matrix(grid).as_quat()
        distinct = {tuple(np.round(q * np.sign(q[np.argmax(np.abs(q))]), 6)) for q in quats}
        assert len(distinct) == 64
        # the sensor's z axis (surface normal) stays perpendicular to the rotation axis a
        np.testing.assert_allclose(grid[:, :, 2] @ ALIGNMENT_AXES[seg], 0.0, atol=1e-9)


def test_quantisation_clips_and_rounds() -> None:
    spec = SensorSpec()
    out = quantise(np.array([[500.0, 0.00001, -3.0, 100.0, 0.0, 0.1]]), spec)
    assert abs(out[0, 0] - spec.acc_range_mps2) < 0.01
    assert out[0, 1] == 0.0
    assert abs(out[0, 3] - spec.gyr_range_rads) < 1e-3


def test_mirrored_kinematics_are_those_of_the_mirrored_mocap(data_dir) -> None:
    """``mirrored`` (closed form on cached kinematics) equals simulating the mocap reflected through a vertical
    plane with the skeleton's sides swapped: the mirror image is a left/right-swapped body, not a guess. The
    functional segment frames are part of it: they reflect with the body."""
    from service.core.bvh import read_bvh
    from service.core.kinematics import GlobalPoses, forward_kinematics
    from service.core.skeleton import SkeletonMap, functional_frames, segment_trajectories, skeleton_map_for
    from training.data.catalog import METRES_PER_UNIT, mocap_entries
    from training.i2s.data.imu_sim import mirrored

    entry = next(e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07")
    poses = forward_kinematics(read_bvh(data_dir / entry.path), METRES_PER_UNIT[entry.source])
    poses = GlobalPoses(poses.names, poses.positions_m[:600], poses.R_world_joint[:600], poses.sample_rate_hz)
    skeleton = skeleton_map_for(entry.source, poses.names)
    M = np.diag([1.0, -1.0, 1.0])
    reflected = GlobalPoses(poses.names, poses.positions_m @ M, M @ poses.R_world_joint @ M, poses.sample_rate_hz)
    swapped = SkeletonMap(skeleton.pelvis, skeleton.right, skeleton.left)

    original = segment_kinematics(functional_frames(segment_trajectories(poses, skeleton))[0])
    expected = mirrored(original)
    got = segment_kinematics(functional_frames(segment_trajectories(reflected, swapped))[0])
    for name in ("lin_acc_mps2", "up_mps2", "gyr_rads", "ang_acc_rads2", "R_world_segment"):
        np.testing.assert_allclose(getattr(got, name), getattr(expected, name), atol=1e-6, err_msg=name)
    # and it is not the identity: the left foot's angular velocity changed
    assert not np.allclose(expected.gyr_rads[:, 0], original.gyr_rads[:, 0], atol=0.1)


def test_mirrored_readings_are_the_mirror_bodys_sensor_on_the_other_side(data_dir) -> None:
    """``mirrored_readings`` of a sensor's window equal the readings of the mirror-image body's other-side segment
    (``mirrored``) carrying that sensor mounted M R S, a proper rotation; and no rotation of the original sensor
    reads them (a reflection is not a remounting), so the side is not lost."""
    traj = _walk_trajectory(data_dir, 300)
    kin = segment_kinematics(traj)
    other = mirrored(kin)
    M = S = np.diag([1.0, -1.0, 1.0])
    R = Rotation.random(1, random_state=3).as_matrix()
    for k in (0, 2, 3):  # left foot, left thigh, pelvis
        args = [getattr(kin, n)[None, :, k] for n in ("lin_acc_mps2", "up_mps2", "gyr_rads", "ang_acc_rads2")]
        reading = imu_readings(*args, R_segment_imu=R)
        twin = [getattr(other, n)[None, :, 6 - k] for n in ("lin_acc_mps2", "up_mps2", "gyr_rads", "ang_acc_rads2")]
        mounted = M @ R[0] @ S
        assert np.isclose(np.linalg.det(mounted), 1.0)
        np.testing.assert_allclose(
            mirrored_readings(reading), imu_readings(*twin, R_segment_imu=mounted[None]), atol=1e-9
        )
        # No rotation of the sensor reads them: the gyroscope alone turns by a half turn about y (−S), and motion
        # in one plane only would be a remounting too (S times the reflection through that plane); one rotation
        # of both vectors together (Kabsch on the accelerometer and gyroscope rows) leaves a residual on this walk.
        both = np.concatenate([reading[0, :, :3] / 9.81, reading[0, :, 3:]])
        both_m = np.concatenate([mirrored_readings(reading)[0, :, :3] / 9.81, mirrored_readings(reading)[0, :, 3:]])
        rot, _ = Rotation.align_vectors(both_m, both)
        assert np.abs(rot.apply(both) - both_m).mean() > 0.1 * np.abs(both).mean(), k


def _walk_trajectory(data_dir, frames: int = 600):
    from service.core.skeleton import functional_frames
    from training.data.catalog import mocap_entries
    from training.i2s.data.mocap import geometric_trajectories

    entry = next(e for e in mocap_entries(data_dir, ["walk"]) if e.group == "cmu_07")
    traj, _ = functional_frames(geometric_trajectories(data_dir / entry.path, entry))
    return SegmentTrajectories(
        traj.R_world_segment[:frames], traj.origin_m[:frames], traj.midpoint_m[:frames], traj.sample_rate_hz
    )


def test_a_braced_knee_keeps_the_leg_rigid_and_the_rest_of_the_body_as_recorded(data_dir) -> None:
    """``stiffened_knee``: with keep 0 the shank turns with the thigh, the foot stays rigid on the shank, the bone
    lengths hold and the other segments are untouched; with keep 1 nothing changes."""
    from training.i2s.data.imu_sim import stiffened_knee

    traj = _walk_trajectory(data_dir)
    same = stiffened_knee(traj, "left", 1.0)
    for name in ("R_world_segment", "origin_m", "midpoint_m"):
        np.testing.assert_allclose(getattr(same, name), getattr(traj, name), atol=1e-9, err_msg=name)

    braced = stiffened_knee(traj, "left", 0.0)
    R, R0 = braced.R_world_segment, traj.R_world_segment
    rel = np.einsum("tji,tjk->tik", R[:, 2], R[:, 1])  # thigh → shank: the identity when braced
    np.testing.assert_allclose(rel, np.broadcast_to(np.eye(3), rel.shape), atol=1e-9)
    foot_on_shank = np.einsum("tji,tjk->tik", R[:, 1], R[:, 0])
    np.testing.assert_allclose(foot_on_shank, np.einsum("tji,tjk->tik", R0[:, 1], R0[:, 0]), atol=1e-9)
    knee = traj.origin_m[:, 1]
    for new, old in ((braced.midpoint_m[:, 1], traj.midpoint_m[:, 1]), (braced.origin_m[:, 0], traj.origin_m[:, 0])):
        np.testing.assert_allclose(np.linalg.norm(new - knee, axis=1), np.linalg.norm(old - knee, axis=1), atol=1e-9)
    untouched = [2, 3, 4, 5, 6]
    np.testing.assert_array_equal(R[:, untouched], R0[:, untouched])
    np.testing.assert_array_equal(braced.midpoint_m[:, untouched], traj.midpoint_m[:, untouched])
    # and walking really bends the knee: the recorded shank turns away from its thigh by tens of degrees
    knee_angle = Rotation.from_matrix(np.einsum("tji,tjk->tik", R0[:, 2], R0[:, 1])).magnitude()
    assert np.degrees(knee_angle.max()) > 40.0
    with pytest.raises(ValueError, match="side must be"):
        stiffened_knee(traj, "middle", 0.0)
    with pytest.raises(ValueError, match="keep must be"):
        stiffened_knee(traj, "right", 1.5)


def test_soft_tissue_motion_has_the_asked_size_and_its_rate_is_its_derivative() -> None:
    from training.i2s.data.imu_sim import SoftTissue, soft_tissue_motion

    rng = np.random.default_rng(0)
    t = (np.arange(128) / RATE)[None, :, None]
    waves = lambda f: np.sin(2 * np.pi * f * t + rng.uniform(0, 6, (4, 1, 3)))  # noqa: E731
    lin_acc, ang_acc = 3 * waves(1.1) + waves(2.7), 5 * waves(1.9)
    sta = SoftTissue(
        freq_hz=np.array([4.0, 6.0, 9.0, 12.0]),
        damping=np.full(4, 0.3),
        mix=rng.normal(size=(4, 6, 6)),
        rot_rms_rad=np.radians([0.5, 1.0, 2.0, 3.0]),
        disp_rms_m=np.full(4, 2e-3),
    )
    theta, theta_rate, u_acc = soft_tissue_motion(lin_acc, ang_acc, sta, RATE)
    rms = np.sqrt(np.mean(np.sum(theta**2, axis=-1), axis=1))
    np.testing.assert_allclose(rms, sta.rot_rms_rad, rtol=1e-9)
    inner = slice(16, -16)  # the mirrored extension bends the ends
    numeric = np.gradient(theta, 1 / RATE, axis=1)[:, inner]
    scale = np.sqrt(np.mean(theta_rate[:, inner] ** 2))
    assert np.max(np.abs(numeric - theta_rate[:, inner])) < 0.1 * scale
    assert np.all(np.isfinite(u_acc)) and np.sqrt(np.mean(u_acc**2)) > 0


def test_a_sensor_turned_on_its_segment_reads_the_turned_vectors_and_the_added_rate() -> None:
    from training.i2s.data.imu_sim import with_soft_tissue

    rng = np.random.default_rng(1)
    acc_s, gyr_s = rng.normal(size=(2, 5, 3)), rng.normal(size=(2, 5, 3))
    theta = np.zeros((2, 5, 3))
    theta[..., 2] = np.radians(30)
    acc, gyr = with_soft_tissue(acc_s, gyr_s, theta, np.zeros_like(theta), np.zeros_like(theta))
    turn = Rotation.from_rotvec([0, 0, np.radians(30)]).as_matrix()
    np.testing.assert_allclose(acc, acc_s @ turn, atol=1e-12)  # R^T v, row vectors
    extra = rng.normal(size=(2, 5, 3))
    _, gyr = with_soft_tissue(acc_s, gyr_s, np.zeros_like(theta), extra, np.zeros_like(theta))
    np.testing.assert_allclose(gyr, gyr_s + extra, atol=1e-12)


def test_the_sampler_turns_thigh_sensors_on_their_segment_more_than_foot_sensors(data_dir, kinematics_cache) -> None:
    """The same windows with and without the soft-tissue artefact (no noise, no displacement): the specific
    force keeps its size, turns by up to the configured angle, and turns more on the thighs than on the feet."""
    from training.data.catalog import mocap_entries
    from training.i2s.data.mocap import build_kinematics
    from training.i2s.data.windows import Augmentation, WindowSampler

    clips = build_kinematics(data_dir, mocap_entries(data_dir, ["walk"])[:3], kinematics_cache)
    quiet = dict(acc_noise_std_mps2=0.0)
    off = WindowSampler(clips, Augmentation(**quiet)).sample(np.random.default_rng(5), 512)
    on = WindowSampler(clips, Augmentation(soft_tissue_rot_deg=6.0, **quiet)).sample(np.random.default_rng(5), 512)
    np.testing.assert_array_equal(on.segment, off.segment)
    a_on, a_off = on.imu[..., :3].astype(np.float64), off.imu[..., :3].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(a_on, axis=-1), np.linalg.norm(a_off, axis=-1), atol=0.02)
    cos = np.sum(a_on * a_off, axis=-1) / np.linalg.norm(a_on, axis=-1) / np.linalg.norm(a_off, axis=-1)
    turned = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.max(np.abs(on.imu[..., 3:] - off.imu[..., 3:])) > 0.01  # the rate of the turning adds to the gyro
    thigh, foot = np.isin(on.segment, [2, 4]), np.isin(on.segment, [0, 6])
    assert np.median(turned[thigh]) > 2 * np.median(turned[foot])
    assert np.percentile(turned, 99) < 6.0 * 3  # RMS up to 6°: peaks stay within a few times that
