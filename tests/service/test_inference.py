"""The parallel runner's chunking, model loading and alignment averaging (real onnxruntime sessions)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.manifest import read_manifest, write_manifest
from service.inference.predict import RunningAlignment, mean_alignment
from service.inference.registry import load_models, version_key
from service.inference.runner import ModelRunner


def test_runner_chunks_equal_one_call(tiny_models: Path) -> None:
    models = load_models(tiny_models, threads=1)
    x = np.random.default_rng(0).normal(size=(37, 128, 6)).astype(np.float32)
    runner = ModelRunner(models, threads=2, chunk=8)
    probs, quats = runner(x)
    np.testing.assert_allclose(probs, models["i2s_assignment"].run(x), atol=1e-6)
    np.testing.assert_allclose(quats, models["i2s_alignment"].run(x), atol=1e-6)
    p_chunk, q_chunk, seconds, cpu = asyncio.run(runner.run_chunk_async(x[:8]))  # the scheduler's unit: one chunk
    assert seconds > 0 and cpu > 0  # onnxruntime runs in the worker's own thread: its CPU time is counted
    np.testing.assert_array_equal(p_chunk, probs[:8])
    np.testing.assert_array_equal(q_chunk, quats[:8])
    runner.close()


def test_versions_compare_numerically() -> None:
    assert version_key("1.10.0") > version_key("1.9.0")
    assert version_key("2026.11.22-073000") > version_key("2026.11.21-235959")


def test_a_pinned_version_is_served_instead_of_the_newest(tiny_models: Path) -> None:
    import shutil

    from service.settings import parse_pins

    newer = tiny_models / "i2s_alignment" / "0.0.2"
    shutil.copytree(tiny_models / "i2s_alignment" / "0.0.1", newer)
    manifest = read_manifest(newer / "manifest.json")
    manifest.version = "0.0.2"
    write_manifest(manifest, newer / "manifest.json")
    assert load_models(tiny_models, 1)["i2s_alignment"].manifest.version == "0.0.2"
    pinned = load_models(tiny_models, 1, parse_pins("i2s_alignment=0.0.1"))
    assert pinned["i2s_alignment"].manifest.version == "0.0.1" and "i2s_assignment" in pinned
    with pytest.raises(ValueError, match="<name>=<version>"):
        parse_pins("i2s_alignment")


@pytest.mark.parametrize("turn_deg", [90.0, 180.0])
def test_mean_alignment_is_not_pulled_by_a_minority_of_turned_windows(turn_deg: float) -> None:
    """Windows scattered 2° around a true alignment, plus 40 % turned about z: the mean stays on the truth, and
    the spread reports the typical window's deviation. (The plain chordal mean is pulled 34° by the 90° turns.)"""
    rng = np.random.default_rng(0)
    truth = Rotation.from_euler("xyz", [20, -35, 110], degrees=True)
    noise = Rotation.from_rotvec(rng.normal(scale=np.radians(2.0), size=(50, 3)))
    windows = truth * noise
    turned = windows[:20] * Rotation.from_euler("z", turn_deg, degrees=True)
    rows = np.concatenate([windows[20:].as_quat(scalar_first=True), turned.as_quat(scalar_first=True)])
    q, spread = mean_alignment(rows)
    assert np.degrees((Rotation.from_quat(q, scalar_first=True).inv() * truth).magnitude()) < 1.5
    plain = np.degrees((Rotation.from_quat(rows, scalar_first=True).mean().inv() * truth).magnitude())
    assert plain > 10.0 or turn_deg == 180.0  # quaternions 180° apart are orthogonal: the majority wins anyway
    assert 1.0 < spread < 6.0
    assert q[0] >= 0.0
    signs = rng.choice([-1.0, 1.0], size=(len(rows), 1))  # q and -q are the same rotation
    q_signed, spread_signed = mean_alignment(rows * signs)
    np.testing.assert_allclose(q_signed, q, atol=1e-9)
    assert spread_signed == pytest.approx(spread)


def test_a_streamed_sensors_alignment_follows_its_last_windows_for_its_segment() -> None:
    """RunningAlignment keeps the last ``capacity`` windows of all seven segment hypotheses: its mean for a segment
    is mean_alignment of exactly those rows, and once the ring has turned over, an old mounting no longer counts."""
    rng = np.random.default_rng(1)

    def windows(euler: list[float], n: int) -> np.ndarray:
        truth = Rotation.from_euler("xyz", euler, degrees=True)
        per_segment = [truth * Rotation.from_euler("z", 20 * k, degrees=True) for k in range(7)]  # one per segment
        noise = Rotation.from_rotvec(rng.normal(scale=np.radians(2.0), size=(n, 3)))
        return np.stack([(r * noise).as_quat(scalar_first=True) for r in per_segment], axis=1)  # (n, 7, 4)

    running = RunningAlignment(capacity=30)
    assert running.mean(3) is None
    first = windows([10, 20, 30], 20)
    for row in first:
        running.add(row)
    for segment in (3, 5):
        q, spread = running.mean(segment)
        q_ref, spread_ref = mean_alignment(first[:, segment].astype(np.float32).astype(np.float64))
        np.testing.assert_allclose(q, q_ref, atol=1e-6)
        assert spread == pytest.approx(spread_ref)
    for row in windows([-40, 5, 90], 30):  # the sensor was re-strapped: 30 new windows fill the ring
        running.add(row)
    q, _ = running.mean(0)
    moved = Rotation.from_euler("xyz", [-40, 5, 90], degrees=True)  # 86° from the old mounting
    assert np.degrees((Rotation.from_quat(q, scalar_first=True).inv() * moved).magnitude()) < 3.0


def test_a_running_alignment_is_recomputed_once_a_sixteenth_of_its_windows_are_new() -> None:
    """Below 32 windows every new window counts at once; later a segment's mean waits for a sixteenth of new
    windows, each segment's apart, and ``fresh`` reads every window."""
    rng = np.random.default_rng(2)
    rows = Rotation.from_rotvec(rng.normal(scale=0.3, size=(120, 3))).as_quat(scalar_first=True)
    running = RunningAlignment(capacity=450)

    def exact(n: int) -> np.ndarray:
        return mean_alignment(np.repeat(rows[:n, None], 7, axis=1)[:, 4].astype(np.float32).astype(np.float64))[0]

    for n, row in enumerate(rows[:100], start=1):
        running.add(np.repeat(row[None], 7, axis=0))
        if n <= 16:  # each window counts
            np.testing.assert_allclose(running.mean(4)[0], exact(n), atol=1e-9)
    at_100 = running.mean(4)[0]
    for n, row in enumerate(rows[100:106], start=101):
        running.add(np.repeat(row[None], 7, axis=0))
        q = running.mean(4)[0]
        if n < 106:  # 100 // 16 = 6 new windows are due
            assert q is at_100
    np.testing.assert_allclose(q, exact(106), atol=1e-9)
    running.add(np.repeat(rows[106][None], 7, axis=0))
    assert running.mean(4)[0] is q
    other = running.mean(2)[0]  # another segment, computed over all 107; segment 4 keeps its own
    assert running.mean(4)[0] is q and running.mean(2)[0] is other
    np.testing.assert_allclose(running.mean(4, fresh=True)[0], exact(107), atol=1e-9)


def _twist_about_y_deg(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of rotations ``(T, 3, 3)``: the angle about y and how far the y axis itself is turned (a pure hinge: 0)."""
    return np.degrees(np.arctan2(R[:, 0, 2], R[:, 0, 0])), np.degrees(np.arccos(np.clip(R[:, 1, 1], -1.0, 1.0)))


def test_whole_body_makes_each_answered_thigh_a_hinge_of_its_sensed_shank() -> None:
    from service.core.body import BODY_SEGMENTS
    from service.inference.pose import whole_body

    rng = np.random.default_rng(3)
    T = 50
    sensors = ["Pelvis", "LeftLowerLeg", "RightLowerLeg"]
    outputs = ["LeftUpperLeg", "RightUpperLeg", "LeftFoot"]
    R_sensors = Rotation.random(T * 3, random_state=4).as_matrix().reshape(T, 3, 3, 3)
    flexion = rng.uniform(0.0, 90.0, size=T)
    # the model's thighs, relative to the pelvis: the left an exact hinge of its shank, the right 20° off it
    off = Rotation.from_rotvec(np.radians(20.0) * np.array([1.0, 0.0, 0.0])).as_matrix()
    R_hinge = Rotation.from_rotvec(-np.radians(flexion)[:, None] * [0.0, 1.0, 0.0]).as_matrix()
    thighs_world = [R_sensors[:, 1] @ R_hinge, R_sensors[:, 2] @ R_hinge @ off]
    R_root_out = np.stack(
        [np.einsum("tji,tjk->tik", R_sensors[:, 0], th) for th in thighs_world]
        + [Rotation.random(T, random_state=5).as_matrix()],
        axis=1,
    )
    index = [BODY_SEGMENTS.index(s) for s in sensors], [BODY_SEGMENTS.index(s) for s in outputs]
    R = whole_body(R_sensors, R_root_out, *index, hinges=True)
    left, right = BODY_SEGMENTS.index("LeftUpperLeg"), BODY_SEGMENTS.index("RightUpperLeg")
    np.testing.assert_allclose(R[:, left], thighs_world[0], atol=1e-9)  # already a hinge: unchanged
    for thigh, shank in ((left, 1), (right, 2)):
        angle, tilt = _twist_about_y_deg(np.einsum("tji,tjk->tik", R_sensors[:, shank], R[:, thigh]))
        assert np.abs(tilt).max() < 1e-4  # shank⁻¹ · thigh turns about y only (degrees; arccos near 1 is coarse)
        np.testing.assert_allclose(angle, -flexion, atol=1e-6)  # the model's flexion is kept
    foot = BODY_SEGMENTS.index("LeftFoot")
    np.testing.assert_allclose(R[:, foot], np.einsum("tij,tjk->tik", R_sensors[:, 0], R_root_out[:, 2]), atol=1e-12)


def _arm_sessions(T: int, flexion_deg: np.ndarray, seed: int) -> tuple[np.ndarray, ...]:
    """Sensors on the pelvis and both forearms, the model answering both upper arms: its answer turned about the
    upper arm's long axis by up to 60° from the true upper arm, which the elbow's hinge (about y, the forearm's long
    axis behind the upper arm's z as in the mocap) joins to the sensed forearm."""
    from service.core.body import BODY_SEGMENTS

    rng = np.random.default_rng(seed)
    R_pelvis = Rotation.random(T, random_state=seed).as_matrix()
    uppers_true = [Rotation.random(T, random_state=seed + 1 + k).as_matrix() for k in range(2)]
    hinge = Rotation.from_rotvec(-np.radians(flexion_deg)[:, None] * [0.0, 1.0, 0.0]).as_matrix()
    forearms = [u @ hinge for u in uppers_true]
    twist = [Rotation.from_rotvec(np.radians(rng.uniform(-60, 60, T))[:, None] * [0.0, 0.0, 1.0]).as_matrix()]
    answered = [uppers_true[0] @ twist[0], uppers_true[1] @ twist[0].transpose(0, 2, 1)]
    R_sensors = np.stack([R_pelvis, *forearms], axis=1)
    R_root_out = np.stack([np.einsum("tji,tjk->tik", R_pelvis, a) for a in answered], axis=1)
    sensors = [BODY_SEGMENTS.index(s) for s in ("Pelvis", "LeftForeArm", "RightForeArm")]
    outputs = [BODY_SEGMENTS.index(s) for s in ("LeftUpperArm", "RightUpperArm")]
    return R_sensors, R_root_out, sensors, outputs, np.stack(uppers_true, axis=1)


def test_whole_body_turns_each_answered_upper_arm_so_its_sensed_forearm_lies_in_the_elbow_s_plane() -> None:
    from service.inference.pose import whole_body

    T = 40
    flexion = np.linspace(35.0, 140.0, T)
    R_sensors, R_root_out, sensors, outputs, uppers_true = _arm_sessions(T, flexion, 20)
    R = whole_body(R_sensors, R_root_out, sensors, outputs, hinges=True)
    as_answered = whole_body(R_sensors, R_root_out, sensors, outputs, hinges=False)
    for k, (upper, forearm) in enumerate(zip(outputs, sensors[1:], strict=True)):
        v = np.einsum("tji,tj->ti", R[:, upper], R[:, forearm, :, 2])  # the forearm's long axis, upper arm frame
        np.testing.assert_allclose(v[:, 1], 0.0, atol=1e-9)  # in the x-z plane: the elbow's hinge along y
        assert (v[:, 0] < 0).all()  # behind z, as a flexed elbow in the mocap
        np.testing.assert_allclose(np.degrees(np.arccos(v[:, 2])), flexion, atol=1e-6)  # the flexion kept
        # turned about its own long axis only: the upper arm points where the model said, so no joint moves
        np.testing.assert_allclose(R[:, upper, :, 2], as_answered[:, upper, :, 2], atol=1e-12)
        np.testing.assert_allclose(R[:, upper], uppers_true[:, k], atol=1e-9)  # the twist the model missed, found
        assert not np.allclose(as_answered[:, upper], uppers_true[:, k], atol=0.1)


def test_a_forearm_sensor_that_turns_with_pronation_does_not_move_the_upper_arm() -> None:
    """Only the forearm's long axis is read: a sensor near the wrist turns about it as the forearm pronates."""
    from service.inference.pose import whole_body

    T = 30
    R_sensors, R_root_out, sensors, outputs, _ = _arm_sessions(T, np.full(T, 70.0), 30)
    R = whole_body(R_sensors, R_root_out, sensors, outputs, hinges=True)
    pronated = R_sensors.copy()
    for k in (1, 2):
        turn = Rotation.from_rotvec(np.radians(np.linspace(-80, 80, T))[:, None] * [0.0, 0.0, 1.0]).as_matrix()
        pronated[:, k] = R_sensors[:, k] @ turn
    R_pronated = whole_body(pronated, R_root_out, sensors, outputs, hinges=True)
    np.testing.assert_allclose(R_pronated[:, outputs], R[:, outputs], atol=1e-9)


def test_a_nearly_straight_elbow_keeps_the_upper_arm_as_answered_and_the_turn_grows_with_the_flexion() -> None:
    from service.inference.pose import ELBOW_PLANE_FLEXION_DEG, whole_body

    low, full = ELBOW_PLANE_FLEXION_DEG
    flexion = np.array([0.5, low - 1.0, (low + full) / 2, full + 1.0])
    R_sensors, R_root_out, sensors, outputs, _ = _arm_sessions(4, flexion, 40)
    R = whole_body(R_sensors, R_root_out, sensors, outputs, hinges=True)
    as_answered = whole_body(R_sensors, R_root_out, sensors, outputs, hinges=False)
    upper, forearm = outputs[0], sensors[1]
    np.testing.assert_allclose(R[:2, upper], as_answered[:2, upper], atol=1e-12)  # below the first: untouched

    def off_plane(R_: np.ndarray) -> np.ndarray:
        v = np.einsum("tji,tj->ti", R_[:, upper], R_[:, forearm, :, 2])
        return np.degrees(np.abs(np.angle(-(v[:, 0] + 1j * v[:, 1]))))

    before, after = off_plane(as_answered), off_plane(R)
    np.testing.assert_allclose(after[2], before[2] / 2, atol=1e-6)  # half way up the ramp: half the turn
    assert after[3] < 1e-6


def test_the_evaluation_digest_names_the_elbows_only_where_a_model_has_them() -> None:
    from service.inference.pose import PoseModel

    models = load_models(Path(__file__).resolve().parents[2] / "onnx_models", 1)
    pose = {name: PoseModel(m) for name, m in models.items() if m.manifest.task == "imu_pose"}
    assert pose["pose_full6"].assembly == "+knee-hinges+elbow-planes+neutral-wrists"
    assert pose["pose_lower3"].assembly == "+knee-hinges"
    assert pose["pose_mrmr6"].assembly == "+knee-hinges+elbow-planes+neutral-wrists"  # its right forearm


def test_each_answered_hand_beside_a_sensed_forearm_follows_it_and_a_measured_hand_is_kept() -> None:
    """The wrist neutral: the hand takes the forearm's orientation as sensed, pronation included."""
    from service.core.body import BODY_SEGMENTS
    from service.inference.pose import whole_body

    T = 15
    sensors = [BODY_SEGMENTS.index(s) for s in ("Pelvis", "LeftForeArm", "RightForeArm")]
    outputs = [BODY_SEGMENTS.index(s) for s in ("LeftHand", "RightHand", "LeftUpperArm")]
    R_sensors = Rotation.random(T * 3, random_state=50).as_matrix().reshape(T, 3, 3, 3)
    R_root_out = Rotation.random(T * 3, random_state=51).as_matrix().reshape(T, 3, 3, 3)
    measured = np.full((T, len(BODY_SEGMENTS), 3, 3), np.nan)
    right_hand = Rotation.random(T, random_state=52).as_matrix()
    measured[:, outputs[1]] = right_hand
    R = whole_body(R_sensors, R_root_out, sensors, outputs, measured, hinges=True)
    np.testing.assert_allclose(R[:, outputs[0]], R_sensors[:, 1], atol=1e-12)  # the left forearm, as sensed
    np.testing.assert_allclose(R[:, outputs[1]], right_hand)  # a sensor on the right hand: as measured
    as_answered = whole_body(R_sensors, R_root_out, sensors, outputs, measured, hinges=False)
    np.testing.assert_allclose(as_answered[:, outputs[0]], np.einsum("tij,tjk->tik", R_sensors[:, 0], R_root_out[:, 0]))


def test_whole_body_keeps_a_thigh_a_sensor_measures_and_one_with_no_sensed_shank() -> None:
    from service.core.body import BODY_SEGMENTS
    from service.inference.pose import whole_body

    T = 20
    R_sensors = Rotation.random(T * 2, random_state=6).as_matrix().reshape(T, 2, 3, 3)
    R_root_out = Rotation.random(T * 2, random_state=7).as_matrix().reshape(T, 2, 3, 3)
    sensors = [BODY_SEGMENTS.index(s) for s in ("Pelvis", "LeftLowerLeg")]
    outputs = [BODY_SEGMENTS.index(s) for s in ("LeftUpperLeg", "RightUpperLeg")]
    measured = np.full((T, len(BODY_SEGMENTS), 3, 3), np.nan)
    left_thigh = Rotation.random(T, random_state=8).as_matrix()
    measured[:, BODY_SEGMENTS.index("LeftUpperLeg")] = left_thigh
    R = whole_body(R_sensors, R_root_out, sensors, outputs, measured, hinges=True)
    np.testing.assert_allclose(R[:, BODY_SEGMENTS.index("LeftUpperLeg")], left_thigh)  # measured: as measured
    right = np.einsum("tij,tjk->tik", R_sensors[:, 0], R_root_out[:, 1])  # no right shank sensed: the model's
    np.testing.assert_allclose(R[:, BODY_SEGMENTS.index("RightUpperLeg")], right, atol=1e-12)


def test_only_models_in_the_hinge_frames_answer_their_knees_as_hinges() -> None:
    from service.inference.pose import PoseModel, hinge_joints

    assert hinge_joints("hinge") and not hinge_joints("rig") and not hinge_joints(None)
    models = load_models(Path(__file__).resolve().parents[2] / "onnx_models", 1)
    pose = [PoseModel(m) for m in models.values() if m.manifest.task == "imu_pose"]
    assert pose and all(p.hinge_joints == (p.loaded.manifest.training_data["limb_twist"] == "hinge") for p in pose)


def test_a_model_in_a_rig_s_own_frames_and_the_mean_pose_keep_the_thighs_as_answered() -> None:
    from service.core.body import BODY_SEGMENTS
    from service.inference.pose import PoseModel, whole_body

    loaded = load_models(Path(__file__).resolve().parents[2] / "onnx_models", 1)["pose_lower3"]
    rig = loaded.manifest.model_copy(deep=True)
    rig.training_data["limb_twist"] = "rig"
    assert PoseModel(loaded).hinge_joints and not PoseModel(type(loaded)(rig, loaded.session, loaded.path)).hinge_joints
    T = 10
    R_sensors = Rotation.random(T * 2, random_state=9).as_matrix().reshape(T, 2, 3, 3)
    R_root_out = Rotation.random(T, random_state=10).as_matrix().reshape(T, 1, 3, 3)
    sensors = [BODY_SEGMENTS.index(s) for s in ("Pelvis", "LeftLowerLeg")]
    outputs = [BODY_SEGMENTS.index("LeftUpperLeg")]
    R = whole_body(R_sensors, R_root_out, sensors, outputs, hinges=False)
    np.testing.assert_allclose(R[:, outputs[0]], np.einsum("tij,tjk->tik", R_sensors[:, 0], R_root_out[:, 0]))


def test_a_shank_measured_on_some_frames_hinges_its_knee_on_those_frames_only() -> None:
    """Frames of several live sessions share one call: a shank sensor beyond the model's on some of them."""
    from service.core.body import BODY_SEGMENTS
    from service.inference.pose import whole_body

    T = 12
    R_sensors = Rotation.random(T, random_state=11).as_matrix().reshape(T, 1, 3, 3)  # the pelvis only
    R_root_out = Rotation.random(T, random_state=12).as_matrix().reshape(T, 1, 3, 3)
    thigh, shank = BODY_SEGMENTS.index("RightUpperLeg"), BODY_SEGMENTS.index("RightLowerLeg")
    measured = np.full((T, len(BODY_SEGMENTS), 3, 3), np.nan)
    measured[: T // 2, shank] = Rotation.random(T // 2, random_state=13).as_matrix()
    R = whole_body(R_sensors, R_root_out, [0], [thigh], measured, hinges=True)
    answered = np.einsum("tij,tjk->tik", R_sensors[:, 0], R_root_out[:, 0])
    np.testing.assert_allclose(R[T // 2 :, thigh], answered[T // 2 :], atol=1e-12)  # no shank there: as answered
    M = np.einsum("tji,tjk->tik", R[: T // 2, shank], R[: T // 2, thigh])
    assert np.abs(M[:, 1, 1] - 1.0).max() < 1e-9  # shank⁻¹ · thigh turns about y only where the shank is measured
    assert not np.allclose(R[: T // 2, thigh], answered[: T // 2])


def test_a_flex_model_in_the_hinge_frames_answers_the_hinges_zeros_as_zero() -> None:
    """The simulated suit (hinge frames): each knee's abduction and rotation and each elbow's abduction answered 0,
    the elbows' rotation (pronation) and every other angle as the network gives them; the capacitive sleeve, whose
    manifest names no such frames, as its network gives it."""
    from service.core.flex import HINGE_ZEROS, hinge_mask
    from service.inference.flex import FlexModel

    models = load_models(Path(__file__).resolve().parents[2] / "onnx_models", 1)
    suit, sleeve = FlexModel(models["flex_bilstm_cm"]), FlexModel(models["flex_capacitive_knee"])
    m = suit.manifest
    assert m.training_data["limb_twist"] == "hinge" and sleeve.answer_mask is None
    mask = hinge_mask(m.joints, m.joint_components)
    assert int((mask == 0).sum()) == 6  # two knees × abduction, rotation; two elbows × abduction
    assert mask[m.joints.index("LeftElbow"), m.joint_components.index("rotation")] == 1.0
    assert set(HINGE_ZEROS) <= set(m.joints)
    lo, hi = m.value_range
    x = np.random.default_rng(60).uniform(lo + 500, hi - 500, size=(4, suit.window, len(m.channels)))
    raw = suit.loaded.run(x.astype(np.float32))
    got = suit.run_windows(x)
    assert np.all(got[:, mask == 0] == 0.0) and np.abs(raw[:, mask == 0]).max() > 0.01
    np.testing.assert_array_equal(got[:, mask == 1], raw[:, mask == 1])
    y = np.random.default_rng(61).uniform(900.0, 1100.0, size=(2, sleeve.window, len(sleeve.manifest.channels)))
    np.testing.assert_array_equal(sleeve.run_windows(y), sleeve.loaded.run(y.astype(np.float32)))


def test_the_stream_median_is_numpys_median() -> None:
    """``median`` (four per window and sensor of a live stream) gives ``np.median``'s value bit for bit: odd and
    even counts, ties, a single value, and NaN."""
    from service.inference.predict import median

    rng = np.random.default_rng(0)
    for n in [1, 2, 3, 4, *rng.integers(5, 500, 200).tolist()]:
        x = rng.normal(size=n)
        if n > 3 and n % 5 == 0:
            x[: n // 2] = x[0]  # ties
        assert median(x) == np.median(x), n
        if n > 1:
            x[int(rng.integers(n))] = np.nan
            assert np.isnan(median(x))
