"""The flex jobs end to end against a real MLflow server: simulated suits from real BVH (the iClone CMU clips)
and the real capacitive sleeves, with tiny training budgets; the shipped ONNX files score as torch did."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from service.core.manifest import read_manifest
from service.core.recordings import CAPACITIVE_CHANNELS, read_capacitive_sleeve
from service.inference.flex import FlexModel
from service.inference.registry import load_model
from tests.training.lab_rig import lab_clips, lab_mapping
from training.flex.capacitive import (
    UnscorableSubject,
    evaluate_capacitive,
    read_trials,
    run_capacitive_experiment,
)
from training.flex.config import CapacitiveConfig, FlexConfig
from training.flex.pipeline import build_sets, evaluate_served, load_flex_data, log_summary_run, run_flex_experiment
from training.flex.simulate import AGEING_BEYOND

TINY = {
    # the served suit's frames, whose hinges' zeros the service answers as zeros (FlexModel.answer_mask)
    "data": {
        "sources": ["cmu_iclone"],
        "test_subjects": ["cmu_07"],
        "val_subjects": ["cmu_03"],
        "suits_per_clip": 1,
        "limb_twist": "hinge",
    },
    "train": {"windows_per_epoch": 128, "max_epochs": 2, "patience": 5},
    "tracking": {"experiment": "test-flex"},
}
REPO = Path(__file__).resolve().parents[3]
SMALL = [8, 16, 16, 16, 8]  # the plumbing, not the fit: a Bi-LSTM of 1/1000 of appendix B's weights, its five layers


@pytest.fixture(scope="module")
def flex_runs(
    mlflow_server: str, data_dir: Path, tmp_path_factory: pytest.TempPathFactory, canonical_cache: Path
) -> dict:
    models = tmp_path_factory.mktemp("onnx_models")
    cache = canonical_cache
    cfgs = [
        FlexConfig.model_validate(
            {"name": "tiny_flex_cm", "model": {"calibration": True, "median": True, "bilstm_sizes": SMALL}, **TINY}
        ),
        FlexConfig.model_validate({"name": "tiny_flex_fcn", "model": {"kind": "fcn"}, **TINY}),
    ]
    data = load_flex_data(cfgs[0], data_dir, cache)
    sets = build_sets(cfgs[0], data)
    results = [run_flex_experiment(cfgs[0], data, sets, models, "0.0.1"), run_flex_experiment(cfgs[1], data, sets)]
    return {
        "results": results,
        "summary": log_summary_run(results, "test-flex"),
        "data": data,
        "models": models,
        "cache": cache,
    }


def test_each_network_is_a_run_with_its_metrics_plots_and_registered_model(flex_runs: dict) -> None:
    client = MlflowClient()
    for r in flex_runs["results"]:
        run = client.get_run(r["run_id"])
        m = run.data.metrics
        for key in (
            "test_mae_deg",
            "test_jitter_deg_s3",
            "val_mae_deg",
            "test_meanpose_mae_deg",
            "test_joint_LeftKnee_deg",
            "test_replaced_mae_deg",
            "test_other_lot_mae_deg",
            "run_time_ms_per_window",
            "train_wall_time_s",
            "onnx_parity_max_abs",
        ):
            assert key in m and np.isfinite(m[key]), key
        assert len(client.get_metric_history(run.info.run_id, "test_ageing_mae_deg")) == 6  # the ageing curve
        assert len(client.get_metric_history(run.info.run_id, "val_mae_deg_epoch")) == 2
        plots = {a.path for a in client.list_artifacts(run.info.run_id, "plots")}
        assert {
            "plots/learning_curve.png",
            "plots/ageing_error.png",
            "plots/joint_errors_test.png",
            "plots/trace_walk.png",
        } <= plots
        assert run.data.tags["trains_on_bandai_namco"] == "False"
    versions = client.search_model_versions("name='tiny_flex_cm'")
    assert len(versions) == 1
    summary = client.get_run(flex_runs["summary"])
    assert {a.path for a in client.list_artifacts(summary.info.run_id, "table")} == {
        "table/table5.csv",
        "table/table5.md",
    }
    assert "BiLSTM-CM_test_mae_deg" in summary.data.metrics and "FCN_test_mae_deg" in summary.data.metrics


def test_the_shipped_flex_model_is_served_and_scores_as_in_its_run(flex_runs: dict) -> None:
    target = flex_runs["models"] / "tiny_flex_cm" / "0.0.1"
    manifest = read_manifest(target / "manifest.json")
    assert manifest.task == "flex_pose" and manifest.flex.calibration and manifest.flex.latency_samples == 1
    assert manifest.channels == ["LeftKnee_flex", "RightKnee_flex", "LeftElbow_flex", "RightElbow_flex"]
    assert manifest.value_range == [0.0, 4095.0] and manifest.sample_rate_hz == 20.0 and manifest.window_samples == 100
    assert manifest.training_data["limb_twist"] == "hinge"  # the frames evaluate-flex scores it in
    assert manifest.training_data["trunk_axes"] == "spine"
    model = FlexModel(load_model(target, 1))
    # the file's golden output is the network's own; the service's answer holds the hinges' zeros, as the run scored
    golden = np.load(target / "golden.npz")
    raw = model.loaded.run(golden["counts"])
    np.testing.assert_allclose(raw, golden["expected"], atol=1e-3)
    assert np.abs(raw[:, model.answer_mask == 0]).max() > 0 and np.all(
        model.run_windows(golden["counts"])[:, model.answer_mask == 0] == 0
    )
    served = evaluate_served(model.loaded, flex_runs["data"])
    logged = flat = flex_runs["results"][0]
    assert served["test"]["mae_deg"] == pytest.approx(logged["test"]["mae_deg"], abs=0.02)
    assert served["ageing"][0.3]["mae_deg"] == pytest.approx(flat["ageing"][0.3]["mae_deg"], abs=0.02)
    # each joint's error is the mean of its three angles' errors, and no angle's bias exceeds its error
    test = served["test"]
    for joint, error in test["per_joint"].items():
        parts, bias = test["per_component"][joint], test["bias"][joint]
        assert np.mean(list(parts.values())) == pytest.approx(error, abs=1e-3)
        assert all(abs(bias[c]) <= parts[c] + 1e-3 for c in parts)


def test_evaluate_flex_rescores_the_validation_suits_and_tags_the_registry_version(
    flex_runs: dict, data_dir: Path
) -> None:
    """A shipped file is scored on the validation suits its run chose by, and ``--tag`` writes that figure and the
    evaluation digest of this installation into its registry version, which ``maybe_promote`` compares by."""
    run_id = flex_runs["results"][0]["run_id"]
    client = MlflowClient()
    [version] = client.search_model_versions(f"name='tiny_flex_cm' and run_id='{run_id}'")
    client.set_model_version_tag("tiny_flex_cm", version.version, "eval_digest", "an older installation's")
    base = [sys.executable, "-m", "training.cli", "evaluate-flex", "--model"]
    base += [str(flex_runs["models"] / "tiny_flex_cm" / "0.0.1"), "--data-dir", str(data_dir)]
    base += ["--cache-dir", str(flex_runs["cache"])]
    done = subprocess.run([*base, "--validation", "--json"], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    val = client.get_run(run_id).data.metrics["val_mae_deg"]
    scored = json.loads(done.stdout[done.stdout.index("{") :])
    assert scored["mae_deg"] == pytest.approx(val, abs=0.02)
    # the validation suits aged beyond the training range, as the run logged them (a choice made for ageing looks
    # there, not at the held-out people)
    logged = {m.step: m.value for m in client.get_metric_history(run_id, "val_ageing_mae_deg")}
    assert sorted(logged) == [round(100 * b) for b in AGEING_BEYOND]
    assert scored["ageing"]["0.45"]["mae_deg"] == pytest.approx(logged[45], abs=0.02)
    refused = subprocess.run([*base, "--tag"], capture_output=True, text=True, cwd=REPO)
    assert refused.returncode != 0 and "--validation" in " ".join((refused.stdout + refused.stderr).split())
    tagged = subprocess.run([*base, "--validation", "--tag"], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert tagged.returncode == 0, tagged.stderr[-2000:]
    tags = client.get_model_version("tiny_flex_cm", version.version).tags
    assert tags["eval_digest"] == flex_runs["data"].digest_val + "|hinge-zeros"  # scored as the service answers
    # --record writes the held-out figures as the service answers into the manifest, keeping the mean pose's
    path = flex_runs["models"] / "tiny_flex_cm" / "0.0.1" / "manifest.json"
    before = next(e for e in read_manifest(path).evaluations if e.name.startswith("held-out")).metrics
    recorded = subprocess.run([*base, "--record", "--json"], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert recorded.returncode == 0, recorded.stderr[-2000:]
    held_out = json.loads(recorded.stdout[recorded.stdout.index("{") :])["test"]
    after = next(e for e in read_manifest(path).evaluations if e.name.startswith("held-out")).metrics
    assert set(after) == set(before) and after["test_meanpose_mae_deg"] == before["test_meanpose_mae_deg"]
    assert after["test_mae_deg"] == pytest.approx(held_out["mae_deg"], abs=1e-4)
    refused = subprocess.run([*base, "--record", "--validation"], capture_output=True, text=True, cwd=REPO)
    assert refused.returncode != 0
    assert float(tags["eval_val_mae_deg"]) == pytest.approx(val, abs=0.02)


def test_sleeve_channels_are_read_by_name_and_a_failed_read_out_ends_the_recording(data_dir: Path) -> None:
    left, rate = read_capacitive_sleeve(data_dir, "CSBaseline", "Left")
    right, _ = read_capacitive_sleeve(data_dir, "CSBaseline", "Right")
    assert rate == pytest.approx(100.0) and left.shape == (5950, len(CAPACITIVE_CHANNELS))
    assert 3900 < len(right) < 4000  # the right sleeve fails at 39.7 s of this trial
    assert np.all(np.abs(right / np.median(right, axis=0) - 1) < 0.5)
    # the right file lists the channels the other way round (Top_Thigh first); by name Bot_Shank comes first
    assert abs(np.median(left[:, 0]) - 9160) < 100
    assert abs(np.median(right[:, 0]) - 911) < 30 and abs(np.median(right[:, 6]) - 1291) < 30


def test_the_capacitive_job_trains_on_one_trial_and_reports_the_other(
    mlflow_server: str, data_dir: Path, tmp_path: Path
) -> None:
    cfg = CapacitiveConfig.model_validate(
        {
            "name": "tiny_capacitive",
            "model": {"calibration": True, "median": True, "input_norm": "window_relative", "bilstm_sizes": SMALL},
            "train": {"windows_per_epoch": 128, "max_epochs": 1},
            "tracking": {"experiment": "test-flex-capacitive"},
        }
    )
    out = run_capacitive_experiment(cfg, data_dir, tmp_path, "0.0.1")
    m = out["metrics"]
    assert {"test_left_knee_mae_deg", "test_right_knee_mae_deg", "test_mae_deg", "val_mae_deg"} <= set(m)
    assert 0.0 <= m["test_beyond_training_share"] < 1.0 and "test_within_training_mae_deg" in m
    loaded = load_model(tmp_path / "tiny_capacitive" / "0.0.1", 1)
    assert loaded.manifest.channels == list(CAPACITIVE_CHANNELS) and loaded.manifest.joints == ["Knee"]
    assert loaded.manifest.sample_rate_hz == 50.0 and loaded.manifest.value_range is None
    again = evaluate_capacitive(loaded, data_dir, "CSStiffKnee", "CSBaseline")
    assert again["mae_deg"] == pytest.approx(m["test_mae_deg"], abs=0.02)
    assert again["per_leg_mae_deg"]["Left"] == pytest.approx(m["test_left_knee_mae_deg"], abs=0.02)
    assert not again["trained_on_this_trial"]

    # the model for others trains on both trials and carries that run's held-out figures as its recipe's
    every = cfg.model_copy(update={"name": "tiny_capacitive_all", "also_train": ["CSStiffKnee"], "test_trial": None})
    final = run_capacitive_experiment(every, data_dir, tmp_path, "0.0.2", [out["run_id"]])
    assert not any(k.startswith("test_") for k in final["metrics"])
    assert {"val_csbaseline_left_mae_deg", "val_csstiffknee_right_mae_deg"} <= set(final["metrics"])
    manifest = read_manifest(tmp_path / "tiny_capacitive_all" / "0.0.2" / "manifest.json")
    assert manifest.training_data["train_trials"] == ["CSBaseline", "CSStiffKnee"]
    lags = manifest.training_data["sleeve_lag_s"]  # the sleeves put in step with the Xsens sensors before training
    assert lags["CSBaseline/Left"] == pytest.approx(0.25) and abs(lags["CSStiffKnee/Left"]) <= 0.01
    [recipe] = manifest.evaluations
    assert recipe.name == "recipe held out on CSStiffKnee" and out["run_id"] in recipe.command
    assert recipe.metrics["test_mae_deg"] == pytest.approx(m["test_mae_deg"], abs=1e-3)
    scored = evaluate_capacitive(load_model(tmp_path / "tiny_capacitive_all" / "0.0.2", 1), data_dir, "CSStiffKnee")
    assert scored["trained_on_this_trial"] and scored["hinge_fitted_on"] == "CSStiffKnee"  # a trial on its own
    assert 0.0 < scored["mae_deg"] < 90.0 and set(scored["per_leg_mae_deg"]) == {"Left", "Right"}
    # another subject recorded the same way is scored from its own folder (here the same files under another name)
    other = tmp_path / "other_data"
    (other / "imu_real" / "capacitive_subx").mkdir(parents=True)
    (other / "imu_real" / "capacitive_subx" / "CSStiffKnee").symlink_to(
        data_dir / "imu_real" / "capacitive_sub01" / "CSStiffKnee"
    )
    theirs = evaluate_capacitive(
        load_model(tmp_path / "tiny_capacitive_all" / "0.0.2", 1), other, "CSStiffKnee", source="capacitive_subx"
    )
    assert not theirs["trained_on_this_trial"] and theirs["mae_deg"] == pytest.approx(scored["mae_deg"], abs=1e-6)
    # a subject whose right sleeve was not recorded is scored on the left leg, the right one named with its reason
    one_leg = other / "imu_real" / "capacitive_suby" / "CSStiffKnee"
    one_leg.mkdir(parents=True)
    for f in (data_dir / "imu_real" / "capacitive_sub01" / "CSStiffKnee").iterdir():
        if not f.name.endswith("_RCS.mot"):
            (one_leg / f.name).symlink_to(f)
    left = evaluate_capacitive(
        load_model(tmp_path / "tiny_capacitive_all" / "0.0.2", 1), other, "CSStiffKnee", source="capacitive_suby"
    )
    assert left["per_leg_mae_deg"] == pytest.approx({"Left": scored["per_leg_mae_deg"]["Left"]}, abs=1e-6)
    assert list(left["skipped_legs"]) == ["Right"] and "_RCS.mot" in left["skipped_legs"]["Right"]
    with pytest.raises(FileNotFoundError, match="_RCS.mot"):  # training reads every leg or stops
        read_trials(
            CapacitiveConfig(name="x", source="capacitive_suby", train_trial="CSStiffKnee", test_trial=None), other
        )
    # one whose right tibia sensor is missing from its orientations: the right leg is named with the missing sensor
    no_tibia = other / "imu_real" / "capacitive_subz" / "CSStiffKnee"
    no_tibia.mkdir(parents=True)
    for f in (data_dir / "imu_real" / "capacitive_sub01" / "CSStiffKnee").iterdir():
        if f.name.endswith("_Orientations.sto"):
            (no_tibia / f.name).write_text(f.read_text().replace("tibia_r_imu", "tibia_x_imu", 1))
        else:
            (no_tibia / f.name).symlink_to(f)
    shankless = evaluate_capacitive(
        load_model(tmp_path / "tiny_capacitive_all" / "0.0.2", 1), other, "CSStiffKnee", source="capacitive_subz"
    )
    assert shankless["per_leg_mae_deg"] == pytest.approx(left["per_leg_mae_deg"], abs=1e-6)
    assert "no RightLowerLeg sensor" in shankless["skipped_legs"]["Right"]
    (one_leg / "OpenSim_Sub01_CSStiffKnee_LCS.mot").unlink()
    with pytest.raises(UnscorableSubject, match="no leg can be scored"):
        evaluate_capacitive(
            load_model(tmp_path / "tiny_capacitive_all" / "0.0.2", 1), other, "CSStiffKnee", source="capacitive_suby"
        )
    # a leg's sleeve held out over both trials (the nearest to another person's sleeve): its figures go in as well
    leg = cfg.model_copy(
        update={
            "name": "tiny_capacitive_leg",
            "also_train": ["CSStiffKnee"],
            "test_trial": None,
            "held_out_leg": "Left",
        }
    )
    left_out = run_capacitive_experiment(leg, data_dir)
    assert {"test_csbaseline_left_mae_deg", "test_csstiffknee_left_mae_deg", "test_mae_deg"} <= set(left_out["metrics"])
    assert not any("right" in k for k in left_out["metrics"] if k.startswith("test_"))
    with_leg = run_capacitive_experiment(every, data_dir, tmp_path, "0.0.3", [out["run_id"], left_out["run_id"]])
    assert with_leg["shipped"]
    names = [e.name for e in read_manifest(tmp_path / "tiny_capacitive_all" / "0.0.3" / "manifest.json").evaluations]
    assert names == ["recipe held out on CSStiffKnee", "recipe held out on the Left leg's sleeve"]
    with pytest.raises(ValueError, match="not both"):
        CapacitiveConfig.model_validate({"name": "x", "held_out_leg": "Left"})  # the stiff-knee trial is held out too
    # a run of another recipe (no calibration module) is refused as the held-out figure
    other = cfg.model_copy(
        update={"name": "tiny_capacitive_plain", "model": cfg.model.model_copy(update={"calibration": False})}
    )
    plain = run_capacitive_experiment(other, data_dir)
    with pytest.raises(ValueError, match="not this recipe"):
        run_capacitive_experiment(every, data_dir, None, None, [plain["run_id"]])
    # so is one whose sleeves were paired with the Xsens rows as the files give them
    unsynced = run_capacitive_experiment(
        cfg.model_copy(update={"name": "tiny_capacitive_unsynced", "sync": False}), data_dir
    )
    with pytest.raises(ValueError, match="sync"):
        run_capacitive_experiment(every, data_dir, None, None, [unsynced["run_id"]])
    # and a single network's as the figure of the mean of several (refused before anything trains)
    several = every.model_copy(update={"train": every.train.model_copy(update={"members": 2})})
    with pytest.raises(ValueError, match="train.members"):
        run_capacitive_experiment(several, data_dir, None, None, [out["run_id"]])


def test_synchronised_pairs_the_rows_read_at_the_same_moment() -> None:
    from training.flex.capacitive import synchronised

    # values are the moment each row was read at
    a, b = synchronised(np.arange(10.0) - 3, np.arange(10.0), 3)  # the sleeve's row t + 3 read at row t
    np.testing.assert_array_equal(a, b)
    assert list(b) == list(range(7))
    a, b = synchronised(np.arange(10.0) + 2, np.arange(8.0), -2)  # the sleeve ahead: its row t - 2 read at row t
    np.testing.assert_array_equal(a, b)
    assert list(b) == list(range(2, 8))
    a, b = synchronised(np.arange(5.0), np.arange(6.0), 0)
    np.testing.assert_array_equal(a, b)
    assert len(a) == 5


def test_bandai_share_sets_bandai_namco_s_part_of_the_draws_and_leaves_the_rest_by_frames() -> None:
    from training.flex.data import FlexClip, window_set

    def clip(path: str, source: str, activity: str, frames: int) -> FlexClip:
        T = frames + 4
        return FlexClip(path, source, "g", activity, np.zeros((T, 1, 3), np.float32), np.zeros((T, 4), np.float32), 4)

    clips = [
        clip("b1", "bandai_namco_1", "walk", 900),
        clip("b2", "bandai_namco_2", "run", 90),
        clip("c1", "cmu_iclone", "walk", 60),
        clip("c2", "cmu_li2018", "walk", 30),
    ]
    by_frames = window_set(clips, 1, 0, 5)
    share = window_set(clips, 1, 0, 5, bandai_share=0.5)
    bandai = np.isin(share.clip_of_end, [0, 1])
    assert by_frames.weights[bandai].sum() == pytest.approx(990 / 1080)
    assert share.weights[bandai].sum() == pytest.approx(0.5)
    # within each side, windows keep their relative weights: c1's 60 frames draw twice c2's 30
    assert share.weights[share.clip_of_end == 2].sum() == pytest.approx(2 * share.weights[share.clip_of_end == 3].sum())


def test_mirror_adds_each_training_clip_performed_by_the_mirror_image_body(
    data_dir: Path, canonical_cache: Path
) -> None:
    cfg = FlexConfig.model_validate({"name": "tiny_flex", **TINY})
    plain = load_flex_data(cfg, data_dir, canonical_cache)
    both = load_flex_data(
        cfg.model_copy(update={"data": cfg.data.model_copy(update={"mirror": True})}), data_dir, canonical_cache
    )
    assert [c.path for c in both.val] == [c.path for c in plain.val]  # held-out sides untouched
    assert [c.path for c in both.test] == [c.path for c in plain.test]
    assert [c.path for c in both.train] == [c.path for c in plain.train] + [f"{c.path}#mirror" for c in plain.train]
    assert both.digest_train != plain.digest_train
    left, right = cfg.sensors.index("LeftKnee"), cfg.sensors.index("RightKnee")
    for c, m in zip(plain.train, both.train[len(plain.train) :], strict=True):
        # the mirror body's left knee bends as the clip's right knee did
        np.testing.assert_allclose(m.bend[:, left], c.bend[:, right], atol=1e-3)


def test_evaluate_flex_scores_a_bvh_folder_through_a_mapping_file(
    flex_runs: dict, data_dir: Path, tmp_path: Path
) -> None:
    """A user's own mocap, read as ``evaluate-pose`` reads it: the iClone clips of a known family, and the same
    clips renamed into a skeleton the job does not know with the mapping file a user writes for it, score alike per
    clip; per motion type (the folder), per joint, ageing and a replaced sensor; a file that cannot be read is left
    out with its reason; without the mapping the unknown skeleton is refused, saying what to give."""
    walks = tmp_path / "lab" / "walks"
    walks.mkdir(parents=True)
    for name in ("07_01", "07_02"):
        (walks / f"{name}.bvh").symlink_to(data_dir / "mocap/cmu_iclone" / f"{name}.bvh")
    (tmp_path / "rig.json").write_text(json.dumps(lab_mapping()))
    model = flex_runs["models"] / "tiny_flex_cm" / "0.0.1"
    base = [sys.executable, "-m", "training.cli", "evaluate-flex", str(tmp_path / "lab"), "--model", str(model)]
    base += ["--cache-dir", str(flex_runs["cache"])]
    env = {k: v for k, v in os.environ.items() if k != "WEARMOCAP_DATA_DIR"}  # frames fitted on the clips, alike
    env["COLUMNS"] = "1000"  # the usage error on one line

    def scored(*extra: str) -> dict:
        done = subprocess.run([*base, *extra, "--json"], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout[done.stdout.index("{") :])

    known = scored()
    for name in ("07_01", "07_02"):
        (walks / f"{name}.bvh").unlink()
    lab_clips(data_dir, walks, ["07_01", "07_02"])
    (walks / "broken.bvh").write_text("HIERARCHY\nROOT Hips\n")
    out = scored("--mapping", str(tmp_path / "rig.json"))
    test = out["test"]
    assert [Path(c["clip"]).name for c in test["clips"]] == ["07_01.bvh", "07_02.bvh"]
    assert [Path(s["clip"]).name for s in out["skipped"]] == ["broken.bvh"] and known["skipped"] == []
    for mine, theirs in zip(test["clips"], known["test"]["clips"], strict=True):
        assert mine["frames"] == theirs["frames"] and abs(mine["frames"] / 20.0 - 157 / 60.0) < 0.2  # 20 Hz
        assert mine["mae_deg"] == pytest.approx(theirs["mae_deg"], abs=1e-3)
    assert set(test["per_activity"]) == {"walks"}
    assert set(test["per_joint"]) == set(read_manifest(model / "manifest.json").joints)
    frames = np.array([c["frames"] for c in test["clips"]])
    assert test["mae_deg"] == pytest.approx(np.average([c["mae_deg"] for c in test["clips"]], weights=frames), abs=1e-3)
    assert set(out["ageing"]) == {str(b) for b in AGEING_BEYOND} and out["replaced"]["mae_deg"] > 0.0
    refused = subprocess.run([*base, "--validation"], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert refused.returncode != 0 and "give no paths" in " ".join((refused.stdout + refused.stderr).split())
    unmapped = subprocess.run(base, capture_output=True, text=True, cwd=REPO, env=env, timeout=300)
    assert unmapped.returncode != 0
    error = unmapped.stderr.split("Invalid value")[1]  # the usage error, after the files' warnings
    assert "--mapping" in error and "MOTION" not in error  # the skeleton's reason, not the broken file's


def test_the_served_suit_model_is_scored_in_the_frames_its_manifest_names() -> None:
    """evaluate-flex builds its clips from the manifest: the served suit model's angles are in the thorax frames,
    a manifest that names no trunk rule in the spine's."""
    from training.flex.pipeline import shipped_config

    models = Path(__file__).resolve().parents[3] / "onnx_models"
    served = read_manifest(next((models / "flex_bilstm_cm").glob("*/manifest.json")))
    cfg, td = shipped_config(served), served.training_data
    assert (cfg.data.trunk_axes, cfg.data.limb_twist) == (td["trunk_axes"], td["limb_twist"]) == ("thorax", "hinge")
    older = served.model_copy(
        update={"training_data": {k: v for k, v in served.training_data.items() if k != "trunk_axes"}}
    )
    assert shipped_config(older).data.trunk_axes == "spine"
    # it reads the counts back to resistance, so its manifest names the read-out's parts that this depends on
    assert served.flex.input_norm == "log_resistance"
    assert all("R_i 15 kΩ" in u and "G 2.3" in u for u in served.units.values())


def test_a_held_out_trial_s_error_splits_at_the_most_each_leg_bent_in_training() -> None:
    """Samples of a held-out trial that bend a knee further than that leg ever did in the training part are
    counted and scored apart: the stiff-knee leg's training range is its own, not the other leg's."""
    from types import SimpleNamespace

    from training.flex.capacitive import beyond_training_range

    def clip(path: str, top: float) -> SimpleNamespace:
        return SimpleNamespace(path=path, pad=2, angles=np.r_[99.0, 99.0, np.linspace(0.0, top, 50)][:, None, None])

    training = SimpleNamespace(clips=[clip("CSStiffKnee/Left", 30.0), clip("CSStiffKnee/Right", 50.0)])
    reference = np.array([10.0, 20.0, 40.0, 60.0])  # the same four samples on each leg
    traces = {"Left": (reference + [1.0, 1.0, 5.0, 9.0], reference), "Right": (reference + 2.0, reference)}
    split = beyond_training_range(traces, training)
    assert split["test_beyond_training_share"] == pytest.approx(3 / 8)  # left 40 and 60 (over 30), right 60
    assert split["test_beyond_training_mae_deg"] == pytest.approx((5.0 + 9.0 + 2.0) / 3)
    assert split["test_within_training_mae_deg"] == pytest.approx((1.0 + 1.0 + 2.0 + 2.0 + 2.0) / 5)
    inside = beyond_training_range({"Left": (reference[:2] + 1.0, reference[:2])}, training)
    assert inside == {"test_beyond_training_share": 0.0, "test_within_training_mae_deg": 1.0}
