"""Ship a tracked run: copy its ONNX model into ``onnx_models/<name>/<version>/`` with manifest.json and
golden.npz, then evaluate the shipped file and record the numbers (and their command) in the manifest.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import re
import shutil
import tempfile
from pathlib import Path

import mlflow
import numpy as np
import onnx
import torch
from mlflow.tracking import MlflowClient

from service.core.manifest import Evaluation, Manifest, TensorSpec, read_manifest, sha256_file, write_manifest
from service.core.segments import SEGMENTS
from service.core.windowing import HOP_SAMPLES, MODEL_RATE_HZ, WINDOW_SAMPLES
from training.data.catalog import BANDAI_LICENCE
from training.i2s.config import ExperimentConfig
from training.i2s.data.mocap import Clip, KinematicsParams, stiff_knee_variants
from training.i2s.evaluate import (
    EVAL_SEED,
    evaluate_braced_knees,
    evaluate_real,
    evaluate_real_alignment,
    evaluate_simulated,
    onnx_predictor,
)
from training.i2s.export import OPSET, OUTPUT_NAMES, PARITY_ATOL, onnx_parity
from training.i2s.metrics import confusion_matrix
from training.plots import confusion_matrix_png
from training.run_labels import record_shipped
from training.snapshot import local_run_id
from training.tracking import download_onnx, record_evaluation

log = logging.getLogger(__name__)

TASKS = {"assignment": "i2s_assignment", "alignment": "i2s_alignment"}


def _output_spec(task: str) -> tuple[TensorSpec, str]:
    if task == "assignment":
        return TensorSpec(
            name=OUTPUT_NAMES[task],
            shape=["batch", len(SEGMENTS)],
            dtype="float32",
            description="class probabilities (softmax inside the graph), classes order",
        ), "probabilities"
    return TensorSpec(
        name=OUTPUT_NAMES[task],
        shape=["batch", len(SEGMENTS), 4],
        dtype="float32",
        description="unit q_segment_imu (w, x, y, z), w >= 0, for each segment hypothesis "
        "in classes order: v_segment = R(q) v_imu",
    ), "quaternion_per_segment"


def run_version(run: mlflow.entities.Run) -> str:
    """The default model version of a run: its start time in UTC."""
    return dt.datetime.fromtimestamp(run.info.start_time / 1000, dt.UTC).strftime("%Y.%m.%d-%H%M%S")


def build_manifest(cfg: ExperimentConfig, run: mlflow.entities.Run, sha256: str, version: str) -> Manifest:
    """The manifest of a run's ONNX model (docs/conventions.md): written beside shipped files by ``export_run`` and
    embedded in the logged MLflow model's metadata by ``training.i2s.pipeline`` (for registry serving)."""
    output, kind = _output_spec(cfg.task)
    mlflow_info = {"run_id": run.info.run_id, "experiment_id": run.info.experiment_id}
    if "model_uri" in run.data.tags:
        mlflow_info["model_uri"] = run.data.tags["model_uri"]
    return Manifest(
        name=cfg.registered_model,  # the name it ships and is served under (several recipes, one served model)
        task=TASKS[cfg.task],
        version=version,  # type: ignore[arg-type]
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        inputs=[
            TensorSpec(
                name="imu",
                shape=["batch", WINDOW_SAMPLES, 6],
                dtype="float32",
                description="acc_x, acc_y, acc_z (m/s^2, specific force), gyr_x, gyr_y, gyr_z "
                "(rad/s), sensor frame, 60 Hz",
            )
        ],
        outputs=[output],
        output_kind=kind,  # type: ignore[arg-type]
        sample_rate_hz=MODEL_RATE_HZ,
        window_samples=WINDOW_SAMPLES,
        hop_samples=HOP_SAMPLES,
        channels=["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"],
        units={"acc": "m/s^2", "gyr": "rad/s"},
        classes=list(SEGMENTS),
        quaternion_convention="Hamilton, scalar first (w, x, y, z), unit, w >= 0; v_segment = R(q) v_imu"
        if cfg.task == "alignment"
        else None,
        sha256=sha256,
        training_data={
            "activities": cfg.data.activities,
            "test_subjects": cfg.data.test_subjects,
            "datasets": [
                {"context": _context(i), "name": i.dataset.name, "digest": i.dataset.digest, "source": i.dataset.source}
                for i in _inputs(run)
            ],
            "train_wall_time_s": run.data.metrics.get("train_wall_time_s"),
            "best_epoch": run.data.metrics.get("best_epoch"),
        }
        # real recordings the network trained on (Zimmermann et al. 2018 §4.3); no real-data evaluation may use them
        | ({"real_train_recordings": cfg.data.real_train_recordings} if cfg.data.real_train_recordings else {})
        | (_teacher(cfg) if cfg.train.distill_from else {})
        | (
            {"bandai_namco": True, "licence": BANDAI_LICENCE}
            if run.data.tags.get("trains_on_bandai_namco") == "true"
            else {}
        ),
        mlflow=mlflow_info,
        exporter={
            "torch": torch.__version__,
            "onnx": onnx.__version__,
            "opset": OPSET,
            "exporter": "torchscript",
            # our additions inside the graph (README "Method"); absent keys mean false in older manifests
            "canonical_frame": cfg.train.canonical_frame,
            "quarter_turns": cfg.train.quarter_turns,
            "gravity_turns": cfg.train.gravity_turns,
            # segment-frame definition of the training labels: 1 geometric, 2 functional (README "Method")
            "kinematics_version": int(run.data.tags.get("kinematics_version", "1")),
        }
        # the classes that take the average over turns about gravity; absent: all of them
        | ({"gravity_turn_segments": cfg.train.gravity_turn_segments} if cfg.train.gravity_turn_segments else {})
        | ({"functional_axes": cfg.train.functional_axes} if cfg.train.functional_axes else {})
        | ({"pelvis_half_turn": cfg.train.pelvis_half_turn} if cfg.train.pelvis_half_turn is not None else {})
        | ({"rnn_stride": cfg.train.rnn_stride} if cfg.train.rnn_stride != 1 else {})
        | (_ensemble(cfg.train.ensemble_of) if cfg.train.ensemble_of else {}),
        parity_atol=PARITY_ATOL,
    )


def _teacher(cfg: ExperimentConfig) -> dict[str, dict]:
    """What a distilled network's manifest records of its teacher (``train.distill_from``): which shipped file taught
    it, on which activities' windows (all: null), and how."""
    t = cfg.train
    assert t.distill_from is not None
    teacher = read_manifest(Path(t.distill_from) / "manifest.json")
    return {
        "distilled_from": {
            "model": f"{teacher.name}/{teacher.version}",
            "sha256": teacher.sha256,
            "activities": t.distill_activities,
            "weight": t.distill_weight,
        }
        # the softening of the class distributions: an alignment teacher's quaternions have none
        | ({"temperature": t.distill_temperature} if cfg.task == "assignment" else {})
    }


def _ensemble(member_dirs: list[str]) -> dict[str, list[str]]:
    """What an ensemble's manifest records of its members: where each ships, its file and its MLflow run (each
    member's own manifest gives its turn averages)."""
    manifests = [read_manifest(Path(d) / "manifest.json") for d in member_dirs]
    return {
        "ensemble_of": [f"{m.name}/{m.version}" for m in manifests],
        "ensemble_sha256": [m.sha256 for m in manifests],
        "ensemble_run_ids": [str(m.mlflow.get("run_id")) for m in manifests],
    }


def export_run(run_id: str, out_root: Path, version: str | None = None) -> Path:
    """Write ``out_root/<name>/<version>/{model.onnx, manifest.json, golden.npz}`` from an MLflow run (``write_run``)
    and record on the run that it shipped as that version."""
    target = write_run(run_id, out_root, version)
    record_shipped(MlflowClient(), run_id, target.parent.name, target.name)
    return target


def write_run(run_id: str, out_root: Path, version: str | None = None) -> Path:
    """``out_root/<name>/<version>/{model.onnx, manifest.json, golden.npz}`` of an MLflow run's model (its parity
    with the golden output logged); ``name`` is the config's registered model (``tracking.registered_model``, by default
    the config's name). Nothing is recorded on the run (a benchmark's copy of a fold model is not a release)."""
    run = MlflowClient().get_run(run_id)
    cfg = ExperimentConfig.model_validate(load_run_config(run_id))
    version = version or run_version(run)
    target = out_root / cfg.registered_model / version
    target.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        # One self-contained file, also for models MLflow stored with external weight data.
        onnx.save_model(
            onnx.load(str(download_onnx(run.data.tags["model_uri"], tmp))),
            str(target / "model.onnx"),
            save_as_external_data=False,
        )
        golden = Path(mlflow.artifacts.download_artifacts(f"runs:/{run_id}/export/golden.npz", dst_path=tmp))
        shutil.copy(golden, target / "golden.npz")
    with np.load(target / "golden.npz") as z:
        parity = onnx_parity(target / "model.onnx", dict(z))
    manifest = build_manifest(cfg, run, sha256_file(target / "model.onnx"), version)
    if "quantized_from" in run.data.tags:  # an int8 copy of a fold (training.i2s.quantize): its parity as measured
        manifest.exporter = {**manifest.exporter, "quantization": run.data.params.get("quantization", "int8")}
        manifest.parity_atol = float(np.ceil(parity * 1000) / 1000)
    write_manifest(manifest, target / "manifest.json")
    log.info("wrote %s %s (parity %.2e) to %s", cfg.registered_model, version, parity, target)
    return target


def _inputs(run: mlflow.entities.Run) -> list:
    return list(run.inputs.dataset_inputs) if run.inputs else []


def _context(dataset_input: mlflow.entities.DatasetInput) -> str:
    return next((t.value for t in dataset_input.tags if t.key == "mlflow.data.context"), "")


def load_run_config(run_id: str) -> dict:
    import yaml

    return yaml.safe_load(mlflow.artifacts.load_text(f"runs:/{run_id}/config.yaml"))


def evaluate_shipped(
    model_dir: Path, data_dir: Path, cache_dir: Path, command: str, max_windows: int | None = None
) -> Manifest:
    """Evaluate the shipped ONNX file (LOSO simulated fold and, for assignment, real recordings)."""
    from training.i2s.data.split import load_clips, split_clips
    from training.i2s.pipeline import PRIMARY_METRIC, held_out_recordings

    manifest = read_manifest(model_dir / "manifest.json")
    run_id = local_run_id(manifest.mlflow["run_id"])  # the manifest keeps the id of the store it was trained in
    cfg = ExperimentConfig.model_validate(load_run_config(run_id))
    predict = onnx_predictor(model_dir / "model.onnx")
    evaluations = []
    clips = load_clips(cfg, data_dir, cache_dir)
    _, _, test = split_clips(clips, cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed)
    sim = evaluate_simulated(predict, cfg.task, test, cfg.augmentation, max_windows)
    evaluations.append(
        Evaluation(
            name="loso_simulated",
            command=command,
            data=f"simulated, eq. 8 grid (64 alignments) x 7 segments, every window of "
            f"held-out subjects {cfg.data.test_subjects}; digest {sim.digest}",
            metrics=_headline(sim.metrics),
        )
    )
    # Each shipped file of a run (float32, int8) logs under its own prefix.
    prefix = "shipped_int8_" if "quantization" in manifest.exporter else "shipped_"
    if "quantization" not in manifest.exporter:  # the registered model is the float32 one
        metric, _ = PRIMARY_METRIC[cfg.task]
        record_evaluation(cfg.registered_model, run_id, metric, sim.metrics[metric], sim.digest)
    metrics_to_log = {f"{prefix}sim_{k}": v for k, v in sim.metrics.items()}
    if cfg.task == "assignment":
        if braced := braced_knee_clips(cfg, test, data_dir, cache_dir):
            knees = evaluate_braced_knees(predict, braced, cfg.augmentation, max_windows)
            scored = [f"recall_{SEGMENTS[k]}" for k in np.unique(knees.segment)]  # the braced shanks and feet
            shown = ["accuracy", "accuracy_ignoring_side", "n_windows", *scored]
            evaluations.append(
                Evaluation(
                    name="loso_simulated_braced_knee",
                    command=command,
                    data=f"simulated, held-out subjects {cfg.data.test_subjects}: each walking clip with the left "
                    f"and with the right knee braced (flexion kept uniform in [0, {BRACED_KEEP_MAX}]); the braced "
                    f"leg's shank and foot, eq. 8 grid (64 alignments), every window; digest {knees.digest}",
                    metrics=_headline({k: knees.metrics[k] for k in shown}),
                )
            )
            metrics_to_log.update({f"{prefix}braced_knee_{k}": v for k, v in knees.metrics.items()})
        held_out = held_out_recordings(cfg, data_dir)
        if not held_out:  # trained on every real person: the real figures are its recipe's folds (loso_run)
            _log_to_run(run_id, metrics_to_log, None)
        else:
            real_metrics, cm = evaluate_real(predict, held_out)
            evaluations.append(
                Evaluation(
                    name="real_recordings",
                    command=command,
                    data=f"imu_real recordings not used for training: "
                    f"{', '.join(r.name for r in held_out)}; still windows skipped; real_accuracy: each window on "
                    "its own, real_window_joint_*: one-to-one over the recording's windows at the same moment",
                    metrics=real_metrics,
                )
            )
            metrics_to_log.update({f"{prefix}{k.replace('/', '.')}": v for k, v in real_metrics.items()})
            with tempfile.TemporaryDirectory() as tmp:
                png = confusion_matrix_png(
                    cm, Path(tmp) / f"confusion_real_{manifest.version}.png", f"{cfg.name}: real recordings"
                )
                _log_to_run(run_id, metrics_to_log, png)
    else:
        real_metrics = evaluate_real_alignment(predict, held_out_recordings(cfg, data_dir))
        evaluations.append(
            Evaluation(
                name="real_recordings_label_free",
                command=command,
                data="imu_real recordings (no I2S ground truth): per sensor, spread of the predicted alignment over "
                "its moving windows, and for the legs the angle of the rotated mean specific force from segment +z "
                "(training.i2s.evaluate.evaluate_real_alignment)",
                metrics=_headline(real_metrics),
            )
        )
        metrics_to_log.update({f"{prefix}{k.replace('/', '.')}": v for k, v in real_metrics.items()})
        _log_to_run(run_id, metrics_to_log, None)
    manifest.evaluations = evaluations + [e for e in manifest.evaluations if e.name == REAL_LOSO]
    write_manifest(manifest, model_dir / "manifest.json")
    return manifest


REAL_LOSO = "real_leave_one_person_out"


def record_real_loso(model_dir: Path, summary_run_id: str, command: str) -> Manifest:
    """Copy a ``real-loso`` summary run's held-out figures (per person, per source and pooled) into a shipped
    model's manifest as the evaluation ``real_leave_one_person_out``: the figures of the recipe that made the
    model, each fold trained without the person it is scored on."""
    from training.i2s.pipeline import HELD_OUT_METRICS

    summary = mlflow.get_run(local_run_id(summary_run_id))  # the id a manifest names may be restored
    if summary.data.tags.get("real_loso") != "summary":
        raise ValueError(f"run {summary_run_id} is not a real-loso summary run")
    folds = json.loads(mlflow.artifacts.load_text(f"runs:/{summary.info.run_id}/evaluation/real_loso.json"))
    metrics = {}
    for name, fold in folds.items():
        for key in (*HELD_OUT_METRICS, "n_windows"):
            if key in fold:  # a run from before a metric was added has none of it
                metrics[f"{key}/{name}"] = round(float(fold[key]), 5)
    manifest = read_manifest(model_dir / "manifest.json")
    evaluation = Evaluation(
        name=REAL_LOSO,
        command=command,
        data=f"real recordings, leave one person out: real-loso summary run {summary_run_id}, "
        f"{sum(1 for n in folds if not n.startswith('pooled'))} people, each fold fine-tuned by the same recipe "
        "without the person it is scored on"
        + (
            f" and quantised as this file is (from real-loso run {summary.data.tags['quantized_from']})"
            if "quantized_from" in summary.data.tags
            else ""
        )
        + "; moving windows; per window and one-to-one per moment",
        metrics=metrics,
    )
    manifest.evaluations = [e for e in manifest.evaluations if e.name != REAL_LOSO] + [evaluation]
    write_manifest(manifest, model_dir / "manifest.json")
    return manifest


# The braced-knee evaluation does not depend on how (or whether) a model was trained on braced knees.
BRACED_KEEP_MAX = 0.4


def braced_knee_clips(cfg: ExperimentConfig, test: list[Clip], data_dir: Path, cache_dir: Path) -> list[Clip]:
    """Stiff-knee variants of the held-out walking clips, the same for every model (``EVAL_SEED``)."""
    if not any(c.entry.activity == "walk" for c in test):
        return []
    params = KinematicsParams(cfg.data.sample_rate_hz, cfg.data.cutoff_hz, cfg.data.filter_order)
    return stiff_knee_variants(data_dir, test, cache_dir, BRACED_KEEP_MAX, EVAL_SEED, params)


def _headline(metrics: dict[str, float]) -> dict[str, float]:
    return {k: round(v, 5) for k, v in metrics.items()}


def _log_to_run(run_id: str, metrics: dict[str, float], png: Path | None) -> None:
    with mlflow.start_run(run_id=run_id):
        mlflow.log_metrics(metrics)
        if png is not None:
            mlflow.log_artifact(str(png), "plots")


def real_table(summary_run_id: str, model_dirs: list[Path], data_dir: Path) -> str:
    """A markdown table: per person, per source and pooled, the held-out figures of a ``real-loso`` summary run
    (per window / one-to-one per moment, moving windows) beside the same figures of shipped models that never
    trained on those recordings (their manifests' ``real_recordings`` evaluation, weighted by window count)."""
    from service.core.recordings import read_all_real

    rid = local_run_id(summary_run_id)
    folds = json.loads(mlflow.artifacts.load_text(f"runs:/{rid}/evaluation/real_loso.json"))
    person_of = {r.name: (r.subject, r.source) for r in read_all_real(data_dir)}
    columns = []
    for model_dir in model_dirs:
        manifest = read_manifest(model_dir / "manifest.json")
        real = next((e.metrics for e in manifest.evaluations if e.name == "real_recordings"), {})
        sums: dict[str, list[float]] = {}
        for rec, (person, source) in person_of.items():
            n = real.get(f"n_windows/{rec}")
            if n is None:
                continue
            for group in (person, f"pooled/{source}", "pooled"):
                acc = sums.setdefault(group, [0.0, 0.0, 0.0])
                acc[0] += n
                acc[1] += n * real[f"accuracy/{rec}"]
                acc[2] += n * real[f"window_joint_accuracy/{rec}"]
        columns.append((f"{manifest.name} {manifest.version}", sums))
    swing = all("real_window_joint_swing_accuracy" in fold for fold in folds.values())  # runs since 2026-12-04
    head = "| held out (moving windows) | leave-one-person-out fold: per window / per moment"
    head += " / per moment, swinging together |" if swing else " |"
    head += "".join(f" {name}: per window / per moment |" for name, _ in columns)
    lines = [head, "|" + " --- |" * (2 + len(columns))]
    for group, fold in folds.items():
        row = f"| {group} ({int(fold['n_windows'])}) | {100 * fold['real_accuracy']:.1f} / "
        row += f"{100 * fold['real_window_joint_accuracy']:.1f}"
        row += f" / {100 * fold['real_window_joint_swing_accuracy']:.1f} % |" if swing else " % |"
        for _, sums in columns:
            n, own, joint = sums.get(group, [0.0, 0.0, 0.0])
            row += f" {100 * own / n:.1f} / {100 * joint / n:.1f} % |" if n else " — |"
        lines.append(row)
    return "\n".join(lines)


def real_confusion(summary_run_id: str, data_dir: Path) -> str:
    """What each held-out person's sensors are taken for: per person and pooled, the confusion of a ``real-loso``
    run's folds on moving windows, each window's own answer (``training.i2s.calibration.fold_predictions``). One
    confusion matrix image per person is logged with the summary run (``plots/real_confusion/<person>.png``); the
    markdown table returned gives each segment's share right and the segment it is most often taken for."""
    from training.i2s.calibration import fold_predictions

    matrices = held_out_confusions(fold_predictions(summary_run_id, data_dir))
    with tempfile.TemporaryDirectory() as tmp:
        for group, cm in matrices.items():
            name = re.sub(r"[^\w.-]", "_", group)  # a person as index.csv names them, as a file name
            confusion_matrix_png(cm, Path(tmp) / f"{name}.png", f"held out {group}, moving windows")
        MlflowClient().log_artifacts(local_run_id(summary_run_id), tmp, "plots/real_confusion")
    return confusion_table(matrices)


def held_out_confusions(held_out: list) -> dict[str, np.ndarray]:
    """Per person of ``held_out`` (``HeldOut`` recordings), then ``pooled`` over them all: counts of moving windows,
    rows the sensor's segment, columns each window's own answer."""
    matrices: dict[str, np.ndarray] = {}
    pooled = np.zeros((len(SEGMENTS), len(SEGMENTS)), np.int64)
    for held in held_out:
        person = matrices.setdefault(held.person, np.zeros_like(pooled))
        for sensor in held.sensors:
            answers = sensor.log_probs[sensor.moving].argmax(axis=1)
            cm = confusion_matrix(np.full(len(answers), sensor.segment), answers)
            person += cm
            pooled += cm
    if "pooled" in matrices:
        raise ValueError("a held-out person is named 'pooled', the name of the total over everyone")
    return matrices | {"pooled": pooled}


def confusion_table(matrices: dict[str, np.ndarray]) -> str:
    """A markdown row per person and segment worn: its moving windows, the share right, and the segment it is most
    often taken for (with how many windows)."""
    lines = ["| held out | segment (moving windows) | right | most often taken for |", "| --- | --- | --- | --- |"]
    for group in sorted(matrices, key=lambda g: (g == "pooled", g)):
        cm = matrices[group]
        if not cm.sum():
            lines.append(f"| {group} | no moving window | — | — |")
        for segment in np.flatnonzero(cm.sum(axis=1)):
            row = cm[segment]
            wrong = row.copy()
            wrong[segment] = 0
            other = int(wrong.argmax())
            taken = f"{SEGMENTS[other]} ({wrong[other]})" if wrong[other] else "—"
            share = 100 * row[segment] / row.sum()
            lines.append(f"| {group} | {SEGMENTS[segment]} ({row.sum()}) | {share:.1f} % | {taken} |")
    return "\n".join(lines)
