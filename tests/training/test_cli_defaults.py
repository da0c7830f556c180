"""The evaluation commands default to the newest version shipped of their model, by version order, not by name."""

from pathlib import Path

import pytest
import typer

from training.cli import newest_shipped


def _ship(root: Path, name: str, version: str) -> None:
    (root / name / version).mkdir(parents=True)
    (root / name / version / "manifest.json").write_text("{}")


REPO_MODELS = Path(__file__).resolve().parents[2] / "onnx_models"


def test_the_newest_version_is_chosen_by_version_not_by_name(tmp_path):
    for version in ("2.9.0", "10.0.0", "3.0.0"):
        _ship(tmp_path, "pose_lower3", version)
    (tmp_path / "pose_lower3" / "11.0.0").mkdir()  # a folder without a shipped model is not a version
    assert newest_shipped(None, "pose_lower3", tmp_path) == tmp_path / "pose_lower3" / "10.0.0"


def test_a_given_model_is_kept_and_a_missing_one_says_what_to_pass(tmp_path):
    given = REPO_MODELS / "pose_lower3" / "3.0.0"
    assert newest_shipped(given, "pose_lower3", tmp_path, task="imu_pose") == given
    with pytest.raises(typer.BadParameter, match="no shipped version of flex_bilstm_cm"):
        newest_shipped(None, "flex_bilstm_cm", tmp_path)


def test_a_given_folder_that_is_no_model_of_the_task_says_what_it_is(tmp_path):
    with pytest.raises(typer.BadParameter, match="x/y is not a shipped model folder"):
        newest_shipped(Path("x/y"), "pose_lower3", tmp_path)
    with pytest.raises(typer.BadParameter, match=r"holds versions \[.*\]: name one"):
        newest_shipped(REPO_MODELS / "pose_lower3", "pose_lower3", tmp_path)
    with pytest.raises(typer.BadParameter, match="is a flex_pose model; this command scores imu_pose models"):
        newest_shipped(REPO_MODELS / "flex_bilstm_cm" / "4.0.0", "pose_lower3", tmp_path, task="imu_pose")


def test_every_default_of_the_repository_resolves():
    repo = Path(__file__).resolve().parents[2] / "onnx_models"
    for name in ("pose_lower3", "flex_bilstm_cm", "flex_capacitive_knee"):
        assert (newest_shipped(None, name, repo) / "manifest.json").is_file()
