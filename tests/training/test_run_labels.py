"""Run names and descriptions in the MLflow UI, from a run's params and tags."""

from __future__ import annotations

from training.config import flatten
from training.pose.config import PoseConfig
from training.run_labels import run_description, run_title


def test_a_pose_run_fine_tuned_on_own_mocap_says_so_and_from_which_file() -> None:
    cfg = PoseConfig.model_validate(
        {
            "name": "pose_full6_lab",
            "data": {"own": {"path": "/lab/mocap/", "val_people": ["p07"]}},
            "train": {"init_from_onnx": "onnx_models/pose_full6/4.0.0"},
        }
    )
    params = {k: str(v) for k, v in flatten(cfg.model_dump()).items()}
    assert run_title(params, {}, ["0.1.0"]) == (
        "pose_full6_lab · held out cmu_05, cmu_06, cmu_07 · + own mocap · from 4.0.0 · shipped 0.1.0"
    )
    assert "trained also on own motion capture (mocap), warm start from 4.0.0" in run_description(params, {}, [])
    plain = {k: str(v) for k, v in flatten(PoseConfig(name="pose_full6").model_dump()).items()}
    assert "own" not in run_title(plain, {}, []) and "own" not in run_description(plain, {}, [])
