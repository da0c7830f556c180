"""The training job, step by step: clips → split → train → export ONNX → evaluate → MLflow → registry."""

from __future__ import annotations

import hashlib
import logging
import tempfile
import time
from pathlib import Path

import mlflow
import numpy as np
import onnx
import pandas as pd
import torch
import yaml
from mlflow.tracking import MlflowClient

from service.core.recordings import RealRecording, read_all_real, read_recording
from training.config import flatten
from training.data.catalog import is_bandai_namco
from training.i2s.config import ExperimentConfig
from training.i2s.data.mocap import KINEMATICS_VERSION, Clip, as_recorded, dataset_digest
from training.i2s.data.split import load_clips, recordings_digest, split_clips
from training.i2s.data.windows import Augmentation, RealWindowSampler, WindowSampler, real_window_samplers
from training.i2s.evaluate import evaluate_real, evaluate_real_alignment, evaluate_simulated, onnx_predictor
from training.i2s.export import PARITY_ATOL, export_onnx, golden_pair, onnx_parity
from training.i2s.ship import build_manifest, run_version
from training.i2s.train import TrainResult, build_model, load_fitted, train
from training.i2s.warmstart import check_real_recordings_declared, ensemble_state, warm_start_from_shipped
from training.plots import confusion_matrix_png, error_boxplot_png, held_out_bars_png, learning_curves_png
from training.run_labels import SHIPPED_TAG, label_run, label_version
from training.tracking import log_onnx_model, maybe_promote, register_model, setup_tracking

log = logging.getLogger(__name__)

PRIMARY_METRIC = {"assignment": ("accuracy", True), "alignment": ("mean_angle_error_deg", False)}


def clip_table(clips: list[Clip]) -> pd.DataFrame:
    return pd.DataFrame(
        [
            {
                "path": c.entry.path,
                "source": c.entry.source,
                "subject": c.entry.group,
                "activity": c.entry.activity,
                "samples_60hz": c.n_samples,
                "digest": c.digest,
                "variant": c.variant,
            }
            for c in clips
        ]
    )


def _log_dataset(clips: list[Clip], data_dir: Path, context: str) -> None:
    ds = mlflow.data.from_pandas(clip_table(clips), source=str(data_dir), name=f"{context}-{dataset_digest(clips)}")
    try:
        mlflow.log_input(ds, context=context)
    except mlflow.exceptions.MlflowException:
        # Two runs inserting the same new dataset at once race on the sqlite UNIQUE constraint;
        # the second attempt finds the dataset the other run stored.
        time.sleep(1.0)
        mlflow.log_input(ds, context=context)


def run_training(
    cfg: ExperimentConfig,
    data_dir: Path,
    cache_dir: Path,
    register: bool = True,
    eval_max_windows: int | None = None,
    fitted: Path | None = None,
    tags: dict[str, str] | None = None,
) -> str:
    """One tracked training run; returns the MLflow run id.

    With ``fitted`` (a ``training.cli fit`` output) the training itself happened elsewhere, on the same clips
    and config (checked): its per-epoch history is logged as this run's, with tags saying where it ran.
    """
    setup_tracking(cfg.tracking.experiment)
    clips = load_clips(cfg, data_dir, cache_dir)
    train_clips, val_clips, test_clips = split_clips(clips, cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed)
    with mlflow.start_run(run_name=cfg.name) as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.log_params({k: str(v) for k, v in flatten(cfg.model_dump()).items()})
        mlflow.log_text(yaml.safe_dump(cfg.model_dump(), sort_keys=False), "config.yaml")
        mlflow.set_tags(
            {
                "task": cfg.task,
                "test_subjects": ",".join(cfg.data.test_subjects),
                "kinematics_version": KINEMATICS_VERSION,
                # the manifest states Bandai-Namco's licence when the clips include its sets
                "trains_on_bandai_namco": str(any(is_bandai_namco(c.entry.source) for c in clips)).lower(),
            }
            | (tags or {})
        )
        for context, part in (("training", train_clips), ("validation", val_clips), ("test", test_clips)):
            if part:
                _log_dataset(part, data_dir, context)
        real_recordings = [read_recording(data_dir, name) for name in cfg.data.real_train_recordings]
        real, real_val = _real_samplers(cfg, real_recordings)
        if fitted is not None:
            result = _fitted_elsewhere(fitted, cfg, train_clips, val_clips, real_recordings)
        else:
            result = train(
                cfg,
                train_clips,
                val_clips,
                log_metrics=lambda m, step: mlflow.log_metrics(m, step=step),
                init_state=_initial_state(cfg, tmp),
                real=real,
                real_val=real_val,
            )
        label_run(MlflowClient(), run.info.run_id)  # its name and description in the UI
        torch.save(result.model.state_dict(), tmp / "model_state.pt")
        mlflow.log_artifact(str(tmp / "model_state.pt"), "checkpoint")
        mlflow.log_metrics({"best_epoch": result.best_epoch, "train_wall_time_s": result.wall_time_s})
        mlflow.log_artifact(str(learning_curves_png(result.history, tmp / "learning_curves.png", cfg.name)), "plots")
        onnx_path = export_onnx(result.model, cfg.task, tmp / "model.onnx")
        golden_imu = WindowSampler(as_recorded(val_clips), Augmentation()).sample(np.random.default_rng(123), 8).imu
        golden = golden_pair(result.model, golden_imu)
        np.savez(tmp / "golden.npz", **golden)
        parity = onnx_parity(onnx_path, golden)
        if parity > PARITY_ATOL:
            raise RuntimeError(f"onnxruntime differs from torch by {parity:.2e} > {PARITY_ATOL:.0e}")
        mlflow.log_metric("onnx_parity_max_abs", parity)
        mlflow.log_artifact(str(tmp / "golden.npz"), "export")
        if test_clips:
            _log_simulated_evaluation(cfg, onnx_path, test_clips, tmp, eval_max_windows)
        log_real_evaluation(cfg, onnx_path, data_dir, tmp)
        proto = onnx.load(str(onnx_path))
        # mlflow.onnx writes the proto's serialisation, whose sha256 the manifest states.
        current = MlflowClient().get_run(run.info.run_id)
        digest = hashlib.sha256(proto.SerializeToString()).hexdigest()
        manifest = build_manifest(cfg, current, digest, run_version(current))
        info = log_onnx_model(proto, golden, manifest)
        mlflow.set_tag("model_uri", info.model_uri)
        run_id = run.info.run_id
    if register:
        register_run(run_id, cfg.registered_model, cfg.task)
    return run_id


# What a real-data fold reports of its held-out windows, pooled over folds by window count.
HELD_OUT_METRICS = (
    "real_accuracy",
    "real_accuracy_ignoring_side",
    "real_window_joint_accuracy",
    "real_window_joint_accuracy_ignoring_side",
    "real_window_joint_swing_accuracy",
    "real_window_joint_swing_accuracy_ignoring_side",
)


def run_real_loso(
    cfg: ExperimentConfig,
    data_dir: Path,
    cache_dir: Path,
    eval_max_windows: int | None = None,
    people: list[str] | None = None,
) -> tuple[str, dict[str, dict[str, float]]]:
    """Zimmermann et al. 2018 §4.3 on the real recordings: leave one person out. A person is a ``RealRecording.subject``
    (the capacitive subject, the x-IMU3 person, each of gaitmap's walkers, each MovingReality participant), so every
    fold is scored on a person no real training window came from. Each fold is a full tracked run of ``cfg`` (simulated
    data plus every other person's recordings, ``data.real_fraction`` of each batch), tagged ``real_loso_held_out``; a
    summary run pools the held-out windows (``pooled_*``, weighted by window count; and per source,
    ``<source>.pooled_*``) and logs the per-person bars. ``people`` runs those folds only (each still trains on everyone
    else). The summary run keeps every fold's predictions of its held-out person's windows, which the confidence
    calibration reads (``training.i2s.calibration.fold_predictions``). Returns the summary run id and the
    per-person figures (keys ``pooled`` and ``pooled/<source>``)."""
    if cfg.task != "assignment" or cfg.data.real_fraction <= 0.0:
        raise ValueError(
            f"real-data folds train assignment with data.real_fraction > 0; got task {cfg.task}, "
            f"real_fraction {cfg.data.real_fraction}"
        )
    persons: dict[str, list[RealRecording]] = {}
    for recording in read_all_real(data_dir):
        persons.setdefault(recording.subject, []).append(recording)
    if unknown := sorted(set(people or []) - set(persons)):
        raise ValueError(f"no real recordings of {unknown}; the people are {sorted(persons)}")
    folds: dict[str, dict[str, float]] = {}
    source_of: dict[str, str] = {}
    chosen = [p for p in persons if people is None or p in people]
    for held_out in chosen:
        others = [r.name for person, group in persons.items() if person != held_out for r in group]
        fold_cfg = ExperimentConfig.model_validate(
            cfg.model_dump() | {"data": cfg.data.model_dump() | {"real_train_recordings": others}}
        )
        log.info("real-data fold %d/%d: %s held out", len(folds) + 1, len(chosen), held_out)
        run_id = _finished_fold(fold_cfg, held_out) or run_training(
            fold_cfg, data_dir, cache_dir, False, eval_max_windows, tags={"real_loso_held_out": held_out}
        )
        folds[held_out] = fold_figures(run_id, persons[held_out])
        source_of[held_out] = persons[held_out][0].source
    return log_real_loso_summary(cfg, folds, source_of, data_dir, f"{cfg.name}_real_loso")


def fold_figures(run_id: str, recordings: list[RealRecording]) -> dict[str, float]:
    """A fold run's figures on its held-out person's ``recordings`` (``HELD_OUT_METRICS``, window count, run id)."""
    metrics = MlflowClient().get_run(run_id).data.metrics
    n_windows = sum(metrics.get(f"n_windows.{r.name.replace('/', '.')}", 0.0) for r in recordings)
    return {"n_windows": n_windows} | {k: metrics[k] for k in HELD_OUT_METRICS} | {"run_id": run_id}  # type: ignore[dict-item]


def log_real_loso_summary(
    cfg: ExperimentConfig,
    folds: dict[str, dict[str, float]],
    source_of: dict[str, str],
    data_dir: Path,
    run_name: str,
    tags: dict[str, str] | None = None,
) -> tuple[str, dict[str, dict[str, float]]]:
    """The summary run of leave-one-person-out folds (``fold_figures`` per person, each person's source): pooled and
    per-source figures, the per-person bars, and every fold's held-out predictions (``fold_predictions``)."""
    pooled = {"pooled": _pooled(list(folds.values()))}
    for source in dict.fromkeys(source_of.values()):
        pooled[f"pooled/{source}"] = _pooled([f for p, f in folds.items() if source_of[p] == source])
    with mlflow.start_run(run_name=run_name) as run, tempfile.TemporaryDirectory() as tmp_dir:
        mlflow.log_params(
            {k: str(v) for k, v in flatten(cfg.model_dump()).items() if k != "data.real_train_recordings"}
        )
        mlflow.set_tags(
            {"task": cfg.task, "real_loso": "summary"}
            | {f"fold_run.{p}": str(f["run_id"]) for p, f in folds.items()}
            | (tags or {})
        )
        for name, figures in pooled.items():
            prefix = "" if name == "pooled" else f"{name.removeprefix('pooled/')}."
            mlflow.log_metrics({f"{prefix}pooled_{k}": v for k, v in figures.items()})
        for person, fold in folds.items():
            mlflow.log_metrics({f"{person}.{k}": fold[k] for k in (*HELD_OUT_METRICS, "n_windows")})
        mlflow.log_dict(folds | pooled, "evaluation/real_loso.json")
        png = held_out_bars_png(
            folds, Path(tmp_dir) / "real_loso.png", f"{run_name}: real recordings, one person held out"
        )
        mlflow.log_artifact(str(png), "plots")
        summary_id = run.info.run_id
    label_run(MlflowClient(), summary_id)  # its name and description in the UI
    from training.i2s.calibration import fold_predictions

    fold_predictions(summary_id, data_dir)  # each fold's held-out predictions, kept with the summary run
    return summary_id, folds | pooled


def _finished_fold(fold_cfg: ExperimentConfig, held_out: str) -> str | None:
    """A finished fold run of the same configuration (every logged parameter equal) holding out the same person:
    a long leave-one-person-out job that stopped goes on where it stopped instead of training again."""
    setup_tracking(fold_cfg.tracking.experiment)
    expected = {k: str(v) for k, v in flatten(fold_cfg.model_dump()).items()}
    runs = MlflowClient().search_runs(
        [mlflow.get_experiment_by_name(fold_cfg.tracking.experiment).experiment_id],
        f"tags.real_loso_held_out = '{held_out}' and attributes.status = 'FINISHED'",
        order_by=["attributes.start_time DESC"],
    )
    for run in runs:
        if "quantized_from" in run.data.tags:  # an int8 copy of a fold (training.i2s.quantize), not one trained
            continue
        if all(run.data.params.get(k) == v for k, v in expected.items()) and "model_uri" in run.data.tags:
            log.info("fold %s: reusing finished run %s", held_out, run.info.run_id)
            return run.info.run_id
    return None


def _pooled(folds: list[dict[str, float]]) -> dict[str, float]:
    """Held-out figures of several folds, weighted by their window counts."""
    total = sum(f["n_windows"] for f in folds)
    return {k: sum(f[k] * f["n_windows"] for f in folds) / total for k in HELD_OUT_METRICS} | {"n_windows": total}


def _fitted_elsewhere(
    fitted: Path, cfg: ExperimentConfig, train_clips: list[Clip], val_clips: list[Clip], real: list[RealRecording]
) -> TrainResult:
    digests = dataset_digest(train_clips), dataset_digest(val_clips), recordings_digest(real)
    result, where = load_fitted(fitted, cfg, *digests)
    if result.warm_start is not None:  # step 0 of the learning curves, as in a run trained here
        mlflow.log_metrics(result.warm_start, step=0)
    for epoch, metrics in enumerate(result.history, start=1):
        mlflow.log_metrics(metrics, step=epoch)
    mlflow.set_tags(
        {
            "fitted_elsewhere": fitted.name,
            "fitted_device": str(where["device"]),
            "fitted_loader_workers": str(where["loader_workers"]),
        }
    )
    return result


def _initial_state(cfg: ExperimentConfig, tmp: Path) -> dict | None:
    if cfg.train.ensemble_of:
        if cfg.task != "assignment":
            raise ValueError("ensemble_of assembles assignment models")
        check_real_recordings_declared(cfg.train.ensemble_of, cfg.data.real_train_recordings, "ensemble member")
        mlflow.set_tag("ensemble_of", ",".join(cfg.train.ensemble_of))
        return ensemble_state(cfg.train.ensemble_of, build_model(cfg))  # type: ignore[arg-type]
    if cfg.train.init_from_run:
        return _checkpoint(cfg.train.init_from_run, tmp)
    if cfg.train.init_from_onnx:
        mlflow.set_tag("init_from_onnx", cfg.train.init_from_onnx)
        return warm_start_from_shipped(Path(cfg.train.init_from_onnx), build_model(cfg))  # type: ignore[arg-type]
    return None


def _checkpoint(run_id: str, tmp: Path) -> dict:
    """The torch state dict logged by an earlier run (pre-training)."""
    path = mlflow.artifacts.download_artifacts(f"runs:/{run_id}/checkpoint/model_state.pt", dst_path=str(tmp))
    mlflow.set_tag("init_from_run", run_id)
    return torch.load(path, weights_only=True)


def _real_samplers(
    cfg: ExperimentConfig, recordings: list[RealRecording]
) -> tuple[RealWindowSampler | None, RealWindowSampler | None]:
    """``real_window_samplers`` of the real training recordings, with their window counts logged as params;
    (None, None) without real data."""
    real, real_val = real_window_samplers(cfg, recordings)
    if real is not None:
        mlflow.log_param("real_train_windows", len(real.segment))
    if real_val is not None:
        mlflow.log_param("real_val_windows", len(real_val.segment))
    return real, real_val


def _log_simulated_evaluation(
    cfg: ExperimentConfig, onnx_path: Path, test_clips: list[Clip], tmp: Path, max_windows: int | None
) -> None:
    ev = evaluate_simulated(onnx_predictor(onnx_path), cfg.task, test_clips, cfg.augmentation, max_windows)
    mlflow.log_metrics({f"test_{k}": v for k, v in ev.metrics.items()})
    mlflow.set_tag("eval_digest", ev.digest)
    title = f"{cfg.name}: LOSO test {','.join(cfg.data.test_subjects)} (simulated)"
    if ev.confusion is not None:
        mlflow.log_artifact(str(confusion_matrix_png(ev.confusion, tmp / "confusion_test.png", title)), "plots")
    else:
        mlflow.log_artifact(
            str(error_boxplot_png(ev.segment, ev.predicted, tmp / "angle_errors_test.png", title)), "plots"
        )
    mlflow.log_dict(ev.metrics, "evaluation/test_simulated.json")


def held_out_recordings(cfg: ExperimentConfig, data_dir: Path) -> list[RealRecording]:
    """Real recordings with known placement that this configuration did not train on."""
    if cfg.data.real_eval_recordings is not None:  # never one it trains on (DataConfig checks)
        return [read_recording(data_dir, name) for name in cfg.data.real_eval_recordings]
    return [r for r in read_all_real(data_dir) if r.name not in cfg.data.real_train_recordings]


def log_real_evaluation(cfg: ExperimentConfig, onnx_path: Path, data_dir: Path, tmp: Path) -> None:
    """Score a model file on the real recordings its configuration did not train on and log it to the active run."""
    predict, recordings = onnx_predictor(onnx_path), held_out_recordings(cfg, data_dir)
    if not recordings:  # trained on every real person: their held-out figures are real-loso's
        log.info("no real recording held out of training: no real-data evaluation in this run")
        return
    if cfg.task == "alignment":
        metrics = evaluate_real_alignment(predict, recordings)
    else:
        metrics, cm = evaluate_real(predict, recordings)
        png = confusion_matrix_png(cm, tmp / "confusion_real.png", f"{cfg.name}: real recordings (moving windows)")
        mlflow.log_artifact(str(png), "plots")
    mlflow.log_metrics({k.replace("/", "."): v for k, v in metrics.items()})
    mlflow.log_dict(metrics, "evaluation/real_recordings.json")


def register_run(run_id: str, name: str, task: str) -> tuple[str, bool]:
    """Register a run's model; move ``champion`` if it beats the champion on the same evaluation."""
    client = MlflowClient()
    run = client.get_run(run_id)
    version = register_model(run.data.tags.get("model_uri", f"runs:/{run_id}/model"), name).version
    # a run registered after it shipped: its version says which shipped files it is, as one registered before does
    label_version(client, name, str(version), [v for v in run.data.tags.get(SHIPPED_TAG, "").split(", ") if v])
    metric, higher = PRIMARY_METRIC[task]
    value = run.data.metrics.get(f"test_{metric}")
    promoted = False
    if value is not None:
        promoted = maybe_promote(name, str(version), metric, value, higher, run.data.tags.get("eval_digest", ""))
    log.info("registered %s version %s (%s)", name, version, "champion" if promoted else "not promoted")
    return str(version), promoted
