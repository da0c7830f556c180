"""The pose job end to end against a real MLflow server, on the iClone CMU clips with tiny networks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from service.core.manifest import read_manifest
from service.inference.pose import PoseModel
from service.inference.registry import load_model
from tests.training.lab_rig import lab_clips, lab_mapping
from training.pose.config import SIX_SENSORS, PoseConfig
from training.pose.pipeline import run_pose_experiment

REPO = Path(__file__).resolve().parents[3]
TINY = {
    "data": {"sources": ["cmu_iclone"], "test_subjects": ["cmu_07"], "val_subjects": ["cmu_03"]},
    "train": {
        "sequences_per_epoch": 32,
        "batch_size": 16,
        "max_epochs": 2,
        "sequence_frames": 120,
        "context_frames": 30,
    },
}


@pytest.fixture(scope="module")
def shipped(
    mlflow_server: str, data_dir: Path, tmp_path_factory: pytest.TempPathFactory, canonical_cache: Path
) -> dict[str, dict]:
    models = tmp_path_factory.mktemp("onnx_models")
    cache = canonical_cache
    out = {}
    # the streaming model trains on data selected for walking (Zheng et al. 2021 §5, both steps), with the
    # joint-position term beside the rotation loss (its answers shifted by the look-ahead)
    walking = {**TINY["data"], "selection": {"reference_activities": ["walk"]}}
    for name, model, train, data in (
        ("tiny_full6", {"kind": "bilstm", "hidden": 16, "layers": 1}, {"lr_schedule": "cosine"}, TINY["data"]),
        (
            "tiny_full6_stream",
            {"kind": "lstm", "hidden": 16, "layers": 2, "look_ahead": 5},
            {"lr_schedule": "constant", "position_loss": 50.0},
            walking,
        ),
    ):
        train = {**TINY["train"], **train}
        cfg = PoseConfig.model_validate(
            {"name": name, "model": model, "data": data, "train": train, "tracking": {"experiment": "test-pose"}}
        )
        out[name] = run_pose_experiment(cfg, data_dir, cache, models, "0.0.1", workers=2)
    return out


def test_the_rotation_term_is_logged_apart_from_the_joint_position_term(shipped: dict[str, dict]) -> None:
    """``train_loss`` holds both terms where the position term is on; ``train_rotation_loss`` compares recipes."""
    client = MlflowClient()

    def history(name: str, key: str) -> list[float]:
        return [h.value for h in sorted(client.get_metric_history(shipped[name]["run_id"], key), key=lambda h: h.step)]

    plain, with_term = "tiny_full6", "tiny_full6_stream"
    assert history(plain, "train_rotation_loss") == pytest.approx(history(plain, "train_loss"))
    rotation, whole = history(with_term, "train_rotation_loss"), history(with_term, "train_loss")
    assert len(rotation) == len(whole) == 2 and all(r < t for r, t in zip(rotation, whole, strict=True))


def test_the_job_logs_its_run_registers_and_ships_a_valid_model(shipped: dict[str, dict]) -> None:
    result = shipped["tiny_full6"]
    client = MlflowClient()
    run = client.get_run(result["run_id"])
    m = run.data.metrics
    assert len(client.get_metric_history(run.info.run_id, "val_angle_deg_epoch")) == 2
    # the cosine schedule over 2 epochs: the full rate, then halfway down to its floor (5 % of it)
    lrs = [h.value for h in sorted(client.get_metric_history(run.info.run_id, "lr"), key=lambda h: h.step)]
    assert lrs == pytest.approx([1e-3, 1e-3 * (0.05 + 0.95 / 2)])
    for key in (
        "test_walk_angle_unsensed_deg",
        "test_walk_jpe_cm",
        "test_subject_cmu_07_sip_deg",
        "test_meanpose_walk_angle_unsensed_deg",
        "val_angle_unsensed_deg",
        "onnx_parity_max_abs",
    ):
        assert key in m and np.isfinite(m[key]), key
    assert 0.0 < m["test_walk_angle_all_deg"] < 180.0 and m["onnx_parity_max_abs"] < 1e-4
    plots = {a.path for a in client.list_artifacts(run.info.run_id, "plots")}
    assert {"plots/learning_curve.png", "plots/segment_errors_test.png", "plots/skeleton_walk.png"} <= plots
    assert {i.tags[0].value for i in run.inputs.dataset_inputs} == {"train", "validation", "test"}
    champion = client.get_model_version_by_alias("tiny_full6", "champion")
    assert champion.run_id == run.info.run_id
    manifest = read_manifest(Path(result["shipped"]) / "manifest.json")
    assert manifest.task == "imu_pose" and manifest.pose.sensors[0] == "Pelvis"
    assert manifest.training_data["bandai_namco"] is False and "licence" not in manifest.training_data
    assert manifest.training_data["limb_twist"] == "rig"  # the frames evaluate-pose scores it in
    assert manifest.training_data["trunk_axes"] == "spine"
    assert manifest.evaluations[0].metrics["test_walk_angle_all_deg"] == pytest.approx(
        m["test_walk_angle_all_deg"], abs=0.05
    )
    # the gait joints' flexion errors, logged by the run and recorded in the manifest, per motion type and overall
    for key in ("test_LeftKnee_flexion_deg", "test_walk_RightHip_flexion_deg", "test_walk_LeftAnkle_flexion_deg"):
        assert 0.0 <= m[key] < 180.0 and manifest.evaluations[0].metrics[key] == pytest.approx(m[key], abs=1e-4)


def test_an_offline_model_assembled_from_finished_runs_answers_as_their_mean(
    shipped: dict[str, dict], data_dir: Path, canonical_cache: Path, tmp_path: Path
) -> None:
    """``train.ensemble_of``: the finished run twice over answers what it answered (its validation figures), the
    manifest says what it was assembled from, and a run of another recipe is refused with what differs."""
    member = shipped["tiny_full6"]
    base = {"name": "tiny_full6", "model": {"kind": "bilstm", "hidden": 16, "layers": 1}, "data": TINY["data"]}
    base |= {"tracking": {"experiment": "test-pose"}}
    cfg = PoseConfig.model_validate(
        base | {"train": {**TINY["train"], "lr_schedule": "cosine", "ensemble_of": [member["run_id"]] * 2}}
    )
    out = run_pose_experiment(cfg, data_dir, canonical_cache, tmp_path, "0.0.2", workers=2)
    want, got = member["val"]["overall"]["all"], out["val"]["overall"]["all"]
    assert got["angle_all_deg"] == pytest.approx(want["angle_all_deg"], abs=1e-3)
    manifest = read_manifest(Path(out["shipped"]) / "manifest.json")
    assert manifest.training_data["ensemble_of"] == [member["run_id"]] * 2
    assert manifest.pose.architecture.startswith("mean of 2 × bilstm")
    other = shipped["tiny_full6_stream"]["run_id"]
    mixed = cfg.model_copy(update={"train": cfg.train.model_copy(update={"ensemble_of": [member["run_id"], other]})})
    with pytest.raises(ValueError, match=f"run {other} is not of this recipe.*model.kind"):
        run_pose_experiment(mixed, data_dir, canonical_cache, tmp_path, "0.0.3", workers=2)


def test_a_run_on_selected_data_logs_what_was_selected(shipped: dict[str, dict]) -> None:
    client = MlflowClient()
    run_id = shipped["tiny_full6_stream"]["run_id"]
    m = client.get_run(run_id).data.metrics
    assert 0 < m["selection_selected_frames"] <= m["selection_similar_frames"] and m["selection_reference_frames"] > 0
    trace = sorted(client.get_metric_history(run_id, "selection_score"), key=lambda h: h.step)
    assert len(trace) == m["selection_deletions"] + 1
    assert "plots/data_selection.png" in {a.path for a in client.list_artifacts(run_id, "plots")}
    assert m["selection_selected_runs"] >= 1 and "selection/frames.json" in {
        a.path for a in client.list_artifacts(run_id, "selection")
    }
    manifest = read_manifest(Path(shipped["tiny_full6_stream"]["shipped"]) / "manifest.json")
    assert manifest.training_data["selected_for"]["reference_activities"] == ["walk"]
    assert manifest.training_data["selected_for"]["selected_frames"] == m["selection_selected_frames"]


def test_the_streaming_model_frame_by_frame_equals_its_offline_evaluation(shipped: dict[str, dict]) -> None:
    """What the live stream answers is exactly what ``evaluate-pose`` scored on the same frames."""
    model = PoseModel(load_model(Path(shipped["tiny_full6_stream"]["shipped"]), 1))
    assert model.spec.streaming and model.spec.look_ahead_frames == 5
    rng = np.random.default_rng(0)
    features = rng.normal(size=(157, 66)).astype(np.float32)
    offline = model.predict(features)
    state, answers = model.new_state(), []
    for start in range(0, len(features), 7):  # packets of 7 frames, then the 5 look-ahead frames repeated at the end
        out, state = model.step(features[start : start + 7], state)
        answers.append(out)
    out, state = model.step(np.repeat(features[-1:], 5, axis=0), state)
    answers.append(out)
    live = np.concatenate(answers)[5:]
    np.testing.assert_allclose(live, offline, atol=1e-5)


def test_a_shipped_model_fine_tuned_on_own_motion_capture_of_an_unknown_rig(
    shipped: dict[str, dict], data_dir: Path, canonical_cache: Path, tmp_path: Path
) -> None:
    """``data.own`` (a folder per person, a mapping file) beside the data directory's clips, from the shipped
    file's weights (``train.init_from_onnx``): the own validation person chooses, starting from the shipped
    network's own figure on them (epoch 0); the own test person is reported; the manifest says what it trained on."""
    own = tmp_path / "lab"
    layout = {"ann/walk": ["07_01", "07_02"], "ann/turns": ["07_05"], "bob": ["07_03"], "cid/walk": ["07_04"]}
    for folder, names in layout.items():
        lab_clips(data_dir, own / folder, names)
    (tmp_path / "rig.json").write_text(json.dumps(lab_mapping()))
    start = Path(shipped["tiny_full6"]["shipped"])
    cfg = PoseConfig.model_validate(
        {
            "name": "tiny_full6_lab",
            "model": {"kind": "bilstm", "hidden": 16, "layers": 1},
            "data": {
                **TINY["data"],
                "own": {
                    "path": str(own),
                    "mapping": str(tmp_path / "rig.json"),
                    "val_people": ["bob"],
                    "test_people": ["cid"],
                    "share": 0.5,
                },
            },
            # no step moves the weights (lr 0): the warm start is never beaten and comes back as it was shipped
            "train": {**TINY["train"], "max_epochs": 1, "lr": 0.0, "init_from_onnx": str(start)},
            "tracking": {"experiment": "test-pose"},
        }
    )
    result = run_pose_experiment(cfg, data_dir, canonical_cache, tmp_path / "models", "0.0.1", workers=2)
    assert set(result["val"]["subject"]) == {"bob"}
    # the own held-out person is scored apart from the data directory's held-out subjects
    assert set(result["test_own"]["subject"]) == {"cid"} and set(result["test_own"]["activity"]) == {"walk"}
    assert "cid" not in result["test"]["subject"] and "cmu_07" in result["test"]["subject"]
    m = read_manifest(Path(result["shipped"]) / "manifest.json")
    assert [e.name for e in m.evaluations][1] == "own held-out people (simulated sensors)"
    assert "cid" in m.evaluations[1].data and "cid" not in m.evaluations[0].data
    assert m.training_data["best_epoch"] == 0
    import onnxruntime as ort

    with np.load(Path(result["shipped"]) / "golden.npz") as golden:
        features = golden["features"]
    answers = [
        ort.InferenceSession(str(d / "model.onnx"), providers=["CPUExecutionProvider"]).run(
            None, {"features": features}
        )
        for d in (start, Path(result["shipped"]))
    ]
    np.testing.assert_allclose(answers[0][0], answers[1][0], atol=1e-5)
    assert m.training_data["init_from"] == "tiny_full6 0.0.1"
    assert m.training_data["own"] | {"train_frames_60hz": 0} == {
        "train_people": ["ann"],
        "train_clips": 3,
        "train_frames_60hz": 0,
        "share_of_draws": 0.5,
        "validation_people": ["bob"],
        "test_people": ["cid"],
        "mapping": "rig.json",
    }
    assert "own" in m.training_data["sources"] and not m.training_data["bandai_namco"]
    # epoch 0 is the shipped network's validation figure on the own validation person (not on cmu_03)
    from service.core.calibration import features_per_frame
    from training.pose.config import served_chunks
    from training.pose.pipeline import VAL_SEED, own_clips
    from training.pose.train import build_net, fixed_sessions, validation_angle
    from training.pose.warmstart import warm_start_from_shipped

    _, val, _ = own_clips(cfg, data_dir, canonical_cache)
    net = build_net(cfg, features_per_frame(len(cfg.sensors)))
    net.load_state_dict(warm_start_from_shipped(start, cfg, net))
    expected = validation_angle(net, fixed_sessions(val, cfg, VAL_SEED), served_chunks(cfg))
    history = MlflowClient().get_metric_history(result["run_id"], "val_angle_deg_epoch")
    assert [h.step for h in sorted(history, key=lambda h: h.step)] == [0, 1]
    assert next(h.value for h in history if h.step == 0) == pytest.approx(expected, abs=1e-4)


def test_evaluate_pose_scores_a_bvh_folder_through_a_mapping_file(
    shipped: dict[str, dict], data_dir: Path, tmp_path: Path
) -> None:
    """A skeleton family we do not know (the iClone rig with its joints renamed) works through a mapping file."""
    clips = tmp_path / "walks"
    lab_clips(data_dir, clips, ["07_01", "07_02"])
    (tmp_path / "rig.json").write_text(json.dumps(lab_mapping()))
    model = shipped["tiny_full6"]["shipped"]
    base = [sys.executable, "-m", "training.cli", "evaluate-pose", str(clips), "--model", model]
    done = subprocess.run(
        [*base, "--mapping", str(tmp_path / "rig.json"), "--json"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout[done.stdout.index("{") :])
    assert [Path(c["clip"]).name for c in report["clips"]] == ["07_01.bvh", "07_02.bvh"]
    assert 0.0 < report["overall"]["all"]["angle_all_deg"] < 180.0 and report["overall"]["all"]["jpe_cm"] > 0.0
    assert set(report["activity"]) == {"walks"}
    # the body's translation: on the true pose the rule follows these walks far better than a pelvis kept in place
    walks = report["overall"]["all"]
    assert walks["trans_truth_1s_cm"] < 0.3 * walks["trans_still_1s_cm"] and walks["trans_1s_cm"] > 0.0
    # per segment, the error and its constant part per clip; where the errors are small (the sensors' own segments,
    # whatever this tiny network answers) the rotation mean's angle is at most the mean angle, up to its slack
    assert len(report["segments"]) == 21
    for name, seg in report["segments"].items():
        assert 0.0 <= seg["constant_per_clip_deg"] <= 180.0
        if name in SIX_SENSORS:
            assert seg["angle_deg"] < 20.0 and seg["constant_per_clip_deg"] <= seg["angle_deg"] + 0.5
    # per joint angle, over all clips and per motion type: six sensors answer every joint of the convention
    from service.core.joint_angles import JOINT_COMPONENTS, JOINTS

    angles = report["joint_angle_error_deg"]
    assert set(angles) == {"all", "walks"}
    assert list(angles["all"]) == [f"{j}_{c}" for j in JOINTS for c in JOINT_COMPONENTS]
    assert all(0.0 <= v <= 180.0 for v in angles["all"].values()) and angles["all"] == angles["walks"]
    bias = report["joint_angle_bias_deg"]["all"]
    assert list(bias) == list(angles["all"]) and all(abs(bias[k]) <= angles["all"][k] + 1e-9 for k in bias)
    # three simulated sessions per clip: the first is the one above, so the mean moves but stays near it, and
    # the interval over the clips holds the mean
    three = subprocess.run(
        [*base, "--mapping", str(tmp_path / "rig.json"), "--sessions", "3", "--json"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert three.returncode == 0, three.stderr[-2000:]
    more = json.loads(three.stdout[three.stdout.index("{") :])
    assert report["sessions"] == 1 and more["sessions"] == 3
    angle, angle3 = report["overall"]["all"]["angle_all_deg"], more["overall"]["all"]["angle_all_deg"]
    assert angle3 != angle and abs(angle3 - angle) < 0.25 * angle
    low, high = more["angle_all_interval_95"]["all"]
    assert low <= angle3 <= high
    unmapped = subprocess.run(base, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert unmapped.returncode != 0
    assert "--mapping" in " ".join((unmapped.stdout + unmapped.stderr).split())


def test_export_refuses_a_pose_run_and_says_how_its_files_are_written(shipped: dict[str, dict]) -> None:
    """``export`` copies I2S runs' files; a pose run's are written when it trains."""
    run_id = shipped["tiny_full6"]["run_id"]
    done = subprocess.run(
        [sys.executable, "-m", "training.cli", "export", run_id, "--out-root", "/nonexistent"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    said = " ".join((done.stdout + done.stderr).split())
    assert done.returncode != 0 and "imu_pose" in said and "--ship" in said


def test_evaluate_pose_scores_the_validation_subjects_on_the_sessions_training_judged_by(
    shipped: dict[str, dict], data_dir: Path, canonical_cache: Path
) -> None:
    """Two files are compared on the same validation sessions as their runs were (how a recipe is chosen)."""
    result = shipped["tiny_full6"]
    base = [sys.executable, "-m", "training.cli", "evaluate-pose", "--model", result["shipped"]]
    where = ["--data-dir", str(data_dir), "--cache-dir", str(canonical_cache)]
    done = subprocess.run(
        [*base, *where, "--validation", "--json"], capture_output=True, text=True, cwd=REPO, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout[done.stdout.index("{") :])
    assert set(report["subject"]) == {"cmu_03"}  # the validation subject, not the held-out cmu_07
    val = MlflowClient().get_run(result["run_id"]).data.metrics["val_angle_unsensed_deg"]
    # the run's own sessions, and its figures are the served file's: the run evaluates in the chunks the service runs
    # (120 frames here; the validation clips are longer)
    assert report["overall"]["all"]["angle_unsensed_deg"] == pytest.approx(val, abs=1e-3)
    refused = subprocess.run([*base, *where, "--validation", "--record"], capture_output=True, text=True, cwd=REPO)
    assert refused.returncode != 0 and "--record" in " ".join((refused.stdout + refused.stderr).split())
    # --tag writes the served file's figure into its registry version, under the digest that names the protocol
    tagged = subprocess.run([*base, *where, "--validation", "--tag"], capture_output=True, text=True, cwd=REPO)
    assert tagged.returncode == 0, tagged.stderr[-2000:]
    [version] = MlflowClient().search_model_versions(f"name='tiny_full6' and run_id='{result['run_id']}'")
    assert version.tags["eval_digest"].endswith("|served-chunks")  # a model in the rig frames: no knee hinges
    assert float(version.tags["eval_val_angle_unsensed_deg"]) == pytest.approx(val, abs=1e-3)
    refused = subprocess.run([*base, *where, "--tag"], capture_output=True, text=True, cwd=REPO)
    assert refused.returncode != 0 and "--validation" in " ".join((refused.stdout + refused.stderr).split())
    # the registry's figure is the runs' one session per clip
    more = [*base, *where, "--validation", "--tag", "--sessions", "2"]
    refused = subprocess.run(more, capture_output=True, text=True, cwd=REPO)
    assert refused.returncode != 0 and "--sessions" in " ".join((refused.stdout + refused.stderr).split())


def test_a_learned_velocity_is_trained_for_a_shipped_model_chosen_on_validation_and_shipped_only_if_it_helps(
    shipped: dict[str, dict], data_dir: Path, canonical_cache: Path, tmp_path: Path, mlflow_server: str
) -> None:
    """``pose-velocity-train`` for the tiny six-sensor model: its epoch and its share on the ground are chosen on
    the validation subject, the held-out table holds the rule beside it, the files ship and the registry's champion
    moves exactly when it beats the rule on validation, and the registered file answers through the service's path
    as torch did, its output shifted by its look-ahead."""
    import yaml

    from service.inference.registry import load_registry_models
    from service.inference.velocity import VelocityModel
    from training.pose.config import PoseVelocityConfig
    from training.pose.velocity import run_velocity_experiment

    pose_config = tmp_path / "tiny_full6.yaml"
    pose_config.write_text(yaml.safe_dump({"name": "tiny_full6", "data": TINY["data"], "train": TINY["train"]}))
    vcfg = PoseVelocityConfig(
        name="tiny_full6_velocity",
        pose_config=str(pose_config),
        pose_model=shipped["tiny_full6"]["shipped"],
        hidden=16,
        layers=1,
        max_epochs=2,
        sequences_per_epoch=32,
        shares=[0.5, 1.0],
        tracking={"experiment": "test-pose"},
    )
    models = tmp_path / "onnx_models"
    out = run_velocity_experiment(vcfg, data_dir, canonical_cache, models, "0.0.1")
    client = MlflowClient()
    run = client.get_run(out["run_id"])
    assert len(client.get_metric_history(out["run_id"], "val_velocity_1s_cm")) == 2
    assert {i.tags[0].value for i in run.inputs.dataset_inputs} == {"train", "validation", "test"}
    val = {k: v for k, v in run.data.metrics.items() if k.startswith("val_trans_")}
    assert {"val_trans_rule_1s_cm", "val_trans_share_0.5_1s_cm", "val_trans_share_1_1s_cm"} <= set(val)
    share = out["share"]
    shares = (val["val_trans_share_0.5_1s_cm"], val["val_trans_share_1_1s_cm"])
    assert val[f"val_trans_share_{share:g}_1s_cm"] == min(shares) == val["val_trans_learned_1s_cm"]
    assert "walk" in out["test"] and {"rule", f"share_{share:g}", "velocity", "still"} <= set(out["test"]["all"])
    beats = val[f"val_trans_share_{share:g}_1s_cm"] < val["val_trans_rule_1s_cm"]
    assert run.data.tags["beats_rule_on_validation"] == str(beats)
    assert (out["shipped"] is not None) == beats == (models / "tiny_full6_velocity" / "0.0.1").is_dir()
    assert run.data.tags["promoted_to_champion"] == str(beats)
    aliases = client.get_registered_model("tiny_full6_velocity").aliases
    assert ("champion" in aliases) == beats
    # the registered file, as the service fetches it from the registry, answers as torch did
    [version] = client.search_model_versions(f"name='tiny_full6_velocity' and run_id='{out['run_id']}'")
    uri = f"models:/tiny_full6_velocity/{version.version}"
    model = VelocityModel(load_registry_models(mlflow_server, [uri], tmp_path / "registry", 1)["tiny_full6_velocity"])
    assert model.spec.learned_share == share and model.spec.sensors == SIX_SENSORS and model.spec.chosen_with
    import mlflow
    import torch

    from training.pose.velocity import VelocityNet, predict_velocity

    state = torch.load(
        mlflow.artifacts.download_artifacts(run_id=out["run_id"], artifact_path="checkpoint/model_state.pt")
    )
    net = VelocityNet(state["mean"].shape[0], 16, 1, model.spec.look_ahead_frames)
    net.load_state_dict(state)
    features = np.random.default_rng(0).normal(size=(90, state["mean"].shape[0])).astype(np.float32)
    np.testing.assert_allclose(model.predict(features), predict_velocity(net.eval(), features), atol=1e-4)
