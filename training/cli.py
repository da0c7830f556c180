"""``wearmocap-train``: thin typer commands over the training library (I2S: simulate, train, register, export,
evaluate; pose: pose-train, evaluate-pose, pose-placement, pose-rig-hinges, pose-rig-pairs,
pose-translation-design, pose-velocity-train; flex: flex-train, evaluate-flex, capacitive-train,
evaluate-capacitive; snapshot-export / snapshot-restore, ui).
Run ``python -m training.cli --help``.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import typer

from training.data.catalog import resolve_data_dir
from training.i2s.config import load_config

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)
DEFAULT_CACHE = Path(".cache/kinematics")

DataDir = typer.Option(None, "--data-dir", help="folder with index.csv (default: $WEARMOCAP_DATA_DIR)")
Override = typer.Option([], "--set", "-s", help="config override, e.g. -s train.max_epochs=2")


@app.callback()
def _logging(verbose: bool = typer.Option(False, "--verbose", "-v")) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )


@app.command()
def simulate(
    config: Path, data_dir: Path | None = DataDir, cache_dir: Path = DEFAULT_CACHE, overrides: list[str] = Override
) -> None:
    """Compute (or reuse from the digest cache) the segment kinematics the simulation draws from."""
    from training.i2s.data.split import load_clips

    cfg = load_config(config, overrides)
    clips = load_clips(cfg, resolve_data_dir(data_dir), cache_dir)
    typer.echo(f"{len(clips)} clips, {sum(c.n_samples for c in clips)} samples at {cfg.data.sample_rate_hz} Hz")


@app.command()
def train(
    config: Path,
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
    overrides: list[str] = Override,
    register: bool = typer.Option(True, help="register the model"),
    eval_max_windows: int | None = typer.Option(None, help="cap the test evaluation (quick runs)"),
    fitted: Path | None = typer.Option(None, help="track a training done by `fit` instead of training here"),
) -> None:
    """Train, export ONNX, evaluate on the held-out subjects and log it all to MLflow."""
    from training.i2s.pipeline import run_training

    cfg = load_config(config, overrides)
    run_id = run_training(cfg, resolve_data_dir(data_dir), cache_dir, register, eval_max_windows, fitted)
    typer.echo(f"run_id={run_id}")


@app.command("real-loso")
def real_loso(
    config: Path,
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
    overrides: list[str] = Override,
    eval_max_windows: int | None = typer.Option(None, help="cap each fold's simulated test evaluation"),
    person: list[str] = typer.Option([], "--person", help="run this person's fold only (repeatable; default all)"),
) -> None:
    """Real-data leave-one-person-out (Zimmermann et al. 2018 §4.3): one tracked fine-tune per real person, trained on
    everyone else and scored on that person; a summary run pools the held-out windows."""
    from training.i2s.pipeline import run_real_loso

    cfg = load_config(config, overrides)
    run_id, folds = run_real_loso(cfg, resolve_data_dir(data_dir), cache_dir, eval_max_windows, person or None)
    for name, fold in folds.items():
        shown = {k: round(float(v), 4) for k, v in fold.items() if k != "run_id"}
        typer.echo(f"{name}: {shown}" + (f" (run {fold['run_id']})" if "run_id" in fold else ""))
    typer.echo(f"run_id={run_id}")


@app.command()
def pack(
    config: Path,
    out: Path,
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
    overrides: list[str] = Override,
) -> None:
    """Write a config's clips (segment kinematics, entries, digests) and its real training recordings
    (`data.real_train_recordings`) to one file for `fit` on another machine."""
    from service.core.recordings import read_recording
    from training.i2s.data.split import load_clips, save_pack

    cfg = load_config(config, overrides)
    root = resolve_data_dir(data_dir)
    clips = load_clips(cfg, root, cache_dir)
    recordings = [read_recording(root, name) for name in cfg.data.real_train_recordings]
    save_pack(clips, out, recordings)
    typer.echo(f"{len(clips)} clips, {len(recordings)} real recordings → {out} ({out.stat().st_size / 1e6:.1f} MB)")


@app.command()
def fit(config: Path, clips: Path, out: Path, overrides: list[str] = Override) -> None:
    """Train only (no MLflow, no data directory) on a `pack` file; `train --fitted OUT` then tracks the result.

    From scratch, or fine-tuning a shipped float32 file (`-s train.init_from_onnx=onnx_models/<name>/<version>`),
    on simulated data alone or mixed with the real recordings the pack carries (`data.real_train_recordings`,
    `data.real_fraction`: Zimmermann et al. 2018 §4.3).

    For a GPU machine: `-s train.device=cuda -s train.loader_workers=3` (README "Training on another machine").
    """
    from training.i2s.data.mocap import dataset_digest
    from training.i2s.data.split import load_pack, load_pack_recordings, recordings_digest, split_clips
    from training.i2s.data.windows import real_window_samplers
    from training.i2s.train import save_fitted
    from training.i2s.train import train as train_model

    cfg = load_config(config, overrides)
    if cfg.train.init_from_run or cfg.train.ensemble_of:
        raise typer.BadParameter(
            "fit trains from scratch or from a shipped file (init_from_onnx); no init_from_run, no ensemble_of"
        )
    packed = {r.name: r for r in load_pack_recordings(clips)}
    if missing := sorted(set(cfg.data.real_train_recordings) - set(packed)):
        raise typer.BadParameter(
            f"data.real_train_recordings names {missing}, which {clips} does not carry (it has {sorted(packed)}); "
            "write the pack with this configuration"
        )
    recordings = [packed[name] for name in cfg.data.real_train_recordings]
    real, real_val = real_window_samplers(cfg, recordings)
    init_state = None
    if cfg.train.init_from_onnx:  # the shipped files travel with the working tree; needs onnx, not MLflow
        from training.i2s.train import build_model
        from training.i2s.warmstart import warm_start_from_shipped

        init_state = warm_start_from_shipped(Path(cfg.train.init_from_onnx), build_model(cfg))  # type: ignore[arg-type]
    train_clips, val_clips, _ = split_clips(load_pack(clips), cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed)
    result = train_model(cfg, train_clips, val_clips, init_state=init_state, real=real, real_val=real_val)
    digests = dataset_digest(train_clips), dataset_digest(val_clips), recordings_digest(recordings)
    save_fitted(out, cfg, result, *digests)
    typer.echo(f"best epoch {result.best_epoch} of {len(result.history)}, {result.wall_time_s / 60:.1f} min → {out}")


@app.command()
def register(
    run_id: str,
    name: str,
    task: str = typer.Option(..., help="assignment or alignment"),
    champion_because: str = typer.Option(
        "", help="make this version champion whatever its test score, for the reason given (tagged on it)"
    ),
) -> None:
    """Register a run's model; the champion alias moves only if it wins on the same evaluation, or with
    --champion-because when the served choice was made on other grounds (a validation rule and speed)."""
    import mlflow

    from training.i2s.pipeline import register_run
    from training.tracking import default_tracking_uri, make_champion

    mlflow.set_tracking_uri(default_tracking_uri())
    version, promoted = register_run(run_id, name, task)
    if champion_because and not promoted:
        make_champion(name, version, champion_because)
        promoted = True
    typer.echo(f"version={version} champion={promoted}")


@app.command()
def export(run_id: str, out_root: Path = typer.Option(Path("onnx_models")), version: str | None = None) -> None:
    """Copy an I2S run's ONNX model into onnx_models/<name>/<version>/ with manifest.json and golden.npz."""
    import mlflow
    from mlflow.tracking import MlflowClient

    from training.i2s.ship import export_run
    from training.tracking import default_tracking_uri

    mlflow.set_tracking_uri(default_tracking_uri())
    task = MlflowClient().get_run(run_id).data.tags.get("task", "")
    if task in ("imu_pose", "imu_pose_velocity", "flex_pose"):  # pose and flex runs write their files as they train
        raise typer.BadParameter(
            f"run {run_id} is an {task} run: its files are written when it trains (--ship --version X); its registered "
            "model is served from the registry as it is (WEARMOCAP_REGISTRY_MODELS, docs/service.md)",
            param_hint="RUN_ID",
        )
    typer.echo(str(export_run(run_id, out_root, version)))


@app.command()
def quantize(
    model_dir: Path,
    version: str | None = typer.Option(
        None, help="the version directory to write beside model_dir (without it, --loso-run's folds only)"
    ),
    rnn: bool = typer.Option(False, help="also int8 LSTM weights (dynamic)"),
    calibration_windows: int = typer.Option(1024, help="training windows for the static calibration"),
    calibrate_on: str = typer.Option(
        "simulated", help="simulated: the run's simulated training windows; real: its real training recordings"
    ),
    float_first_conv: bool = typer.Option(False, help="keep the convolutions of the raw sensor channels float32"),
    max_probability_diff: float = typer.Option(
        0.01, help="refuse an assignment file whose golden probabilities move further than this"
    ),
    loso_run: str | None = typer.Option(
        None, help="also quantise this real-loso run's folds alike and write their held-out figures as a new run"
    ),
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
) -> None:
    """Write an int8 variant of a shipped model (static QDQ Conv, optionally int8 LSTM); evaluate it next. With
    --loso-run, the recipe's folds are quantised alike and scored on their held-out people first (without --version,
    only they are: judge them before a file that the service would serve is written)."""
    import mlflow

    from training.i2s.quantize import CALIBRATE_ON, quantize_folds, ship_int8
    from training.tracking import default_tracking_uri

    if calibrate_on not in CALIBRATE_ON:
        raise typer.BadParameter(f"one of {', '.join(CALIBRATE_ON)}; got {calibrate_on!r}", param_hint="--calibrate-on")
    if version is None and loso_run is None:
        raise typer.BadParameter("name the --version to write (or --loso-run to quantise a recipe's folds only)")
    mlflow.set_tracking_uri(default_tracking_uri())
    root = resolve_data_dir(data_dir)
    model_dir = shipped_model(model_dir)
    if loso_run:
        summary = quantize_folds(loso_run, root, cache_dir, calibration_windows, rnn, calibrate_on, float_first_conv)
        typer.echo(f"int8 folds: run_id={summary}  (next: python -m training.cli real-table --loso-run {summary})")
    if version is None:
        return
    target = ship_int8(
        model_dir,
        version,
        root,
        cache_dir,
        calibration_windows,
        rnn,
        calibrate_on,
        float_first_conv,
        max_probability_diff,
    )
    typer.echo(f"{target}  (next: python -m training.cli evaluate {target})")


@app.command()
def evaluate(
    model_dir: Path,
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
    max_windows: int | None = typer.Option(None, help="cap the simulated evaluation (quick checks)"),
    loso_run: str | None = typer.Option(
        None, help="also record this real-loso summary run's held-out figures (the model's recipe, per person)"
    ),
) -> None:
    """Evaluate a shipped model (LOSO fold on simulated data, real recordings) and record it in its manifest."""
    import mlflow

    from service.core.manifest import read_manifest
    from training.i2s.ship import evaluate_shipped, record_real_loso
    from training.tracking import default_tracking_uri

    task = read_manifest(shipped_model(model_dir) / "manifest.json").task
    if task not in ("i2s_assignment", "i2s_alignment"):
        raise typer.BadParameter(
            f"{model_dir} is a {task} model; evaluate scores I2S models (evaluate-pose, evaluate-flex and "
            "evaluate-capacitive score the others)"
        )

    mlflow.set_tracking_uri(default_tracking_uri())
    _restore_into_empty_store()  # a fresh clone: the runs the manifests name
    command = f"python -m training.cli evaluate {model_dir}" + (f" --max-windows {max_windows}" if max_windows else "")
    if loso_run:
        record_real_loso(model_dir, loso_run, f"python -m training.cli evaluate {model_dir} --loso-run {loso_run}")
    manifest = evaluate_shipped(model_dir, resolve_data_dir(data_dir), cache_dir, command, max_windows)
    for ev in manifest.evaluations:
        headline = {
            k: v
            for k, v in ev.metrics.items()
            if "/" not in k and not k.startswith(("precision", "recall", "f1_")) and "_ax" not in k
        }
        typer.echo(f"{ev.name}: {headline}")


@app.command()
def calibrate(
    model_dir: Path,
    loso_run: str = typer.Option(..., help="the real-loso summary run whose folds predict their held-out people"),
    version: str | None = typer.Option(
        None, help="write into a new version beside MODEL_DIR (the same network, this calibration) instead"
    ),
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
) -> None:
    """Calibrate the confidence of the joint assignment on the held-out people of a real-loso run and write it
    into a shipped assignment model's manifest (``confidence``); logs the reliability diagram, the expected
    calibration error, the selective accuracy and the time to answer to MLflow (training.i2s.calibration).
    A served version's answers should not change under its clients: ``--version`` ships the new calibration as
    a new version whose manifest says which it derives from."""
    import datetime as dt
    import json
    import shutil

    from service.core.manifest import read_manifest, write_manifest
    from training.i2s.calibration import calibrate as run_calibration
    from training.i2s.calibration import confidence_spec, servable
    from training.tracking import setup_tracking

    setup_tracking("i2s")  # beside the runs it calibrates, so that the snapshot keeps it
    manifest = read_manifest(model_dir / "manifest.json")
    if manifest.task != "i2s_assignment":
        raise typer.BadParameter(f"{model_dir} is a {manifest.task} model; calibrate takes i2s_assignment models")
    source = model_dir
    if version is not None:
        target = model_dir.parent / version
        if target.exists():
            raise typer.BadParameter(f"{target} exists already")
        shutil.copytree(model_dir, target)
        manifest.exporter = {**manifest.exporter, "derived_from": f"{manifest.name}/{manifest.version}"}
        manifest.version, manifest.created_utc = version, dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        write_manifest(manifest, target / "manifest.json")
        model_dir = target
    fitted, metrics, timing = run_calibration(loso_run, resolve_data_dir(data_dir), model_dir, cache_dir)
    if servable(fitted).session is None and fitted.session is not None:
        typer.echo("no session probability reached the target: the manifest keeps the per-sensor rule", err=True)
    run_id = str(metrics.pop("run"))
    manifest.confidence = confidence_spec(
        fitted,
        fitted_on=f"sessions of the held-out people of real-loso run {loso_run}; figures cross-fitted by person "
        f"(MLflow run {run_id})",
        metrics=metrics,
        command=f"python -m training.cli calibrate {source} --loso-run {loso_run}"
        + (f" --version {version}" if version else ""),
    )
    write_manifest(manifest, model_dir / "manifest.json")
    typer.echo(json.dumps(metrics, indent=1))
    typer.echo(json.dumps(timing, indent=1))


@app.command("real-table")
def real_table_command(
    loso_run: str = typer.Option(..., help="a real-loso summary run"),
    models: list[Path] = typer.Option([], "--model", help="shipped model dirs to set beside it (repeatable)"),
    data_dir: Path | None = DataDir,
) -> None:
    """Markdown table: each held-out person's figures from a real-loso run beside shipped models' own figures on
    the same recordings (their manifests)."""
    import mlflow

    from training.i2s.ship import real_table
    from training.tracking import default_tracking_uri

    mlflow.set_tracking_uri(default_tracking_uri())
    typer.echo(real_table(loso_run, models, resolve_data_dir(data_dir)))


@app.command("real-confusion")
def real_confusion_command(
    loso_run: str = typer.Option(..., help="a real-loso summary run"),
    data_dir: Path | None = DataDir,
) -> None:
    """Markdown table: what each held-out person's sensors are taken for in a real-loso run (moving windows, each
    window's own answer); a confusion matrix image per person is logged with the summary run."""
    import mlflow

    from training.i2s.ship import real_confusion
    from training.tracking import default_tracking_uri

    mlflow.set_tracking_uri(default_tracking_uri())
    typer.echo(real_confusion(loso_run, resolve_data_dir(data_dir)))


@app.command("swing-fit")
def swing_fit_command(
    config: Path = typer.Option(Path("training/configs/i2s_assignment.yaml"), help="whose training clips to fit on"),
    data_dir: Path | None = DataDir,
    cache_dir: Path = DEFAULT_CACHE,
) -> None:
    """Fit how sensors worn together swing together (``service.core.assignment.SWING``) on a config's simulated
    training clips; prints the table to paste there."""
    from training.i2s.config import load_config
    from training.i2s.data.split import load_clips, split_clips
    from training.i2s.swing import fit_swing

    cfg = load_config(config)
    clips = load_clips(cfg, resolve_data_dir(data_dir), cache_dir)
    train, _, _ = split_clips(clips, cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed)
    for name, (mean, std, n) in fit_swing([c for c in train if not c.variant]).items():
        typer.echo(f'    "{name}": ({mean:.3f}, {std:.3f}),  # {n} windows')


@app.command("sway-fit")
def sway_fit_command(
    whole_recording: bool = typer.Option(False, help="the pelvis' frame over the whole recording, not as live"),
    data_dir: Path | None = DataDir,
) -> None:
    """Fit how a leg sensor's swing follows the pelvis' sway (``service.core.assignment.sway_table``) on the real
    recordings that carry a pelvis sensor, every person, the pelvis' frame from the served alignment model; prints
    the table."""
    from service.core.recordings import read_all_real
    from service.core.segments import SEGMENTS
    from service.inference.registry import load_models
    from training.i2s.swing import fit_sway, recording_laterals, sway_samples

    align = load_models(Path("onnx_models"), 2)["i2s_alignment"]
    recordings = read_all_real(resolve_data_dir(data_dir))
    samples = [sway_samples(rec, recording_laterals(rec, align.run, not whole_recording)) for rec in recordings]
    typer.echo(f"# alignment {align.manifest.version}")
    for name, (mean, std, n) in sorted(fit_sway(samples).items(), key=lambda kv: SEGMENTS.index(kv[0])):
        typer.echo(f'    "{name}": ({mean:.3f}, {std:.3f}),  # {n} windows')


@app.command("swing-table")
def swing_table_command(
    loso_run: str = typer.Option(..., help="a real-loso summary run"),
    weights: list[float] = typer.Option([], "--weight", help="another swing weight to compare (repeatable)"),
    sway_weights: list[float] = typer.Option(
        [], "--sway-weight", help="a weight of the pelvis' sway to compare (repeatable; default 1/16 … 1)"
    ),
    whole_recording: bool = typer.Option(False, help="the pelvis' frame over the whole recording, not as live"),
    model: Path | None = typer.Option(None, help="a shipped model of that recipe: record the figures in its manifest"),
    data_dir: Path | None = DataDir,
) -> None:
    """Markdown table: each held-out person's per-moment answers from a real-loso run without and with how the
    sensors swing together, and with the pelvis' sway (its table fitted without the held-out person)."""
    import mlflow

    from training.i2s.swing import SWAY_WEIGHTS, swing_table
    from training.tracking import default_tracking_uri

    mlflow.set_tracking_uri(default_tracking_uri())
    command = f"python -m training.cli swing-table --loso-run {loso_run}" + (f" --model {model}" if model else "")
    sway = tuple(sway_weights) or SWAY_WEIGHTS
    typer.echo(swing_table(loso_run, resolve_data_dir(data_dir), weights, model, command, sway, not whole_recording))


@app.command("evaluate-real")
def evaluate_real_command(
    source: str = typer.Argument(..., help="a shipped model dir, or runs:/<run_id> of a tracked run"),
    config: Path = typer.Option(..., help="the config whose held-out real recordings to use"),
    data_dir: Path | None = DataDir,
) -> None:
    """On the real recordings a config did not train on (compare models on one set): an assignment model's accuracy,
    an alignment model's label-free checks (stability, half turns, uprightness; ``evaluate_real_alignment``)."""
    import tempfile

    import mlflow

    from service.core.manifest import read_manifest
    from training.i2s.evaluate import evaluate_real, evaluate_real_alignment, onnx_predictor
    from training.i2s.pipeline import held_out_recordings
    from training.tracking import default_tracking_uri, download_onnx

    cfg = load_config(config)
    with tempfile.TemporaryDirectory() as tmp:
        if source.startswith("runs:/"):
            mlflow.set_tracking_uri(default_tracking_uri())
            run = mlflow.get_run(source.removeprefix("runs:/"))
            task = run.data.tags.get("task") or run.data.params.get("task", "")
            onnx_path = download_onnx(run.data.tags["model_uri"], tmp)
        else:
            task = read_manifest(Path(source) / "manifest.json").task.removeprefix("i2s_")
            onnx_path = Path(source) / "model.onnx"
        if task not in ("assignment", "alignment"):
            raise typer.BadParameter(f"evaluate-real reads I2S assignment and alignment models; {source} is {task!r}")
        recordings = held_out_recordings(cfg, resolve_data_dir(data_dir))
        typer.echo(f"{task} on {len(recordings)} recordings: {', '.join(r.name for r in recordings)}")
        if task == "alignment":
            for key, value in evaluate_real_alignment(onnx_predictor(onnx_path), recordings).items():
                if not key.startswith("nominal_frame_heading_deg/"):
                    typer.echo(f"{key}: {value:.4f}")
            return
        metrics, _ = evaluate_real(onnx_predictor(onnx_path), recordings)
    for key, value in metrics.items():
        shown = ("accuracy/", "joint", "window_joint", "real_accuracy", "real_joint", "real_window_joint")
        if key.startswith((*shown, "real_n_windows")):
            typer.echo(f"{key}: {value:.4f}")


POSE_CACHE = Path(".cache/pose_motion")


@app.command("pose-train")
def pose_train(
    config: Path,
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    overrides: list[str] = Override,
    ship: bool = typer.Option(False, help="ship the model under onnx_models/<name>/<version>"),
    version: str | None = typer.Option(None, help="the shipped version (default 0.0.0+<run id>)"),
    models_dir: Path = typer.Option(Path("onnx_models")),
) -> None:
    """Train a pose model (training/configs/pose_*.yaml), evaluate it on validation and held-out subjects,
    export ONNX, log everything to MLflow and register it."""
    from training.pose.config import load_pose_config
    from training.pose.pipeline import run_pose_experiment

    cfg = load_pose_config(config, overrides)
    out = run_pose_experiment(cfg, resolve_data_dir(data_dir), cache_dir, models_dir if ship else None, version)
    typer.echo(f"run_id={out['run_id']} shipped={out['shipped']}")
    for activity, m in out["test"]["activity"].items():
        base = out["mean_pose"]["activity"][activity]
        typer.echo(
            f"{activity:18s} angle {m['angle_unsensed_deg']:6.2f}° (mean pose {base['angle_unsensed_deg']:6.2f}°)  "
            f"all {m['angle_all_deg']:6.2f}°  SIP {m['sip_deg']:6.2f}°  JPE {m['jpe_cm']:5.2f} cm"
        )


@app.command("pose-velocity-train")
def pose_velocity_train(
    config: Path = typer.Argument(Path("training/configs/pose_full6_velocity.yaml"), help="a velocity config"),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    overrides: list[str] = Override,
    ship: bool = typer.Option(False, help="ship it under onnx_models/<name>/<version> if it beats the rule"),
    version: str | None = typer.Option(None, help="the shipped version (default 0.0.0+<run id>)"),
    models_dir: Path = typer.Option(Path("onnx_models")),
) -> None:
    """Train the learned pelvis velocity of a pose model's sensors (``translation: learned``; TransPose 2021's
    fallback branch), choose its share on the ground on the validation subjects, score the held-out subjects
    against the supporting-foot rule, export, log to MLflow and register it."""
    from training.pose.config import load_velocity_config
    from training.pose.velocity import run_velocity_experiment

    vcfg = load_velocity_config(config, overrides)
    out = run_velocity_experiment(vcfg, resolve_data_dir(data_dir), cache_dir, models_dir if ship else None, version)
    typer.echo(f"run_id={out['run_id']} share={out['share']:g} shipped={out['shipped']}")
    key = f"share_{out['share']:g}"
    for activity, m in sorted(out["test"].items()):
        typer.echo(
            f"{activity:14s} held out, 1 s: rule {m['rule']:6.1f} cm  with the learned velocity {m[key]:6.1f} cm  "
            f"velocity alone {m['velocity']:6.1f} cm  kept in place {m['still']:6.1f} cm"
        )


@app.command("pose-placement")
def pose_placement(
    config: Path = typer.Argument(Path("training/configs/pose_full6.yaml"), help="a pose config: its training clips"),
    sensors: int = typer.Option(10, help="how many sensors to place (the pelvis counts)"),
    frames: int = typer.Option(4000, help="random training frames the MIC is estimated on"),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    overrides: list[str] = Override,
) -> None:
    """Where to put N sensors (Zheng et al. 2021 §6): mRMR over the maximal information coefficient between the
    candidate positions' measurements, the pelvis first; one MLflow run (experiment pose_placement)."""
    from training.pose.config import load_pose_config
    from training.pose.pipeline import run_placement_search

    cfg = load_pose_config(config, overrides)
    out = run_placement_search(cfg, resolve_data_dir(data_dir), cache_dir, sensors, frames)
    typer.echo(f"run_id={out['run_id']}")
    for k, (name, value, gain) in enumerate(zip(out["order"], out["phi"], out["gain"], strict=True), start=1):
        typer.echo(f"{k:2d}  {name:15s} Φ {value:+.4f}" + ("" if gain is None else f"  eq. 19 {gain:+.4f}"))


@app.command("pose-rig-hinges")
def pose_rig_hinges(
    per_source: int = typer.Option(12, help="walking clips drawn per source"),
    seed: int = typer.Option(0),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    limb_twist: str = typer.Option("rig", help="the frames' limb rule: rig (as trained) or hinge"),
) -> None:
    """Whether the rigs agree on the limbs' turn about their long axes: per source, the elbow's and the knee's
    hinge axis in the upper arm's and thigh's frame over walking clips (on y where the frames are anatomical)."""
    from training.pose.rig_check import rig_hinge_table

    typer.echo(rig_hinge_table(resolve_data_dir(data_dir), cache_dir, per_source, seed, limb_twist=limb_twist))


@app.command("pose-rig-pairs")
def pose_rig_pairs(
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    limb_twist: str = typer.Option("hinge", help="the frames' limb rule: rig or hinge (as served)"),
    trunk_axes: str = typer.Option("spine", help="the upper trunk's rule: spine (the rigs' joints) or thorax"),
) -> None:
    """How far apart li2018's and iClone's versions of the same CMU trials hold each segment (against the vertical
    and the pelvis's heading): what two rigs' frames disagree on for the same motion."""
    from service.core.body import TRUNK_AXES
    from training.pose.rig_check import paired_trial_table

    if trunk_axes not in TRUNK_AXES:
        raise typer.BadParameter(f"--trunk-axes is one of {list(TRUNK_AXES)}, got {trunk_axes!r}")
    typer.echo(paired_trial_table(resolve_data_dir(data_dir), cache_dir, limb_twist=limb_twist, trunk_axes=trunk_axes))


@app.command("pose-translation-design")
def pose_translation_design(
    model: Path = typer.Option(Path("onnx_models/pose_full6/4.1.0"), help="a shipped offline pose model"),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    flight_g: float | None = typer.Option(None, help="the flight threshold (specific force, g) to try"),
    band_m: float | None = typer.Option(None, help="the contact band (m) to try"),
    inertial_share: float | None = typer.Option(None, help="the inertial share to try"),
) -> None:
    """The translation rule on its design set (training-side clips only): per activity, the error of the pelvis
    displacement over 1 s and 5 s windows with the model's answer, on the true pose, and for a pelvis kept still."""
    import service.core.translation as translation
    from service.core.manifest import read_manifest
    from training.pose.pipeline import load_pose_data, shipped_config
    from training.pose.translation_design import design_table

    for name, value in (
        ("FLIGHT_SPECIFIC_FORCE_G", flight_g),
        ("CONTACT_BAND_M", band_m),
        ("INERTIAL_SHARE", inertial_share),
    ):
        if value is not None:
            setattr(translation, name, value)
    constants = {k: getattr(translation, k) for k in ("FLIGHT_SPECIFIC_FORCE_G", "CONTACT_BAND_M", "INERTIAL_SHARE")}
    data = load_pose_data(shipped_config(read_manifest(model / "manifest.json")), resolve_data_dir(data_dir), cache_dir)
    typer.echo(f"{model}, {constants}")
    typer.echo(f"{'design set':28s} clips  1 s cm  5 s cm  true pose 1 s cm  kept still 1 s cm")
    for name, m in design_table(model, data.train).items():
        typer.echo(
            f"{name:28s} {m['clips']:5.0f}  {m['trans_1s_cm']:6.1f}  {m['trans_5s_cm']:6.1f}  "
            f"{m['trans_truth_1s_cm']:16.1f}  {m['trans_still_1s_cm']:17.1f}"
        )


@app.command("pose-free-batch")
def pose_free_batch(
    model: Path = typer.Argument(..., help="a shipped streaming pose model exported with a batch of one"),
    version: str = typer.Option(..., help="the version to ship it as"),
    models_dir: Path = typer.Option(Path("onnx_models")),
) -> None:
    """Ship a streaming pose model again with a symbolic batch dimension (same weights and nodes, checked), so
    that the service runs several live sessions in one call."""
    from training.pose.export import free_batch_dimension

    typer.echo(free_batch_dimension(model, version, models_dir))


@app.command("pose-acc-check")
def pose_acc_check(
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    activity: str = typer.Option("walk", help="the catalogue activity to compare on"),
) -> None:
    """Compare the simulated acceleration of the Butterworth + gradient pipeline with TransPose's smoothed finite
    difference, on CMU and on Bandai-Namco (30 fps, resampled to 60 Hz first)."""
    import json

    from training.data.catalog import mocap_entries
    from training.pose.data import build_motions
    from training.pose.simulate import acceleration_check

    root = resolve_data_dir(data_dir)
    entries = mocap_entries(root, [activity])
    typer.echo(json.dumps(acceleration_check(build_motions(root, entries, cache_dir)), indent=1))


def newest_shipped(
    model: Path | None, name: str, models_dir: Path = Path("onnx_models"), task: str | None = None
) -> Path:
    """``model`` if given (checked: a shipped model folder, of ``task`` where named), else the newest version
    shipped of ``name`` under ``models_dir``."""
    if model is not None:
        return shipped_model(model, task)
    from service.inference.registry import newest_version_dir

    newest = newest_version_dir(models_dir, name)
    if newest is None:
        raise typer.BadParameter(f"no shipped version of {name} under {models_dir}; pass --model")
    return newest


def shipped_model(model: Path, task: str | None = None) -> Path:
    """``model`` if it is a shipped model folder (``manifest.json`` and ``model.onnx``) of ``task``; else a usage
    error that says what it is and what was expected."""
    from service.core.manifest import read_manifest

    if not (model / "manifest.json").is_file():
        versions = sorted(p.parent.name for p in model.glob("*/manifest.json")) if model.is_dir() else []
        hint = f"; it holds versions {versions}: name one, e.g. {model / versions[-1]}" if versions else ""
        raise typer.BadParameter(f"{model} is not a shipped model folder (no manifest.json){hint}")
    found = read_manifest(model / "manifest.json").task
    if task is not None and found != task:
        raise typer.BadParameter(f"{model} is a {found} model; this command scores {task} models")
    return model


@app.command("pose-real-check")
def pose_real_check(
    model: Path | None = typer.Option(
        None, help="a shipped lower-body pose model (default: the newest under onnx_models/pose_lower3)"
    ),
    data_dir: Path | None = DataDir,
    pelvis_heading: str = typer.Option(
        "legs",
        help="'legs': the pelvis's alignment turned to the legs' heading, as the service's assignment "
        "calibration does; 'alignment': as the I2S alignment gives it",
    ),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """A lower-body pose model on real recordings (capacitive subject, MovingReality): its thighs, feet and knee
    flexion against the thigh and foot sensors, every sensor aligned by the served I2S alignment model."""
    import json

    from service.inference.pose import PoseModel
    from service.inference.registry import load_model, load_models
    from training.pose.real_check import pooled, real_pose_check

    alignment = load_models(Path("onnx_models"), 2)["i2s_alignment"]
    model = newest_shipped(model, "pose_lower3", task="imu_pose")
    if pelvis_heading not in ("legs", "alignment"):
        raise typer.BadParameter(f"--pelvis-heading: 'legs' or 'alignment', got {pelvis_heading!r}")
    results = real_pose_check(resolve_data_dir(data_dir), PoseModel(load_model(model, 2)), alignment, pelvis_heading)
    summary = {
        "alignment_model": alignment.manifest.version,
        "pelvis_heading": pelvis_heading,
        "capacitive_sub01": pooled(results, "capacitive"),
        "movingreality": pooled(results, "movingreality"),
    }
    if as_json:
        typer.echo(json.dumps({"recordings": results, **summary}, indent=1))
        return
    for name, r in results.items():
        typer.echo(f"{name:32s} " + "  ".join(f"{k} {v:.2f}" for k, v in r.items() if k != "frames"))
    for name in ("capacitive_sub01", "movingreality"):
        typer.echo(f"pooled {name}: " + "  ".join(f"{k} {v:.2f}" for k, v in summary[name].items()))
    typer.echo(f"pelvis heading: {pelvis_heading}")


def _rigs_of(data_dir: Path | None) -> Path | None:
    """The data directory whose rigs give a user's clips of the same skeleton their training frames, where there
    is one; a user's own mocap is scored without it too."""
    try:
        return resolve_data_dir(data_dir)
    except RuntimeError as exc:
        if data_dir is not None:  # named, but not one: say so, since the frames then differ
            raise typer.BadParameter(str(exc)) from None
        typer.echo(f"no data directory ({exc}): every skeleton's frames are fitted on its own clips", err=True)
        return None


@app.command("evaluate-pose")
def evaluate_pose(
    paths: list[Path] = typer.Argument(None, help="BVH files or folders (default: the held-out subjects)"),
    model: Path = typer.Option(..., help="a shipped pose model, e.g. onnx_models/pose_full6/3.0.0"),
    mapping: Path | None = typer.Option(None, help="JSON/YAML mapping of an unknown skeleton onto the body"),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    as_json: bool = typer.Option(False, "--json", help="print per clip and overall metrics as JSON"),
    record: bool = typer.Option(
        False,
        help="held-out mode: write the figures into the model's manifest (with --sessions N > 1, as an evaluation of "
        "its own beside the one-session figures training recorded)",
    ),
    validation: bool = typer.Option(
        False,
        "--validation",
        help="score the validation subjects on the sessions training judged its epochs and recipes by, not the "
        "held-out ones (to compare two files on the same sessions before a choice)",
    ),
    tag: bool = typer.Option(
        False,
        "--tag",
        help="with --validation: write the figure into the model's registry versions, as a run tags a new one, so "
        "that the registry compares later runs with the file as served (versions tagged by runs before served-chunk "
        "evaluation were scored on whole clips)",
    ),
    velocity_model: Path | None = typer.Option(
        None,
        help="a shipped velocity model of the same sensors (onnx_models/pose_full6_velocity/<version>): also score "
        "the translation with it (translation: learned) beside the rule",
    ),
    sessions: int = typer.Option(
        1,
        min=1,
        help="simulated sessions per clip (other mountings and noise; the first is the one training scored): each "
        "clip's figures are their mean",
    ),
) -> None:
    """Score a shipped pose model on mocap: simulate its sensors on the clips and report per clip and overall
    segment-angle error, SIP error, joint-position error and jitter (per activity and subject too), with 95 %
    bootstrap intervals over clips of the mean segment-angle error."""
    import json

    import numpy as np

    from service.core.manifest import read_manifest, with_evaluation, write_manifest
    from training.pose.evaluate import clip_intervals, per_joint_mean, per_segment_mean
    from training.pose.pipeline import (
        TEST_SEED,
        VAL_SEED,
        evaluate_shipped_pose,
        load_pose_data,
        results_table,
        shipped_config,
    )
    from training.pose.user_mocap import user_clips

    if paths and (validation or record):
        raise typer.BadParameter("--validation and --record score the data directory's subjects: give no paths")
    if validation and record:
        raise typer.BadParameter("--record writes held-out figures; it does not go with --validation")
    if tag and not validation:
        raise typer.BadParameter("--tag writes the validation figure the registry compares by: give --validation")
    if tag and sessions > 1:
        raise typer.BadParameter("--tag writes the figure runs log, on one session per clip: leave --sessions at 1")
    if velocity_model is not None and sessions > 1:
        raise typer.BadParameter("--velocity-model scores one session per clip: leave --sessions at 1")
    manifest = read_manifest(shipped_model(model, "imu_pose") / "manifest.json")
    cfg = shipped_config(manifest)  # scored in the segment frames the model answers in
    skipped: list[dict[str, str]] = []  # a user's files that could not be scored, with the reason
    if paths:
        d = cfg.data
        try:
            clips = user_clips(list(paths), mapping, d.limb_twist, _rigs_of(data_dir), cache_dir, skipped, d.trunk_axes)
        except (ValueError, OSError) as exc:  # no file could be read: the first reason (a mapping's first)
            raise typer.BadParameter(str(exc)) from None
    else:
        data = load_pose_data(cfg, resolve_data_dir(data_dir), cache_dir)
        clips = data.val if validation else data.test
    results, summary = evaluate_shipped_pose(model, clips, VAL_SEED if validation else TEST_SEED, sessions)
    intervals = clip_intervals(results)
    learned = None
    if velocity_model is not None:
        learned = _learned_translation(model, velocity_model, clips, VAL_SEED if validation else TEST_SEED)
    if tag:
        from service.inference.pose import assembly, hinge_joints
        from training.pose.data import pose_evaluation_digest
        from training.pose.evaluate import flat_metrics
        from training.pose.pipeline import SELECTION_METRIC
        from training.snapshot import local_run_id
        from training.tracking import record_evaluation, setup_tracking

        setup_tracking("pose")
        value = flat_metrics(summary, "val")[SELECTION_METRIC]  # as the run logs it
        run_id = local_run_id(manifest.mlflow["run_id"])
        tagged = record_evaluation(
            manifest.name,
            run_id,
            SELECTION_METRIC,
            value,
            pose_evaluation_digest(clips, assembly(hinge_joints(cfg.data.limb_twist), cfg.sensors, cfg.outputs)),
        )
        typer.echo(f"{manifest.name} versions {tagged}: {SELECTION_METRIC} {value:.4f} (served chunks)", err=True)
    if record:
        from training.pose.pipeline import HELD_OUT, evaluation_record

        manifest = read_manifest(model / "manifest.json")
        old = next(e for e in manifest.evaluations if e.name == HELD_OUT)
        command = f"python -m training.cli evaluate-pose --model {model}"
        name = HELD_OUT  # the training run's protocol; more sessions per clip are recorded beside it
        if sessions > 1:
            command, name = f"{command} --sessions {sessions}", f"{HELD_OUT}, {sessions} sessions per clip"
        new = evaluation_record(
            name, command, old.data, summary, intervals if sessions > 1 else None, per_joint_mean(results)
        )
        write_manifest(with_evaluation(manifest, new, after=HELD_OUT), model / "manifest.json")
    error, constant = per_segment_mean(results), per_segment_mean(results, constant=True)
    joint_error, joint_bias = per_joint_mean(results), per_joint_mean(results, bias=True)
    if as_json:
        per_clip = [{"clip": r.path, "frames": r.frames, **r.metrics} for r in results]
        segments = {s: {"angle_deg": error[s], "constant_per_clip_deg": constant[s]} for s in error}
        report = {"clips": per_clip, **summary, "segments": segments, "skipped": skipped, "sessions": sessions}
        report["angle_all_interval_95"] = {k: list(v) for k, v in intervals.items()}
        report["joint_angle_error_deg"] = joint_error
        report["joint_angle_bias_deg"] = joint_bias
        typer.echo(json.dumps(report | ({"translation_learned": learned} if learned else {}), indent=1))
        return
    for left_out in skipped:
        typer.echo(f"left out {left_out['clip']}: {left_out['reason']}")
    typer.echo(results_table(results))
    typer.echo("segment          angle°  of it constant per clip°")
    for s in error:
        typer.echo(f"{s:16s} {error[s]:6.2f}  {constant[s]:6.2f}")
    _echo_joint_errors(joint_error, "mean absolute")
    _echo_joint_errors(joint_bias, "mean signed (answer − truth)")
    for kind in ("activity", "subject"):
        for key, m in summary[kind].items():
            typer.echo(
                f"{kind} {key:22s} all {m['angle_all_deg']:6.2f}°  unsensed {m['angle_unsensed_deg']:6.2f}°  "
                f"SIP {m['sip_deg']:6.2f}°  JPE {m['jpe_cm']:5.2f} cm  jitter {m['jitter_mps3']:7.1f} m/s³"
            )
            five = "n/a (no clip lasts 5 s)" if np.isnan(m["trans_5s_cm"]) else f"{m['trans_5s_cm']:5.1f} cm"
            typer.echo(
                f"{'':{len(kind) + 23}s} translation error over 1 s {m['trans_1s_cm']:5.1f} cm, over 5 s {five} "
                f"(on the true pose {m['trans_truth_1s_cm']:5.1f} cm, pelvis kept in place "
                f"{m['trans_still_1s_cm']:5.1f} cm)"
            )
    typer.echo(
        f"mean segment-angle error with 95 % bootstrap intervals over clips ({sessions} simulated session"
        f"{'s' if sessions > 1 else ''} per clip):"
    )
    for key, (low, high) in intervals.items():
        m = summary["overall"]["all"] if key == "all" else summary["activity"][key]
        typer.echo(f"  {key:14s} {m['angle_all_deg']:6.2f}°  [{low:.2f}, {high:.2f}]")
    m = summary["overall"]["all"]
    typer.echo(
        f"overall all {m['angle_all_deg']:.2f}°, unsensed {m['angle_unsensed_deg']:.2f}°, JPE {m['jpe_cm']:.2f} cm, "
        f"translation over 1 s {m['trans_1s_cm']:.1f} cm (pelvis kept in place {m['trans_still_1s_cm']:.1f} cm)"
    )
    if learned is not None:
        typer.echo(f"translation over 1 s with {velocity_model} (cm): the rule, the rule with the learned velocity")
        for activity, row in sorted(learned.items()):
            typer.echo(f"  {activity:14s} rule {row['rule']:6.1f}  learned {row['learned']:6.1f}")


def _echo_joint_errors(joint_error: dict[str, dict[str, float]], what: str) -> None:
    """The joint angles' errors (``service.core.joint_angles``; ``what``: which mean), a row per joint, a column per
    motion type, flexion / abduction / rotation in each cell."""
    from service.core.joint_angles import JOINT_COMPONENTS, JOINTS

    kinds = list(joint_error)
    joints = [j for j in JOINTS if f"{j}_flexion" in joint_error["all"]]
    if not joints:
        return
    typer.echo(f"joint angle error, {what} (flexion / abduction / rotation, degrees):")
    typer.echo(f"  {'joint':22s}" + "".join(f"{k:>20s}" for k in kinds))
    for j in joints:
        cells = ["/".join(f"{joint_error[k][f'{j}_{c}']:.1f}" for c in JOINT_COMPONENTS) for k in kinds]
        typer.echo(f"  {j:22s}" + "".join(f"{c:>20s}" for c in cells))


def _learned_translation(model: Path, velocity_model: Path, clips: list, seed: int) -> dict[str, dict[str, float]]:
    """Per activity, the translation error over 1 s with the rule and with the velocity model's share of its
    velocity (``translation: learned``), on the sessions the pose figures were scored on."""
    from service.inference.pose import PoseModel
    from service.inference.registry import load_model
    from service.inference.velocity import VelocityModel
    from training.pose.config import PoseConfig
    from training.pose.train import fixed_sessions
    from training.pose.velocity import learned_velocities, translation_cases, translation_errors

    pose = PoseModel(load_model(model, 2))
    velocity = VelocityModel(load_model(velocity_model, 2))
    if velocity.spec.sensors != pose.spec.sensors:
        raise typer.BadParameter(f"{velocity_model} reads {velocity.spec.sensors}, {model} {pose.spec.sensors}")
    cfg = PoseConfig(name=pose.name, sensors=pose.spec.sensors, output_segments=pose.spec.output_segments)
    cases = translation_cases(clips, fixed_sessions(clips, cfg, seed), pose)
    share = velocity.spec.learned_share
    errors = translation_errors(cases, learned_velocities(velocity.predict, cases), [share])
    key = f"share_{share:g}"
    return {a: {"rule": r["rule"], "learned": r[key], "clips": r["clips"]} for a, r in errors.items()}


FLEX_TABLE5 = ["bilstm", "transformer", "fcn", "tcn", "bilstm_c", "bilstm_m", "bilstm_cm"]


def _flex_configs(configs: list[Path], overrides: list[str]):
    from training.flex.config import load_flex_config

    return [load_flex_config(c, overrides) for c in configs]


@app.command("flex-train")
def flex_train(
    configs: list[Path] = typer.Argument(
        None, help="flex configs (default: the Table 5 set, training/configs/flex_*.yaml)"
    ),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    overrides: list[str] = Override,
    ship: str | None = typer.Option(None, help="ship the model of this config name under onnx_models/"),
    version: str | None = typer.Option(None, help="the shipped version (default 0.0.0+<run id>)"),
    models_dir: Path = typer.Option(Path("onnx_models")),
) -> None:
    """Train flex networks on simulated sensors (Chen et al. 2024 Table 5: one MLflow run each, then one summary
    run with the table, bar chart and ageing curves), evaluated on held-out subjects."""
    from training.flex.pipeline import (
        build_sets,
        load_flex_data,
        log_summary_run,
        markdown_table,
        run_flex_experiment,
        summary_table,
    )

    paths = configs or [Path(f"training/configs/flex_{v}.yaml") for v in FLEX_TABLE5]
    cfgs = _flex_configs(paths, overrides)
    split = {c.data.model_dump_json(exclude={"bandai_share", "suits_per_clip", "activity_cap_frames"}) for c in cfgs}
    if len(split) > 1:
        raise typer.BadParameter("one flex-train call takes configs of one data split (sources and subjects)")
    data = load_flex_data(cfgs[0], resolve_data_dir(data_dir), cache_dir)
    sets_by_data: dict[str, dict] = {}  # configs that draw their training windows alike share the simulated sets
    results = []
    for cfg in cfgs:
        key = f"{cfg.data.model_dump_json()}|{cfg.model.window}"
        if key not in sets_by_data:
            sets_by_data[key] = build_sets(cfg, data)
        shipping = ship == cfg.name
        target = models_dir if shipping else None
        results.append(run_flex_experiment(cfg, data, sets_by_data[key], target, version if shipping else None))
        r = results[-1]
        typer.echo(
            f"{cfg.variant:12s} held-out {r['test']['mae_deg']:.2f}° (mean pose {r['mean_pose']['mae_deg']:.2f}°) "
            f"jitter {r['test']['jitter_deg_s3'] / 1e4:.3f}e4 °/s³, {r['train_wall_time_s'] / 60:.1f} min"
        )
    if len(results) > 1:
        run_id = log_summary_run(results, cfgs[0].tracking.experiment)
        typer.echo(f"summary run {run_id}")
        typer.echo(markdown_table(summary_table(results)))


@app.command("evaluate-flex")
def evaluate_flex(
    paths: list[Path] = typer.Argument(None, help="BVH files or folders (default: the held-out subjects)"),
    mapping: Path | None = typer.Option(None, help="JSON/YAML mapping of an unknown skeleton onto the body"),
    model: Path | None = typer.Option(
        None, help="a shipped flex model folder (default: the newest under onnx_models/flex_bilstm_cm)"
    ),
    data_dir: Path | None = DataDir,
    cache_dir: Path = typer.Option(POSE_CACHE, help="canonical-body motion cache"),
    as_json: bool = typer.Option(False, "--json"),
    validation: bool = typer.Option(
        False,
        "--validation",
        help="score the validation subjects' suits, which its run chose its epoch by, not the held-out ones (and "
        "the same suits aged beyond the training range, which a choice made for ageing may look at)",
    ),
    tag: bool = typer.Option(
        False,
        "--tag",
        help="with --validation: write the figure into the model's registry versions under the evaluation digest "
        "of this installation, so that the registry compares later runs with it",
    ),
    record: bool = typer.Option(
        False,
        "--record",
        help="write the held-out figures into the model's manifest (after a change to how it answers)",
    ),
) -> None:
    """A shipped flex model (its ONNX file through onnxruntime) on simulated suits worn in mocap: the held-out
    subjects', or the BVH files given (read as ``evaluate-pose`` reads them, a mapping file for an unknown
    skeleton): error overall, per motion type, clip and joint, jitter, and under ageing beyond the training range
    and a replaced sensor."""
    import json

    from service.core.joint_angles import JOINT_COMPONENTS
    from service.inference.registry import load_model
    from training.flex.pipeline import (
        SELECTION_METRIC,
        evaluate_served,
        evaluation_digest,
        load_flex_data,
        shipped_config,
    )

    if paths and (validation or record):
        raise typer.BadParameter("--validation and --record score the data directory's subjects: give no paths")
    if tag and not validation:
        raise typer.BadParameter("--tag writes the validation figure the registry compares by: give --validation")
    if record and validation:
        raise typer.BadParameter("--record writes held-out figures; it does not go with --validation")
    model_dir = newest_shipped(model, "flex_bilstm_cm", task="flex_pose")
    loaded = load_model(model_dir, 2)
    m = loaded.manifest
    if "test_subjects" not in m.training_data:
        raise typer.BadParameter(
            f"{m.name} {m.version} is not a simulated-suit model (its manifest names no held-out subjects); "
            "a capacitive sleeve model is scored by evaluate-capacitive"
        )
    cfg = shipped_config(m)  # its clips built and split as its run had them
    skipped: list[dict[str, str]] = []  # a user's files that could not be scored, with the reason
    if paths:
        from training.flex.pipeline import user_flex_data

        try:
            data = user_flex_data(cfg, list(paths), mapping, _rigs_of(data_dir), cache_dir, skipped)
        except (ValueError, OSError) as exc:  # no file could be read: the first reason (a mapping's first)
            raise typer.BadParameter(str(exc)) from None
    else:
        data = load_flex_data(cfg, resolve_data_dir(data_dir), cache_dir)
    out = evaluate_served(loaded, data, validation)
    if validation:
        val = out["val"]
        if tag:
            from training.snapshot import local_run_id
            from training.tracking import record_evaluation, setup_tracking

            setup_tracking(cfg.tracking.experiment)
            run_id = local_run_id(m.mlflow["run_id"])
            tagged = record_evaluation(m.name, run_id, SELECTION_METRIC, val["mae_deg"], evaluation_digest(cfg, data))
            if not tagged:
                raise typer.BadParameter(
                    f"no registered version of {m.name} comes from run {run_id} in this tracking store: nothing tagged "
                    "(restore the store with snapshot-restore, or set MLFLOW_TRACKING_URI to the one it was trained in)"
                )
            typer.echo(f"{m.name} versions {tagged}: {SELECTION_METRIC} {val['mae_deg']:.4f}", err=True)
        if as_json:
            typer.echo(json.dumps(val | {"ageing": out["ageing"]}, indent=1))
            return
        typer.echo(f"validation: {val['mae_deg']:.2f}° jitter {val['jitter_deg_s3'] / 1e4:.3f}e4 °/s³")
        for b, v in out["ageing"].items():
            typer.echo(f"validation, ageing {b}: {v['mae_deg']:.2f}° jitter {v['jitter_deg_s3'] / 1e4:.3f}e4")
        return
    test = out["test"]
    if record:
        from service.core.manifest import with_evaluation, write_manifest
        from training.flex.pipeline import HELD_OUT, held_out_metrics

        old = next((e for e in m.evaluations if e.name == HELD_OUT), None)
        if old is None:
            raise typer.BadParameter(f"{m.name} {m.version}'s manifest has no held-out evaluation to record into")
        metrics = held_out_metrics(test, out["ageing"], out["replaced"])
        metrics |= {k: v for k, v in old.metrics.items() if k not in metrics}  # the mean pose's: not the model's
        write_manifest(with_evaluation(m, old.model_copy(update={"metrics": metrics})), model_dir / "manifest.json")
    if as_json:
        typer.echo(json.dumps(out | ({"skipped": skipped} if paths else {}), indent=1))
        return
    for left_out in skipped:
        typer.echo(f"left out {left_out['clip']}: {left_out['reason']}")
    for c in test["clips"] if paths else []:
        typer.echo(f"  {c['clip']}: {c['mae_deg']:6.2f}°  ({c['frames']} frames, jitter {c['jitter_deg_s3']:.0f} °/s³)")
    typer.echo(
        f"{'these clips' if paths else 'held-out'}: {test['mae_deg']:.2f}° jitter "
        f"{test['jitter_deg_s3'] / 1e4:.3f}e4 °/s³; without each clip's constant offset per angle "
        f"{test['offset_free_mae_deg']:.2f}°"
    )
    for a, v in out["test"]["per_activity"].items():
        typer.echo(f"  {a:18s} {v['mae_deg']:6.2f}°  ({v['frames']} frames)")
    typer.echo(
        f"  {'joint':22s} {'mean':>6s}  " + "  ".join(f"{c:>9s}" for c in JOINT_COMPONENTS) + "  bias (answer − truth)"
    )
    for j, v in out["test"]["per_joint"].items():
        parts, bias = out["test"]["per_component"][j], out["test"]["bias"][j]
        typer.echo(
            f"  {j:22s} {v:6.2f}°  "
            + "  ".join(f"{parts[c]:8.2f}°" for c in JOINT_COMPONENTS)
            + "  "
            + " ".join(f"{bias[c]:+6.1f}" for c in JOINT_COMPONENTS)
        )
    for b, v in out["ageing"].items():
        typer.echo(f"ageing {b}: {v['mae_deg']:.2f}° jitter {v['jitter_deg_s3'] / 1e4:.3f}e4")
    typer.echo(f"one sensor replaced mid-clip: {out['replaced']['mae_deg']:.2f}°")


@app.command("capacitive-train")
def capacitive_train(
    configs: list[Path] = typer.Argument(None, help="default: training/configs/flex_capacitive_knee.yaml"),
    data_dir: Path | None = DataDir,
    overrides: list[str] = Override,
    ship: bool = typer.Option(False, help="ship the model under onnx_models/<name>/<version>"),
    version: str | None = typer.Option(None, help="the shipped version (default 0.0.0+<run id>)"),
    models_dir: Path = typer.Option(Path("onnx_models")),
    held_out_run: list[str] = typer.Option(
        [], help="a run of the same recipe that held a trial out: its figures go into the manifest (repeatable)"
    ),
) -> None:
    """Train knee flexion from real capacitive sleeves (one trial type trains, the other is held out; or every
    trial, for a model to ship, with its recipe's held-out runs named), log it to MLflow and register it."""
    from training.flex.capacitive import run_capacitive_experiment
    from training.flex.config import load_capacitive_config

    for path in configs or [Path("training/configs/flex_capacitive_knee.yaml")]:
        cfg = load_capacitive_config(path, overrides)
        out = run_capacitive_experiment(
            cfg, resolve_data_dir(data_dir), models_dir if ship else None, version, held_out_run
        )
        m = out["metrics"]
        what = f"the {cfg.held_out_leg} leg's sleeve" if cfg.held_out_leg else cfg.test_trial
        held_out = (
            f"held-out {what} {m['test_mae_deg']:.2f}° (mean flexion {m['test_mean_flexion_mae_deg']:.2f}°)"
            if "test_mae_deg" in m
            else "nothing held out"
        )
        typer.echo(
            f"{cfg.name} ({cfg.variant}): validation {m['val_mae_deg']:.2f}°, {held_out}, "
            f"{m['train_wall_time_s']:.0f} s; run {out['run_id']}"
        )


@app.command("evaluate-capacitive")
def evaluate_capacitive_command(
    model: Path | None = typer.Option(
        None, help="a shipped capacitive model (default: the newest under onnx_models/flex_capacitive_knee)"
    ),
    data_dir: Path | None = DataDir,
    test_trial: str = typer.Option("CSStiffKnee", help="the trial scored"),
    train_trial: str = typer.Option(
        "CSBaseline", help="the trial of the same session the knee hinge reference is fitted on (may be the same)"
    ),
    source: str = typer.Option(
        "capacitive_sub01", help="the subject's folder under imu_real/ (another subject in the same layout works)"
    ),
) -> None:
    """A shipped capacitive knee model (onnxruntime) on a trial: knee flexion MAE per leg and both, and whether the
    model trained on that trial (then it is no held-out figure); a leg that cannot be scored is named with the
    reason (``skipped_legs``)."""
    import json

    from service.inference.registry import load_model
    from training.flex.capacitive import UnscorableSubject, evaluate_capacitive

    loaded = load_model(newest_shipped(model, "flex_capacitive_knee", task="flex_pose"), 2)
    if loaded.manifest.name != "flex_capacitive_knee" and "sleeve_lag_s" not in loaded.manifest.training_data:
        raise typer.BadParameter(
            f"{loaded.manifest.name} {loaded.manifest.version} is not a capacitive sleeve model; a simulated-suit "
            "model is scored by evaluate-flex"
        )
    try:
        out = evaluate_capacitive(loaded, resolve_data_dir(data_dir), test_trial, train_trial, source)
    except (FileNotFoundError, UnscorableSubject) as exc:  # a subject's files in another layout: what was expected
        raise typer.BadParameter(str(exc)) from None
    typer.echo(json.dumps(out, indent=1))


@app.command("evaluate-csv")
def evaluate_csv(
    sensor: list[str] = typer.Option(
        ..., "--sensor", help="SEGMENT=PATH, one per sensor: a CSV file and the segment the sensor was on"
    ),
    rate: float = typer.Option(..., help="the files' sample rate, Hz"),
    acc_unit: str = typer.Option("m/s^2", help="m/s^2 or g"),
    gyr_unit: str = typer.Option("rad/s", help="rad/s or deg/s"),
    skip_columns: int = typer.Option(0, help="leading columns before acc x, y, z, gyr x, y, z (e.g. 1 for time)"),
    models: Path = typer.Option(Path("onnx_models"), help="the model tree; the newest version of each is used"),
    assignment: str | None = typer.Option(None, help="an assignment version to use instead (e.g. 1.8.0)"),
    alignment: str | None = typer.Option(None, help="an alignment version to use instead"),
) -> None:
    """Score the shipped models on a labelled recording of your own: one CSV file per sensor (a header row, then
    acc and gyr columns), all recorded together. Prints the assignment per window, per moment (one-to-one over the
    sensors, as the service answers), per moment with the worn segments declared, per moment with each sensor's
    body part declared (its side not), and over the whole recording,
    and the label-free alignment checks (``evaluate_real``, ``evaluate_real_alignment``)."""
    from service.core.assignment import is_moving
    from service.core.recordings import csv_recording
    from service.core.segments import SEGMENTS
    from service.core.windowing import MODEL_RATE_HZ, WINDOW_SAMPLES, sliding_windows
    from service.inference.registry import version_key
    from training.i2s.evaluate import evaluate_real, evaluate_real_alignment, onnx_predictor

    files = []
    for item in sensor:
        segment, sep, path = item.partition("=")
        if not sep or segment not in SEGMENTS:
            raise typer.BadParameter(f"expected SEGMENT=PATH with SEGMENT one of {', '.join(SEGMENTS)}, got {item!r}")
        files.append((segment, Path(path)))
    if len({segment for segment, _ in files}) != len(files):
        raise typer.BadParameter(f"one sensor per segment, got {[segment for segment, _ in files]}")
    try:
        rec = csv_recording("csv", files, rate, acc_unit, gyr_unit, skip_columns)
    except (ValueError, OSError) as exc:
        raise typer.BadParameter(str(exc)) from None

    def model_dir(task: str, version: str | None) -> Path:
        versions = sorted((d.name for d in (models / task).iterdir() if d.is_dir()), key=version_key)
        return models / task / (version or versions[-1])

    moving = [int(is_moving(sliding_windows(s.imu)).sum()) for s in rec.sensors]
    if not all(moving):
        raise typer.BadParameter(
            f"every sensor needs a moving {WINDOW_SAMPLES}-sample window at {MODEL_RATE_HZ:g} Hz; moving windows "
            f"per sensor: {dict(zip((s.sensor_id for s in rec.sensors), moving, strict=True))}"
        )
    assign_dir, align_dir = model_dir("i2s_assignment", assignment), model_dir("i2s_alignment", alignment)
    metrics, _ = evaluate_real(onnx_predictor(assign_dir / "model.onnx"), [rec])
    typer.echo(f"assignment {assign_dir}: {int(metrics['real_n_windows'])} moving windows")
    keys = ("real_accuracy", "real_window_joint_accuracy", "real_window_joint_swing_accuracy")
    for key in (*keys, "real_window_joint_worn_accuracy"):
        typer.echo(f"  {key}: {metrics[key]:.4f} (ignoring left/right {metrics[key + '_ignoring_side']:.4f})")
    typer.echo(
        f"  real_window_joint_part_accuracy (body parts declared): {metrics['real_window_joint_part_accuracy']:.4f}"
    )
    typer.echo(f"  joint assignment over the recording: {metrics['real_joint_assignment_correct_fraction']:.4f}")
    typer.echo(
        "  the same, weighing how the sensors swing together (as the service answers with a model calibrated so): "
        f"{metrics['real_joint_assignment_swing_correct_fraction']:.4f}"
    )
    for s in rec.sensors:
        typer.echo(f"  {s.sensor_id}: {metrics.get(f'accuracy/csv/{SEGMENTS[s.segment]}', float('nan')):.4f}")
    checks = evaluate_real_alignment(onnx_predictor(align_dir / "model.onnx"), [rec])
    typer.echo(f"alignment {align_dir} (label-free checks):")
    for key, value in checks.items():
        if key.startswith("real_"):
            typer.echo(f"  {key}: {value:.2f}")


@app.command("offset-baseline")
def offset_baseline(
    config: Path, data_dir: Path | None = DataDir, cache_dir: Path = DEFAULT_CACHE, overrides: list[str] = Override
) -> None:
    """Alignment error of the untrained population-offset reference on a config's LOSO fold (Table A10)."""
    from service.core.segments import SEGMENTS
    from training.i2s.data.split import load_clips, split_clips
    from training.i2s.evaluate import population_offset_baseline

    cfg = load_config(config, overrides)
    clips = load_clips(cfg, resolve_data_dir(data_dir), cache_dir)
    train_clips, _, test_clips = split_clips(clips, cfg.data.test_subjects, cfg.data.val_fraction, cfg.seed)
    m = population_offset_baseline(train_clips, test_clips, cfg.augmentation)
    headline = ", ".join(f"{k} {m[f'{k}_angle_error_deg']:.2f}°" for k in ("mean", "median", "max"))
    typer.echo(f"held out {cfg.data.test_subjects}: {headline}")
    typer.echo("segment: mean error about x / y / z (deg)")
    for name in SEGMENTS:
        typer.echo(f"  {name}: " + " / ".join(f"{m[f'{name}_ax{ax}_mean_deg']:.1f}" for ax in range(3)))


SNAPSHOT = Path("mlflow_snapshot")


def _restore_into_empty_store() -> None:
    """Replay the committed snapshot into the current tracking store if it has no runs at all (a fresh clone)."""
    from training.snapshot import log_restore, restore_if_empty

    if (report := restore_if_empty(SNAPSHOT, Path("onnx_models"))) is not None:
        log_restore(report)


@app.command("snapshot-export")
def snapshot_export(
    out_dir: Path = typer.Option(SNAPSHOT),
    experiment: list[str] = typer.Option(["i2s", "pose", "flex", "flex_capacitive", "pose_placement"]),
) -> None:
    """Write the finished runs of the tracking store and its registry to a folder (training.snapshot)."""
    import mlflow

    from training.snapshot import export_snapshot
    from training.tracking import default_tracking_uri

    mlflow.set_tracking_uri(default_tracking_uri())
    typer.echo(f"{export_snapshot(out_dir, experiment)} runs written to {out_dir}")


@app.command("snapshot-restore")
def snapshot_restore(
    snapshot_dir: Path = typer.Option(SNAPSHOT), models_dir: Path = typer.Option(Path("onnx_models"))
) -> None:
    """Replay a snapshot into the tracking store; runs restored before are skipped (training.snapshot)."""
    import mlflow

    from training.snapshot import log_restore, restore_snapshot
    from training.tracking import default_tracking_uri

    mlflow.set_tracking_uri(default_tracking_uri())
    log_restore(restore_snapshot(snapshot_dir, models_dir))


@app.command("restore-model")
def restore_model_cmd(
    name: str,
    version: str,
    snapshot_dir: Path = typer.Option(SNAPSHOT),
    models_dir: Path = typer.Option(Path("onnx_models")),
) -> None:
    """Bring a shipped version that is no longer served back into onnx_models/ from the snapshot's archive
    (``mlflow_snapshot/models/``), with an ensemble's members; the service then serves it when pinned with
    WEARMOCAP_MODEL_VERSIONS, or by default if it is the newest."""
    from training.snapshot import restore_model

    try:
        restored = restore_model(name, version, snapshot_dir, models_dir)
    except (LookupError, FileExistsError) as exc:
        raise typer.BadParameter(str(exc)) from None
    for folder in restored:
        typer.echo(f"restored {folder}")


@app.command("archive-model")
def archive_model_cmd(
    name: str,
    version: str,
    snapshot_dir: Path = typer.Option(SNAPSHOT),
    models_dir: Path = typer.Option(Path("onnx_models")),
) -> None:
    """Move a version that is no longer served out of onnx_models/ into the snapshot's archive (``restore-model``
    brings it back)."""
    from training.snapshot import archive_model

    typer.echo(f"archived {archive_model(name, version, snapshot_dir, models_dir)}")


@app.command()
def ui(
    port: int = 5000,
    host: str = "127.0.0.1",
    restore: bool = typer.Option(True, help="restore mlflow_snapshot/ into an empty store first"),
) -> None:
    """Start the MLflow UI on the project's tracking store. A store with no runs yet (a fresh clone) first gets the
    committed snapshot of the runs behind the shipped models (``snapshot-restore``)."""
    import mlflow

    from training.tracking import default_tracking_uri

    uri = default_tracking_uri()
    mlflow.set_tracking_uri(uri)
    if restore:
        _restore_into_empty_store()
    from mlflow.tracking import MlflowClient

    from training.run_labels import label_unlabelled

    label_unlabelled(MlflowClient())
    # One worker and no job runner (MLflow's GenAI jobs): three processes instead of about sixteen.
    cmd = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri, "--host", host, "--port", str(port)]
    cmd += ["--workers", "1"]
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    typer.echo(f"MLflow UI on http://{host}:{port} (store {uri})")
    raise typer.Exit(subprocess.call(cmd, env=env))


def main() -> None:
    """The command line; a config or override it cannot use ends with what was expected (exit 2), not a traceback."""
    from pydantic import ValidationError

    from training.config import ConfigError

    try:
        app()
    except (ConfigError, ValidationError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
