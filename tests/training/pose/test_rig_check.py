"""The rig check's hinge axis: a simulated elbow whose axis is turned about the upper arm's long axis."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.core.flex import azimuth_elevation_deg, hinge_in_proximal


@pytest.mark.parametrize("turn_deg", [-25.0, 0.0, 11.0])
def test_the_hinge_axis_is_found_in_the_proximal_frame_whatever_the_upper_arm_does(turn_deg: float) -> None:
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 6.0, 600)
    upper = Rotation.from_rotvec(np.c_[0.3 * np.sin(t), 0.2 * np.cos(1.3 * t), 0.5 * np.sin(0.7 * t)])
    axis = Rotation.from_euler("z", turn_deg, degrees=True).apply([0.0, 1.0, 0.0])  # y turned about z
    flexion = np.radians(10 + 25 * (1 + np.sin(2 * np.pi * t)))  # 10-60° of elbow flexion
    carrying = Rotation.from_euler("x", 8, degrees=True)  # a constant carrying angle of the forearm's frame
    fore = upper * Rotation.from_rotvec(flexion[:, None] * axis) * carrying
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), size=(len(t), 3)))
    found, motion = hinge_in_proximal(upper.as_matrix(), (fore * noise).as_matrix())
    azimuth, elevation = azimuth_elevation_deg(found)
    assert azimuth == pytest.approx(turn_deg, abs=1.0) and abs(elevation) < 1.0
    assert motion == pytest.approx(50.0, abs=3.0)


def test_hinge_twisted_frames_put_the_elbows_and_knees_hinges_on_y(data_dir) -> None:
    """li2018's own frames turn the right upper arm 18° off its elbow's hinge; turned by ``hinge_twisted`` (on the
    same walks) every limb's hinge lies on y, in the proximal and in the distal segment's frame."""
    from service.core.body import BODY_SEGMENTS, body_motion, read_clip_offsets, read_rig, rig_offsets
    from training.data.catalog import mocap_entries
    from training.pose.data import HINGE_LIMBS, hinge_twisted

    walks = [data_dir / e.path for e in mocap_entries(data_dir, ["walk"], ["cmu_li2018"])][:4]
    offsets = rig_offsets([read_clip_offsets(p, None, "cmu_li2018") for p in walks])
    twisted = hinge_twisted(offsets, walks, "cmu_li2018")

    def azimuths(offs) -> dict[str, float]:
        out: dict[str, list[float]] = {}
        for path in walks:
            R = body_motion(*read_rig(path, None, "cmu_li2018"), offs).R_world_segment
            for side in ("Left", "Right"):
                for proximal, distal in HINGE_LIMBS:
                    p, d = BODY_SEGMENTS.index(side + proximal), BODY_SEGMENTS.index(side + distal)
                    for name, a, b in ((proximal, p, d), (distal, d, p)):
                        out.setdefault(side + name, []).append(
                            azimuth_elevation_deg(hinge_in_proximal(R[:, a], R[:, b])[0])[0]
                        )
        return {k: float(np.median(v)) for k, v in out.items()}

    before, after = azimuths(offsets), azimuths(twisted)
    assert abs(before["RightUpperArm"]) > 10.0
    assert all(abs(v) < 1.0 for v in after.values()), after
    hand = BODY_SEGMENTS.index("LeftHand")  # turned with its forearm; the feet and the trunk are not turned
    forearm = BODY_SEGMENTS.index("LeftForeArm")
    np.testing.assert_allclose(offsets[hand].T @ twisted[hand], offsets[forearm].T @ twisted[forearm], atol=1e-9)
    for segment in ("LeftFoot", "Pelvis", "T8", "Head"):
        np.testing.assert_allclose(twisted[BODY_SEGMENTS.index(segment)], offsets[BODY_SEGMENTS.index(segment)])


def test_evaluate_pose_s_clips_take_the_frames_of_the_model_s_limb_rule(data_dir, tmp_path) -> None:
    """A user's BVH folder read for a model trained in hinge frames has its elbows' hinges on the upper arms' y,
    as the model's training clips did; read for a model in its rig's frames it keeps the rig's turn."""
    from service.core.body import BODY_SEGMENTS
    from training.data.catalog import mocap_entries
    from training.pose.user_mocap import user_clips

    for e in mocap_entries(data_dir, ["walk"], ["cmu_li2018"])[:4]:
        (tmp_path / (data_dir / e.path).name).symlink_to(data_dir / e.path)
    arm, fore = BODY_SEGMENTS.index("RightUpperArm"), BODY_SEGMENTS.index("RightForeArm")

    def azimuth(clips) -> float:
        found = [
            hinge_in_proximal(c.motion.R_world_segment[:, arm], c.motion.R_world_segment[:, fore])[0] for c in clips
        ]
        return float(np.median([azimuth_elevation_deg(a)[0] for a in found]))

    assert abs(azimuth(user_clips([tmp_path], None, "rig"))) > 10.0
    assert abs(azimuth(user_clips([tmp_path], None, "hinge"))) < 1.0
    # and for a model whose upper trunk is read from the thorax: the shoulders held, on average, as T8 is
    t8, shoulder = BODY_SEGMENTS.index("T8"), BODY_SEGMENTS.index("LeftShoulder")

    def shoulder_from_t8(clips) -> float:
        rel = np.concatenate(
            [
                np.einsum("tji,tjk->tik", c.motion.R_world_segment[:, t8], c.motion.R_world_segment[:, shoulder])
                for c in clips
            ]
        )
        return float(np.degrees(Rotation.from_matrix(rel).mean().magnitude()))

    assert shoulder_from_t8(user_clips([tmp_path], None, "hinge")) > 10.0
    assert shoulder_from_t8(user_clips([tmp_path], None, "hinge", trunk_axes="thorax")) < 3.0


def test_a_user_s_clips_of_a_training_rig_are_scored_in_its_training_frames(data_dir, tmp_path) -> None:
    """Sprints of a rig the models trained on get that rig's frames (fitted on its walks), not frames fitted on
    the sprints; a skeleton the data directory does not have gets None (its frames are fitted on the clips)."""
    from training.data.catalog import mocap_entries
    from training.pose.data import build_rig_offsets, load_motion
    from training.pose.user_mocap import catalogue_rig, user_clips

    runs = [data_dir / e.path for e in mocap_entries(data_dir, ["run"], ["cmu_li2018"])][:2]
    entries = mocap_entries(data_dir, sources=["cmu_li2018"])
    for twist, trunk in (("rig", "spine"), ("hinge", "thorax"), ("hinge", "spine")):  # the last one used below
        cache = tmp_path / "cache"
        trained = build_rig_offsets(data_dir, entries, cache, limb_twist=twist, trunk_axes=trunk)["cmu_li2018"]
        np.testing.assert_allclose(catalogue_rig(runs, data_dir, cache, twist, trunk), trained, atol=1e-12)
    # and so a user's folder of them is read (evaluate-pose with a data directory)
    sprints = tmp_path / "sprints"
    sprints.mkdir()
    for p in runs:
        (sprints / p.name).symlink_to(p)
    [clip, _] = user_clips([sprints], None, "hinge", data_dir, tmp_path / "cache")
    np.testing.assert_allclose(
        clip.motion.R_world_segment, load_motion(Path(clip.path), "", 0, None, trained).R_world_segment, atol=1e-12
    )
    # a folder of two rigs: each file in its own rig's frames
    walk = data_dir / mocap_entries(data_dir, ["walk"], ["cmu_iclone"])[0].path
    (sprints / walk.name).symlink_to(walk)
    iclone = build_rig_offsets(
        data_dir, mocap_entries(data_dir, sources=["cmu_iclone"]), tmp_path / "cache", limb_twist="hinge"
    )
    for clip in user_clips([sprints], None, "hinge", data_dir, tmp_path / "cache"):
        rig = iclone["cmu_iclone"] if clip.path.endswith(walk.name) else trained
        np.testing.assert_allclose(
            clip.motion.R_world_segment, load_motion(Path(clip.path), "", 0, None, rig).R_world_segment, atol=1e-12
        )
    # the root's OFFSET (where a take starts) is no part of the skeleton: Bandai-Namco's takes start anywhere
    moved = tmp_path / "moved.bvh"
    text = runs[0].read_text()
    assert "OFFSET 0.000000 0.000000 0.000000" in text.splitlines()[3]
    moved.write_text(text.replace("OFFSET 0.000000 0.000000 0.000000", "OFFSET 1.5 0.0 -2.0", 1))
    np.testing.assert_allclose(catalogue_rig([moved], data_dir, tmp_path / "cache", "hinge"), trained, atol=1e-12)
    renamed = tmp_path / "07_01.bvh"
    renamed.write_text((data_dir / "mocap/cmu_iclone/07_01.bvh").read_text().replace("CC_Base_", "Lab_"))
    assert catalogue_rig([renamed], data_dir, tmp_path / "cache", "rig") is None
    assert catalogue_rig([runs[0], data_dir / "mocap/cmu_iclone/07_01.bvh"], data_dir, tmp_path, "rig") is None


def test_a_folder_whose_feet_never_stand_flat_is_scored_with_the_feet_level_at_their_contact(
    data_dir, tmp_path
) -> None:
    """li2018's sprints never stand flat for the 10 frames a level foot frame needs: fitted on them alone (no data
    directory to take the rig's frames from), each foot is taken level where it moves slowest, within a few
    degrees of the frames the rig's walks give; before, such a folder could not be scored at all."""
    from service.core.body import BODY_SEGMENTS, NoStanceError, read_clip_offsets
    from training.data.catalog import mocap_entries
    from training.pose.data import build_rig_offsets, load_motion
    from training.pose.user_mocap import user_clips

    sprints = tmp_path / "sprints"
    sprints.mkdir()
    for e in mocap_entries(data_dir, ["run"], ["cmu_li2018"])[:2]:
        (sprints / (data_dir / e.path).name).symlink_to(data_dir / e.path)
        with pytest.raises(NoStanceError):
            read_clip_offsets(data_dir / e.path)
    [clip, _] = user_clips([sprints], None, "rig")
    walks = build_rig_offsets(data_dir, mocap_entries(data_dir, sources=["cmu_li2018"]), tmp_path / "c")["cmu_li2018"]
    motion = load_motion(Path(clip.path), "", 0, None, walks)  # the same clip in the frames of the rig's walks
    for side in ("Left", "Right"):
        k = BODY_SEGMENTS.index(f"{side}Foot")
        rel = np.einsum("tji,tjk->tik", motion.R_world_segment[:, k], clip.motion.R_world_segment[:, k])
        assert np.degrees(Rotation.from_matrix(rel).magnitude()).max() < 10.0, side


def test_a_user_s_files_that_cannot_be_scored_are_left_out_with_the_reason(data_dir, tmp_path) -> None:
    """One broken or too short file in a folder does not stop the others; a folder of nothing else is an error."""
    from service.core.bvh import BvhFormatError
    from training.data.catalog import mocap_entries
    from training.pose.user_mocap import MIN_USER_SECONDS, user_clips

    good = data_dir / mocap_entries(data_dir, ["run"], ["cmu_li2018"])[0].path
    lines = good.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith("Frames:"))
    short = lines[:k] + ["Frames: 3", lines[k + 1]] + lines[k + 2 : k + 5]  # 3 frames at 120 Hz
    folder = tmp_path / "clips"
    folder.mkdir()
    (folder / good.name).symlink_to(good)
    (folder / "short.bvh").write_text("\n".join(short) + "\n")
    (folder / "broken.bvh").write_text("HIERARCHY\nROOT Hips\n")
    skipped: list[dict[str, str]] = []
    [clip] = user_clips([folder], None, "rig", skipped=skipped)
    assert clip.path.endswith(good.name)
    reasons = {Path(s["clip"]).name: s["reason"] for s in skipped}
    assert set(reasons) == {"short.bvh", "broken.bvh"}
    assert f"shorter than {MIN_USER_SECONDS} s" in reasons["short.bvh"] and "MOTION" in reasons["broken.bvh"]
    (folder / good.name).unlink()
    (folder / "short.bvh").unlink()
    with pytest.raises(BvhFormatError, match="MOTION"):
        user_clips([folder], None, "rig")


def test_the_same_trial_in_two_rigs_reads_the_same_limbs_in_hinge_frames(data_dir, tmp_path) -> None:
    """li2018 and iClone retargeted the same CMU trials: in the hinge frames their arms and legs agree within a few
    degrees; the trunk, head and hands do not where their frames come from each rig's own joints, and the upper
    trunk does where it is read from the hip and shoulder joint centres (docs/pose.md)."""
    from training.pose.rig_check import paired_trial_angles

    apart = paired_trial_angles(data_dir, tmp_path)
    assert len(apart) == 21 and len(apart["T8"]) >= 8
    for side in ("Left", "Right"):
        for limb in ("UpperArm", "ForeArm", "UpperLeg", "LowerLeg"):
            assert np.median(apart[side + limb]) < 3.0, side + limb
    # the upper trunk read from the hip and shoulder joint centres: T8 and the shoulders agree, the head nearly
    thorax = paired_trial_angles(data_dir, tmp_path, trunk_axes="thorax")
    assert np.median(apart["T8"]) > 12.0 and np.median(thorax["T8"]) < 8.0
    for segment in ("LeftShoulder", "RightShoulder"):
        assert np.median(apart[segment]) > 10.0 and np.median(thorax[segment]) < 3.0, segment
    assert np.median(thorax["Head"]) < np.median(apart["Head"]) - 4.0
    for segment in ("Pelvis", "L5", "LeftForeArm", "RightLowerLeg"):  # the rest as before
        assert np.median(thorax[segment]) == pytest.approx(np.median(apart[segment]), abs=0.05), segment


def test_a_shipped_model_is_scored_in_the_frames_its_manifest_names() -> None:
    """evaluate-pose builds its clips from the manifest: the six-sensor default reads the thorax, the mRMR model
    (trained before that rule) the rigs' spines, and a manifest that names neither the old defaults."""
    from service.core.manifest import read_manifest
    from training.pose.pipeline import shipped_config

    models = Path(__file__).resolve().parents[3] / "onnx_models"
    served = read_manifest(next((models / "pose_full6").glob("*/manifest.json")))
    older = read_manifest(models / "pose_mrmr6" / "2.0.0" / "manifest.json")
    assert (served.training_data["trunk_axes"], shipped_config(served).data.trunk_axes) == ("thorax", "thorax")
    assert shipped_config(served).data.limb_twist == "hinge" and "trunk_axes" not in older.training_data
    assert shipped_config(older).data.trunk_axes == "spine"
    assert shipped_config(served).data.test_subjects == served.training_data["test_subjects"]


def test_an_unknown_trunk_rule_is_refused_not_read_as_another(tmp_path) -> None:
    from service.core.body import check_trunk_axes
    from training.pose.data import build_rig_offsets
    from training.pose.user_mocap import user_clips

    assert check_trunk_axes("thorax") == "thorax"
    for call in (
        lambda: user_clips([tmp_path], None, "hinge", trunk_axes="Thorax"),
        lambda: build_rig_offsets(tmp_path, [], tmp_path, trunk_axes="chest"),
    ):
        with pytest.raises(ValueError, match="trunk_axes is one of"):
            call()


def test_a_rig_s_frames_are_fitted_on_its_walks_and_on_all_its_clips_only_where_too_few_walks_give_offsets(
    tmp_path, monkeypatch
) -> None:
    """Which clips each rig's offsets average: its walks where three of them give offsets; all that give offsets
    where fewer do (too few walks, or walks that cannot be fitted); the other clips are read only then."""
    import training.pose.data as data
    from training.data.catalog import CatalogEntry

    def entry(source: str, name: str, activity: str) -> CatalogEntry:
        return CatalogEntry(f"{source}/{name}", source, "", activity, 60.0, "", "")

    clips = [entry("a", f"w{k}", "walk") for k in range(3)] + [entry("a", "d0", "dance")]  # three good walks
    clips += [entry("b", "w0", "walk"), entry("b", "d0", "dance"), entry("b", "d1", "dance")]  # one walk
    clips += [entry("c", f"w{k}", "walk") for k in range(3)] + [entry("c", "d0", "dance")]  # walks that fail
    turn = {e.path: k for k, e in enumerate(clips)}  # each clip's offsets: a turn of its own about z
    read: list[str] = []

    def job(args):
        _, e, _, _ = args
        read.append(e.path)
        if e.path.startswith("c/w") and e.path != "c/w0":
            return None
        return np.broadcast_to(Rotation.from_euler("z", turn[e.path], degrees=True).as_matrix(), (21, 3, 3))

    monkeypatch.setattr(data, "mocap_entries", lambda _: clips)
    monkeypatch.setattr(data, "_clip_offsets_job", job)
    monkeypatch.setattr(data, "ProcessPoolExecutor", _InProcessPool)
    monkeypatch.setattr(
        data,
        "rig_offsets",
        lambda per_clip: sorted(round(Rotation.from_matrix(o[0]).as_euler("xyz", degrees=True)[2]) for o in per_clip),
    )
    out = data.build_rig_offsets(tmp_path, clips, tmp_path)
    assert out == {"a": [0, 1, 2], "b": [4, 5, 6], "c": [7, 10]}  # a: its walks; b: all; c: the walk and the dance
    assert "a/d0" not in read  # a rig with three good walks never reads its other clips


class _InProcessPool:
    """ProcessPoolExecutor's ``map`` in this process (a monkeypatched job is not seen by worker processes)."""

    def __init__(self, max_workers: int) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass

    def map(self, fn, jobs, chunksize: int = 1):
        return map(fn, jobs)


def test_a_broken_file_beside_good_ones_of_an_unknown_skeleton_is_left_out_alone(data_dir, tmp_path) -> None:
    """The files of one skeleton share frames fitted on them: a file among them that cannot be read (truncated, a
    value that is not a number or not finite, a corrupt gzip) is left out with its own reason, and the others are
    fitted and scored without it; a mapping that cannot be read names its file."""
    import gzip
    import json

    from service.core.body import MappingError
    from tests.training.lab_rig import lab_clips, lab_mapping
    from training.pose.user_mocap import user_clips

    walk = tmp_path / "mine" / "walk"
    lab_clips(data_dir, walk, ["07_01", "07_02"])
    text = (walk / "07_01.bvh").read_text()
    head, motion = text.split("Frame Time:")
    rows = motion.splitlines()
    (walk / "truncated.bvh").write_text(head + "Frame Time:" + "\n".join(rows[: len(rows) // 2]) + "\n")
    (walk / "nan.bvh").write_text(
        head + "Frame Time:" + "\n".join([rows[0], rows[1].replace(" ", " nan ", 1)] + rows[2:])
    )
    (walk / "word.bvh").write_text(head + "Frame Time:" + "\n".join([rows[0], rows[1] + " x1"] + rows[2:]))
    (walk / "crc.bvh.gz").write_bytes(gzip.compress(text.encode())[:-8] + b"\0" * 8)
    mapping = tmp_path / "lab.json"
    mapping.write_text(json.dumps(lab_mapping()))
    skipped: list[dict[str, str]] = []
    clips = user_clips([tmp_path / "mine"], mapping, "hinge", skipped=skipped)
    assert sorted(Path(c.path).name for c in clips) == ["07_01.bvh", "07_02.bvh"]
    reasons = {Path(s["clip"]).name: s["reason"] for s in skipped}
    assert set(reasons) == {"truncated.bvh", "nan.bvh", "word.bvh", "crc.bvh.gz"}, reasons
    assert "values" in reasons["truncated.bvh"] and "not finite" in reasons["nan.bvh"]
    assert "'x1'" in reasons["word.bvh"] and "gzip" in reasons["crc.bvh.gz"]
    assert all(Path(s["clip"]).name in s["reason"] for s in skipped)  # each its own reason
    broken = tmp_path / "broken.yaml"
    broken.write_text("segments: [unclosed\n")
    with pytest.raises(MappingError, match="broken.yaml: not valid YAML"):
        user_clips([tmp_path / "mine"], broken, "hinge")
    twice = lab_mapping()
    twice["segments"]["RightUpperLeg"] = twice["segments"]["LeftUpperLeg"]
    mapping.write_text(json.dumps(twice))
    with pytest.raises(MappingError, match="share one"):
        user_clips([tmp_path / "mine"], mapping, "hinge")
