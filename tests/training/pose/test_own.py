"""A user's own motion capture in pose training (``data.own``): how it is split, drawn and refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from service.core.body import BodyMotion
from training.pose.config import PoseConfig
from training.pose.data import OWN_SOURCE, MotionClip
from training.pose.pipeline import carries_bandai, own_clips, with_own
from training.pose.train import clip_weights
from training.pose.user_mocap import bvh_files


def clip(source: str, activity: str, frames: int) -> MotionClip:
    z = np.zeros((frames, 21, 3))
    motion = BodyMotion(np.broadcast_to(np.eye(3), (frames, 21, 3, 3)), z, z, 60.0)
    return MotionClip(f"{source}/{activity}/{frames}", source, "", activity, motion, "0" * 20)


def test_own_clips_get_their_share_of_the_draws_and_the_rest_are_weighed_as_without_them() -> None:
    theirs = [clip("bandai_namco_1", "walk", 600), clip("cmu_iclone", "walk", 200), clip("cmu_iclone", "run", 100)]
    own = [clip(OWN_SOURCE, "walk", 300), clip(OWN_SOURCE, "stairs", 100)]
    w = clip_weights(theirs + own, 72_000, bandai_share=0.25, own_share=0.3)
    assert w.sum() == pytest.approx(1.0)
    assert w[3:].sum() == pytest.approx(0.3) and w[3] == pytest.approx(0.3 * 0.75)
    np.testing.assert_allclose(w[:3], 0.7 * clip_weights(theirs, 72_000, bandai_share=0.25))
    # own clips only (share 1.0 drops the data directory's training clips before they are weighed)
    np.testing.assert_allclose(clip_weights(own, 72_000, own_share=1.0), [0.75, 0.25])


def test_a_config_that_validates_and_tests_on_one_person_or_fine_tunes_an_average_is_refused() -> None:
    own = {"path": "lab", "val_people": ["ann", "bob"], "test_people": ["bob"]}
    with pytest.raises(ValidationError, match="bob"):
        PoseConfig.model_validate({"name": "x", "data": {"own": own}})
    with pytest.raises(ValidationError, match="init_from_onnx"):
        PoseConfig.model_validate(
            {"name": "x", "train": {"init_from_onnx": "onnx_models/x/1.0.0", "ensemble_of": ["a", "b"]}}
        )
    with pytest.raises(ValidationError, match="share"):
        PoseConfig.model_validate({"name": "x", "data": {"own": {"path": "lab", "share": 0.0}}})


def test_an_own_folder_that_is_not_laid_out_per_person_says_what_it_has(tmp_path: Path) -> None:
    def attempt(**own) -> str:
        cfg = PoseConfig.model_validate({"name": "x", "data": {"own": own}})
        with pytest.raises(ValueError) as err:
            own_clips(cfg, tmp_path, tmp_path / "cache")
        return str(err.value)

    assert "is not a folder" in attempt(path=str(tmp_path / "absent"))
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "walk.bvh").write_text("HIERARCHY")
    assert "holds no folders" in attempt(path=str(tmp_path / "lab"))
    (tmp_path / "lab" / "ann").mkdir()
    said = attempt(path=str(tmp_path / "lab"), val_people=["anne"])
    assert "anne" in said and "['ann']" in said


def test_own_clips_alone_replace_the_data_directorys_and_own_validation_people_judge() -> None:
    theirs, their_val = [clip("cmu_iclone", "walk", 200)], [clip("cmu_iclone", "walk", 100)]
    own, own_val = [clip(OWN_SOURCE, "walk", 300)], [clip(OWN_SOURCE, "walk", 150)]
    assert with_own(theirs, their_val, own, own_val, 0.5) == (theirs + own, own_val)
    assert with_own(theirs, their_val, own, own_val, 1.0) == (own, own_val)
    assert with_own(theirs, their_val, own, [], 0.5) == (theirs + own, their_val)
    with pytest.raises(ValidationError, match="seen_share"):
        PoseConfig.model_validate({"name": "x", "data": {"seen_share": 0.1, "own": {"path": "lab", "share": 1.0}}})


def test_a_fine_tune_of_a_bandai_namco_network_carries_its_licence_whatever_it_trains_on() -> None:
    shipped = Path(__file__).resolve().parents[3] / "onnx_models/pose_full6_stream/4.0.0"
    own_only = [clip(OWN_SOURCE, "walk", 300)]
    assert not carries_bandai(PoseConfig(name="x"), own_only)
    assert carries_bandai(PoseConfig(name="x"), [*own_only, clip("bandai_namco_1", "walk", 300)])
    cfg = PoseConfig.model_validate({"name": "x", "train": {"init_from_onnx": str(shipped)}})
    assert carries_bandai(cfg, own_only)


def test_bvh_files_are_found_through_linked_folders(tmp_path: Path) -> None:
    (tmp_path / "elsewhere" / "walk").mkdir(parents=True)
    (tmp_path / "elsewhere" / "walk" / "a.bvh.gz").write_bytes(b"")
    (tmp_path / "elsewhere" / "notes.txt").write_text("")
    (tmp_path / "ann").mkdir()
    (tmp_path / "ann" / "b.bvh").write_text("")
    (tmp_path / "ann" / "linked").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    assert [p.relative_to(tmp_path) for p in bvh_files(tmp_path / "ann")] == [
        Path("ann/b.bvh"),
        Path("ann/linked/walk/a.bvh.gz"),
    ]
