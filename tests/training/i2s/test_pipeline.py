"""The training job against a real MLflow tracking server: tiny configurations, a few steps each."""

from __future__ import annotations

import ast
from pathlib import Path

import httpx
import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from benchmarks.servers import start_service, stop
from service.core.manifest import read_manifest, write_manifest
from service.core.segments import SEGMENTS
from service.inference.registry import load_models, load_registry_models
from training.i2s.config import load_config
from training.i2s.data.mocap import KINEMATICS_VERSION
from training.i2s.pipeline import run_training
from training.i2s.ship import export_run
from training.tracking import record_evaluation

REPO = Path(__file__).resolve().parents[3]
TINY = [
    "data.activities=[walk]",
    "data.test_subjects=[cmu_07]",
    "train.steps_per_epoch=3",
    "train.max_epochs=2",
    "train.val_windows=256",
    "train.batch_size=64",
    "train.threads=2",
]
# The jobs' own real-data evaluation on one recording: scoring all 25 with a 16-pass network took most of the suite.
ONE_REAL = "data.real_eval_recordings=[ximu3_lowerbody]"


def test_assignment_job_logs_everything_and_moves_champion_only_on_a_win(
    mlflow_server: str, data_dir: Path, kinematics_cache: Path, tmp_path: Path
) -> None:
    cfg = load_config(REPO / "training/configs/i2s_assignment.yaml", TINY + ["tracking.experiment=test-i2s", ONE_REAL])
    run_id = run_training(cfg, data_dir, kinematics_cache, register=True, eval_max_windows=1500)
    client = MlflowClient()
    run = client.get_run(run_id)
    assert len(client.get_metric_history(run_id, "val_loss")) == 2
    assert 0.0 <= run.data.metrics["test_accuracy"] <= 1.0
    assert run.data.metrics["onnx_parity_max_abs"] < 1e-4
    artifacts = {a.path for a in client.list_artifacts(run_id, "plots")}
    assert {"plots/confusion_test.png", "plots/learning_curves.png"} <= artifacts
    assert {i.tags[0].value for i in run.inputs.dataset_inputs} == {"training", "validation", "test"}
    champion = client.get_model_version_by_alias(cfg.registered_model, "champion")
    assert champion.run_id == run_id

    # A second run on the same evaluation: champion moves iff its accuracy is strictly higher. It averages over
    # turns (about gravity for the leg classes only), which its manifest records, and trains on braced knees too.
    legs = "[LeftLowerLeg,LeftUpperLeg,RightUpperLeg,RightLowerLeg]"
    averaged = ["train.quarter_turns=true", "train.gravity_turns=2", f"train.gravity_turn_segments={legs}"]
    averaged.append("augmentation.stiff_knee_share=0.2")
    cfg2 = load_config(
        REPO / "training/configs/i2s_assignment.yaml", TINY + ["tracking.experiment=test-i2s", ONE_REAL, *averaged]
    )
    cfg2 = cfg2.model_copy(update={"seed": 1})
    run2 = run_training(cfg2, data_dir, kinematics_cache, register=True, eval_max_windows=1500)
    acc1 = run.data.metrics["test_accuracy"]
    acc2 = client.get_run(run2).data.metrics["test_accuracy"]
    now = client.get_model_version_by_alias(cfg.registered_model, "champion").run_id
    assert now == (run2 if acc2 > acc1 else run_id)

    def datasets(run_id: str) -> dict[str, str]:
        inputs = client.get_run(run_id).inputs.dataset_inputs
        return {i.tags[0].value: i.dataset.name for i in inputs}

    # the braced-knee variants joined training and validation; the test set is the recorded clips, as before
    first, second = datasets(run_id), datasets(run2)
    assert first["test"] == second["test"]
    assert first["training"] != second["training"] and first["validation"] != second["validation"]
    exporter = read_manifest(export_run(run2, tmp_path / "averaged", version="0.0.2") / "manifest.json").exporter
    assert exporter["gravity_turn_segments"] == legs.strip("[]").split(",") and exporter["gravity_turns"] == 2
    # `evaluate` on a shipped float32 file re-tags its registered version with the newer evaluation
    (tagged,) = record_evaluation(cfg.registered_model, run_id, "accuracy", 0.25, "re-evaluated")
    version = client.get_model_version(cfg.registered_model, tagged)
    assert (version.tags["eval_digest"], version.tags["eval_accuracy"]) == ("re-evaluated", "0.250000")

    # The service (a real uvicorn process) serves the champion straight from the registry, without mlflow.
    champion = client.get_model_version_by_alias(cfg.registered_model, "champion")
    proc, base = start_service(
        tmp_path / "no_local_models",
        mlflow_tracking_uri=mlflow_server,
        registry_models=f"models:/{cfg.registered_model}@champion",
        registry_cache_dir=str(tmp_path / "registry_cache"),
    )
    try:
        served = httpx.get(f"{base}/v1/models").json()["i2s_assignment"]
        assert f"@champion (version {champion.version})" in served["source"]
        assert served["mlflow"]["run_id"] == champion.run_id
        window = {"samples": np.tile([0.0, 0.0, 9.81, 0.5, 0.0, 0.0], (128, 1)).tolist()}
        r = httpx.post(f"{base}/v1/imu/windows", json={"windows": [window]})
        assert r.status_code == 200 and r.json()["results"][0]["segment"] in SEGMENTS
    finally:
        stop(proc)
    missing = load_registry_models(mlflow_server, [f"models:/{cfg.registered_model}@nope"], tmp_path / "c", 1)
    assert missing == {}

    # Export to an onnx_models tree; the service loads it and refuses a tampered copy.
    shipped = export_run(run_id, tmp_path / "onnx_models", version="0.0.1")
    manifest = read_manifest(shipped / "manifest.json")
    assert manifest.mlflow["run_id"] == run_id and manifest.task == "i2s_assignment"
    assert "licence" not in manifest.training_data  # the config's sources are CMU's (public domain)
    with np.load(shipped / "golden.npz") as z:
        got = load_models(tmp_path / "onnx_models", 1)["i2s_assignment"].run(z["imu"])
        np.testing.assert_allclose(got, z["expected"], atol=manifest.parity_atol)
    manifest.sha256 = "0" * 64
    write_manifest(manifest, shipped / "manifest.json")
    assert load_models(tmp_path / "onnx_models", 1) == {}


def test_alignment_job_runs_and_exports_unit_quaternions(
    mlflow_server: str, data_dir: Path, kinematics_cache: Path, tmp_path: Path
) -> None:
    flexion = ["tracking.experiment=test-i2s", "train.functional_axes=[LeftLowerLeg,RightLowerLeg]"]
    bandai = "data.sources=[cmu_iclone,bandai_namco_1]"  # gzipped clips at 30 fps, resampled to 60 Hz
    cfg = load_config(REPO / "training/configs/i2s_alignment.yaml", TINY + flexion + [ONE_REAL, bandai])
    run_id = run_training(cfg, data_dir, kinematics_cache, register=False, eval_max_windows=1500)
    run = MlflowClient().get_run(run_id)
    assert run.data.metrics["test_mean_angle_error_deg"] > 0.0
    assert "plots/angle_errors_test.png" in {a.path for a in MlflowClient().list_artifacts(run_id, "plots")}
    shipped = export_run(run_id, tmp_path / "onnx_models", version="0.0.1")
    model = load_models(tmp_path / "onnx_models", 1)["i2s_alignment"]
    q = model.run(np.random.default_rng(0).normal(size=(5, 128, 6)).astype(np.float32))
    assert q.shape == (5, 7, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-5)
    assert np.all(q[..., 0] >= 0)
    manifest = read_manifest(shipped / "manifest.json")
    assert manifest.output_kind == "quaternion_per_segment"
    assert manifest.exporter["kinematics_version"] == int(KINEMATICS_VERSION) == 2  # functional segment frames
    assert manifest.exporter["functional_axes"] == ["LeftLowerLeg", "RightLowerLeg"]
    assert run.data.tags["trains_on_bandai_namco"] == "true"
    assert manifest.training_data["licence"].startswith("CC BY-NC 4.0")


def test_a_training_fitted_elsewhere_is_tracked_here_and_only_with_its_own_config_and_clips(
    mlflow_server: str, data_dir: Path, kinematics_cache: Path, tmp_path: Path
) -> None:
    """`pack` → `fit` (no MLflow, no data directory; here on the CPU with a loader worker) → `train --fitted`:
    the run logs the fitted history and weights, says where they were trained, and refuses a fitted file whose
    config or clips differ from the run's."""
    import torch
    from typer.testing import CliRunner

    from training.cli import app
    from training.i2s.data.mocap import dataset_digest
    from training.i2s.data.split import load_clips, load_pack, recordings_digest, save_pack, split_clips
    from training.i2s.train import load_fitted

    overrides = TINY + ["tracking.experiment=test-fitted", ONE_REAL]
    cfg = load_config(REPO / "training/configs/i2s_alignment.yaml", overrides)
    clips = load_clips(cfg, data_dir, kinematics_cache)
    packed = load_pack(save_pack(clips, tmp_path / "clips.npz"))
    assert [c.digest for c in packed] == [c.digest for c in clips]
    np.testing.assert_allclose(packed[0].kin.gyr_rads, clips[0].kin.gyr_rads, rtol=1e-6, atol=1e-6)

    fitted = tmp_path / "fitted.pt"
    args = ["fit", str(REPO / "training/configs/i2s_alignment.yaml"), str(tmp_path / "clips.npz"), str(fitted)]
    for item in overrides + ["train.loader_workers=1"]:
        args += ["-s", item]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "best epoch" in result.output

    run_id = run_training(cfg, data_dir, kinematics_cache, register=False, eval_max_windows=500, fitted=fitted)
    run = MlflowClient().get_run(run_id)
    assert run.data.tags["fitted_device"] == "cpu" and run.data.tags["fitted_loader_workers"] == "1"
    history = MlflowClient().get_metric_history(run_id, "val_angle_error_deg")
    assert [m.step for m in history] == [1, 2]
    saved = torch.load(fitted, weights_only=True)
    assert history[-1].value == pytest.approx(saved["history"][-1]["val_angle_error_deg"])

    train_clips, val_clips, _ = split_clips(clips, cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed)
    digests = dataset_digest(train_clips), dataset_digest(val_clips), recordings_digest([])
    other = load_config(REPO / "training/configs/i2s_alignment.yaml", overrides + ["train.lr=5e-4"])
    with pytest.raises(ValueError, match=r"train.lr 0.001 there, 0.0005 here"):
        load_fitted(fitted, other, *digests)
    with pytest.raises(ValueError, match="fitted on other clips"):
        load_fitted(fitted, cfg, digests[0], "0" * 20, digests[2])


def test_fit_mixes_in_the_real_recordings_its_pack_carries_and_is_tracked_only_with_the_same_ones(
    mlflow_server: str, data_dir: Path, kinematics_cache: Path, tmp_path: Path
) -> None:
    """Zimmermann et al. 2018 §4.3 on another machine: `pack` carries the config's real training recordings, `fit` mixes
    them into its batches and validates on their held-back part (``val_real_*``), and `train --fitted` tracks the result
    with the real windows it used, refusing other real data; a pack without the recordings is refused."""
    import torch
    from typer.testing import CliRunner

    from service.core.recordings import read_recording
    from training.cli import app
    from training.i2s.data.mocap import dataset_digest
    from training.i2s.data.split import load_clips, load_pack_recordings, recordings_digest, split_clips
    from training.i2s.data.windows import RealWindowSampler
    from training.i2s.train import load_fitted

    config = REPO / "training/configs/i2s_assignment.yaml"
    name = "capacitive_sub01/CSBaseline"
    real = [f"data.real_train_recordings=[{name}]", "data.real_fraction=0.25", "data.real_val_weight=0.5"]
    scored = "data.real_eval_recordings=[capacitive_sub01/EMGBaseline,ximu3_lowerbody]"
    with pytest.raises(ValueError, match="names recordings this run trains on"):
        load_config(config, TINY + real + [f"data.real_eval_recordings=[{name}]"])
    overrides = TINY + ["tracking.experiment=test-fitted-real", scored] + real
    runner = CliRunner()

    def cli(*args: str, sets: list[str]) -> str:
        result = runner.invoke(app, [*args, *(x for item in sets for x in ("-s", item))])
        assert result.exit_code == 0, result.output
        return result.output

    common = ["--data-dir", str(data_dir), "--cache-dir", str(kinematics_cache)]
    cli("pack", str(config), str(tmp_path / "clips.npz"), *common, sets=overrides)
    recorded = read_recording(data_dir, name)
    packed = load_pack_recordings(tmp_path / "clips.npz")
    assert [r.name for r in packed] == [name]
    assert recordings_digest(packed) == recordings_digest([recorded])  # float32 on both sides, as windowed
    cli("pack", str(config), str(tmp_path / "sim_only.npz"), *common, sets=TINY)
    refused = runner.invoke(
        app,
        ["fit", str(config), str(tmp_path / "sim_only.npz"), str(tmp_path / "x.pt")]
        + [x for item in overrides for x in ("-s", item)],
    )
    assert refused.exit_code != 0 and "does not carry" in refused.output

    fitted = tmp_path / "fitted.pt"
    cli("fit", str(config), str(tmp_path / "clips.npz"), str(fitted), sets=overrides)
    saved = torch.load(fitted, weights_only=True)
    assert all("val_real_loss" in epoch for epoch in saved["history"])  # validated on the real held-back part

    cfg = load_config(config, overrides)
    run_id = run_training(cfg, data_dir, kinematics_cache, register=False, eval_max_windows=500, fitted=fitted)
    run = MlflowClient().get_run(run_id)
    windows = RealWindowSampler([recorded], "train", cfg.data.real_val_fraction).segment
    assert run.data.params["real_train_windows"] == str(len(windows))
    history = MlflowClient().get_metric_history(run_id, "val_real_loss")
    assert [m.value for m in history] == pytest.approx([e["val_real_loss"] for e in saved["history"]])
    # the run scores the real recordings it was told to, never one it trained on
    assert f"n_windows.{name.replace('/', '.')}" not in run.data.metrics
    assert "n_windows.capacitive_sub01.EMGBaseline" in run.data.metrics

    train_clips, val_clips, _ = split_clips(
        load_clips(cfg, data_dir, kinematics_cache), cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed
    )
    with pytest.raises(ValueError, match="other real recordings"):
        load_fitted(fitted, cfg, dataset_digest(train_clips), dataset_digest(val_clips), recordings_digest([]))


def test_real_loso_holds_each_person_out_once_and_pools_their_windows(
    mlflow_server: str, data_dir: Path, kinematics_cache: Path, tmp_path: Path
) -> None:
    """Two of the real people, two fold runs: each trains on every other person's recordings and is scored on
    their own only; the summary's pooled figures are the window-weighted means of the folds' held-out figures."""
    from service.core.recordings import read_all_real
    from training.i2s.pipeline import HELD_OUT_METRICS, run_real_loso

    cfg = load_config(
        REPO / "training/configs/i2s_assignment.yaml",
        TINY + ["tracking.experiment=test-i2s", "data.real_fraction=0.25", "train.max_epochs=1"],
    )
    chosen = ["ximu3_unknown", "movingreality_pp03"]
    summary_id, folds = run_real_loso(cfg, data_dir, kinematics_cache, eval_max_windows=300, people=chosen)
    persons: dict[str, set[str]] = {}
    for recording in read_all_real(data_dir):
        persons.setdefault(recording.subject, set()).add(recording.name)
    assert (
        len(persons) == 13
    )  # the capacitive subject, the x-IMU3 person, three gaitmap walkers, eight in MovingReality
    assert set(folds) == {*chosen, "pooled", "pooled/ximu3_lowerbody", "pooled/movingreality"}
    client = MlflowClient()
    for person in chosen:
        run = client.get_run(str(folds[person]["run_id"]))
        assert run.data.tags["real_loso_held_out"] == person
        trained_on = set(ast.literal_eval(run.data.params["data.real_train_recordings"]))
        assert trained_on == set().union(*persons.values()) - persons[person]  # everyone else, none of their own
        held_out = {k.removeprefix("n_windows.") for k in run.data.metrics if k.startswith("n_windows.")}
        assert held_out == {name.replace("/", ".") for name in persons[person]}  # scored on their own only
    total = sum(folds[p]["n_windows"] for p in chosen)
    assert folds["pooled"]["n_windows"] == total > 1000
    summary = client.get_run(summary_id)
    for key in HELD_OUT_METRICS:
        expected = sum(folds[p][key] * folds[p]["n_windows"] for p in chosen) / total
        assert summary.data.metrics[f"pooled_{key}"] == pytest.approx(expected)
        assert summary.data.metrics[f"movingreality.pooled_{key}"] == pytest.approx(folds["movingreality_pp03"][key])
        assert 0.0 <= expected <= 1.0
    assert "plots/real_loso.png" in {a.path for a in client.list_artifacts(summary_id, "plots")}
    from training.i2s.calibration import PREDICTIONS_ARTIFACT, fold_predictions

    kept = {a.path for a in client.list_artifacts(summary_id, "evaluation")}
    assert {f"{PREDICTIONS_ARTIFACT}.npz", f"{PREDICTIONS_ARTIFACT}.json"} <= kept
    held = fold_predictions(summary_id, data_dir)  # read back from the summary run: each fold's own person
    assert {h.person for h in held} == set(chosen)
    assert sum(len(h.sensors[0].moving) for h in held if h.person == "ximu3_unknown") > 0
    from service.core.manifest import read_manifest
    from training.i2s.ship import real_table

    table = real_table(summary_id, [REPO / "mlflow_snapshot/models/i2s_assignment/1.8.0"], data_dir).splitlines()
    assert len(table) == 2 + len(folds)  # header, rule, one row per person and per pooled group
    shipped = next(
        e.metrics
        for e in read_manifest(REPO / "mlflow_snapshot/models/i2s_assignment/1.8.0/manifest.json").evaluations
        if e.name == "real_recordings"
    )
    row = next(line for line in table if line.startswith("| ximu3_unknown"))
    own, joint = shipped["accuracy/ximu3_lowerbody"], shipped["window_joint_accuracy/ximu3_lowerbody"]
    assert row.endswith(f" {100 * own:.1f} / {100 * joint:.1f} % |"), row
    fold = folds["ximu3_unknown"]  # the fold's own figures, the per-moment answer weighing the swing the third
    assert "swinging together" in table[0]
    assert row.startswith(
        f"| ximu3_unknown ({int(fold['n_windows'])}) | {100 * fold['real_accuracy']:.1f} / "
        f"{100 * fold['real_window_joint_accuracy']:.1f} / {100 * fold['real_window_joint_swing_accuracy']:.1f} % |"
    ), row
    # run again (a job that stopped, started again): the finished folds are reused, not trained again
    _, again = run_real_loso(cfg, data_dir, kinematics_cache, eval_max_windows=300, people=chosen[:1])
    assert again[chosen[0]]["run_id"] == folds[chosen[0]]["run_id"]
    from training.i2s.pipeline import _finished_fold

    others = ast.literal_eval(client.get_run(str(folds[chosen[0]]["run_id"])).data.params["data.real_train_recordings"])
    same = cfg.model_copy(update={"data": cfg.data.model_copy(update={"real_train_recordings": others})})
    assert _finished_fold(same, chosen[0]) == folds[chosen[0]]["run_id"]
    changed = same.model_copy(update={"data": same.data.model_copy(update={"real_fraction": 0.3})})
    assert _finished_fold(changed, chosen[0]) is None  # another recipe trains its own folds
    # its folds quantised as a shipped file is (each calibrated on its own training people), scored on the same people
    import mlflow
    import onnx

    from training.i2s.quantize import input_convolutions, quantize_folds

    int8_id = quantize_folds(summary_id, data_dir, kinematics_cache, 64, False, "real", True)
    int8 = client.get_run(int8_id)
    assert int8.data.tags["quantized_from"] == summary_id and int8.data.tags["real_loso"] == "summary"
    for person in chosen:
        fold_run = client.get_run(int8.data.tags[f"fold_run.{person}"])
        assert fold_run.data.tags["quantized_from"] == folds[person]["run_id"]
        assert fold_run.data.tags["real_loso_held_out"] == person
        assert int8.data.metrics[f"{person}.n_windows"] == folds[person]["n_windows"]  # the same windows scored
        assert "real training windows" in fold_run.data.params["quantization"]
    assert {h.person for h in fold_predictions(int8_id, data_dir)} == set(chosen)
    fold_model = client.get_run(int8.data.tags[f"fold_run.{chosen[0]}"]).data.tags["model_uri"]
    graph = onnx.load(str(next(Path(mlflow.artifacts.download_artifacts(fold_model)).rglob("*.onnx")))).graph
    weights = {n.name: n.input[1] for n in graph.node if n.op_type == "Conv"}
    dequantized = {n.output[0] for n in graph.node if n.op_type == "DequantizeLinear"}
    first = input_convolutions(REPO / "onnx_models/i2s_assignment/1.11.0/model.onnx")
    assert first == ["/net/cnn/net/net.0/Conv"]
    assert [name for name, w in weights.items() if w not in dequantized] == first  # the input convolution stays float
    assert len(weights) == 3
    # an int8 fold is written out as a fold model is (the held-out time-to-answer benchmark serves it), its golden
    # pair within the parity it states
    from service.inference.registry import load_model
    from training.i2s.ship import write_run

    written = write_run(int8.data.tags[f"fold_run.{chosen[0]}"], tmp_path / "int8", version="0.0.0")
    manifest = read_manifest(written / "manifest.json")
    assert "quantization" in manifest.exporter and manifest.parity_atol >= 1e-4
    with np.load(written / "golden.npz") as golden:
        got = load_model(written, threads=1).run(golden["imu"])
        assert np.abs(got - golden["expected"]).max() <= manifest.parity_atol
    with pytest.raises(ValueError, match="not a real-loso summary run"):
        quantize_folds(str(folds[chosen[0]]["run_id"]), data_dir, kinematics_cache, 64, False, "real", True)
    with pytest.raises(ValueError, match="real_fraction > 0"):
        run_real_loso(load_config(REPO / "training/configs/i2s_assignment.yaml", TINY), data_dir, kinematics_cache)
    with pytest.raises(ValueError, match="no real recordings of \\['nobody'\\]"):
        run_real_loso(cfg, data_dir, kinematics_cache, people=["nobody"])
