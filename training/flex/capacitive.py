"""Knee flexion from real capacitive sleeves (Pearl et al. 2022; ``capacitive_sub01``), with the networks of Chen
et al. 2024: seven sleeve channels on one leg's shank and thigh → that knee's flexion.

The reference is the knee's functional hinge angle between the Xsens femur and tibia sensors
(``service.core.flex.fit_hinge``), fitted per leg on the training trial and applied unchanged to the held-out
trial (the same session and mounting). Both legs' sleeves train one model (each leg one recording); the last
``val_share`` of the training trial of each leg is the validation part (early stopping, the choice between
variants); the other trial type is the test and never chooses anything.

The model shipped for other people's sleeves trains on every trial (``also_train``): it has no held-out trial of
its own, so its manifest carries the held-out figures of runs of the same recipe that held one out
(``held_out_evaluation``), as an I2S model trained on every person carries its recipe's leave-one-person-out ones.

The sleeves and the Xsens sensors are only roughly synchronised (the dataset's ReadMe): Sub01's baseline trial
reads its sleeves 0.25 s (left) and 0.39 s (right) behind the Xsens rows. Each leg's sleeve is put in step with
the Xsens sensors by its read-out board's own IMU against the Xsens shank sensor
(``service.core.recordings.capacitive_sleeve_sync``; ``sync: false`` pairs rows as the files give them).
"""

from __future__ import annotations

import json
import logging
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import mlflow
import numpy as np
import onnx
import pandas as pd
from mlflow.tracking import MlflowClient

from service.core.flex import fit_hinge, hinge_angle_deg
from service.core.manifest import Evaluation, ReadoutCheckSpec, sha256_file
from service.core.recordings import (
    CAPACITIVE_CHANNELS,
    CAPACITIVE_FAILURE,
    CAPACITIVE_REFERENCE_S,
    SYNC_MIN_CORRELATION,
    capacitive_sleeve_sync,
    read_capacitive_oriented,
    read_capacitive_sleeve,
)
from service.core.resample import resample_uniform
from service.inference.registry import load_model
from training.config import flatten
from training.flex.config import CapacitiveConfig
from training.flex.data import FlexClip, WindowSet, window_set
from training.flex.evaluate import clip_metrics, mean_pose_predictor
from training.flex.export import build_flex_manifest, export_flex_onnx, onnx_parity
from training.flex.pipeline import log_datasets
from training.flex.train import torch_predictor, train_flex
from training.plots import flex_learning_curve_png, traces_png
from training.run_labels import label_run
from training.shipping import ship_files, with_registry
from training.snapshot import local_run_id
from training.tracking import log_onnx_model, maybe_promote, register_model, setup_tracking

log = logging.getLogger(__name__)

SIDES = ("Left", "Right")
REFERENCE_VERSION = "ref2"  # 2: the knee reference from repaired orientation rows (2026-12-06)
CHANNEL_UNITS = "raw capacitance reading of the sleeve's read-out (Sub01: about 9,000-15,000 left, 900-1,300 right)"
HINGE_CONVENTION = (
    "knee flexion in degrees, positive flexed: the functional hinge angle between femur and tibia sensors "
    "(service.core.flex.fit_hinge), zero at the training trial's 2nd percentile (full extension in walking)"
)


class UnscorableSubject(ValueError):
    """A subject's trial in which no leg can be scored (``evaluate_capacitive``), with each leg's reason."""


@dataclass
class LegRecording:
    trial: str
    side: str
    readings: np.ndarray  # (T, 7) at the model rate
    flexion_deg: np.ndarray  # (T,)
    sleeve_lag_s: float = 0.0  # how far the file's sleeve rows lagged the Xsens rows (undone here)


def read_trials(
    cfg: CapacitiveConfig, data_dir: Path, skipped: dict[str, str] | None = None, sleeves_of: set[str] | None = None
) -> dict[str, list[LegRecording]]:
    """Every trial of ``cfg``, both legs, at ``cfg.rate_hz``; the hinge of each knee fitted on ``cfg.train_trial``.
    With ``skipped``, a leg that fails in any trial (its sleeve file missing or unreadable or without a channel, its
    thigh or shank sensor missing, its sleeve not to be put in step with the Xsens rows, its hinge not to be fitted)
    is left out of every trial, its reason recorded there under its side; without it the error is raised.
    ``sleeves_of``: the trials whose sleeves are read (default: every one); the others give only their orientations
    (the hinge fit) and no recordings."""
    names = cfg.training_trials + ([cfg.test_trial] if cfg.test_trial else [])
    oriented = {t: read_capacitive_oriented(data_dir, t, cfg.source) for t in names}
    out: dict[str, list[LegRecording]] = {t: [] for t in names}
    for side in SIDES:
        try:
            legs = _read_leg(cfg, data_dir, oriented, side, set(names) if sleeves_of is None else sleeves_of)
        except (FileNotFoundError, ValueError) as exc:
            if skipped is None:
                raise
            log.warning("%s %s leg left out: %s", cfg.source, side, exc)
            skipped[side] = str(exc)
            continue
        for trial, rec in legs.items():
            out[trial].append(rec)
    return out


def _read_leg(
    cfg: CapacitiveConfig, data_dir: Path, oriented: dict[str, dict], side: str, sleeves_of: set[str]
) -> dict[str, LegRecording]:
    """One leg of the trials ``sleeves_of``: the sleeve in step with the Xsens sensors, and its knee's flexion (the
    hinge fitted on ``cfg.train_trial``'s orientations)."""
    thigh, shank = f"{side}UpperLeg", f"{side}LowerLeg"
    for trial, sensors in oriented.items():
        missing = [s for s in (thigh, shank) if s not in sensors]
        if missing:
            raise ValueError(
                f"{cfg.source}/{trial}: no {' or '.join(missing)} sensor in its Orientations.sto (its columns read "
                f"as {sorted(f'{seg} ({s.name})' for seg, s in sensors.items())})"
            )
    fit = oriented[cfg.train_trial]
    hinge = fit_hinge(fit[thigh].q_world_sensor, fit[shank].q_world_sensor)
    out = {}
    for trial, sensors in oriented.items():
        if trial not in sleeves_of:
            continue
        cs, rate = read_capacitive_sleeve(data_dir, trial, side, cfg.source)
        angle = hinge_angle_deg(sensors[thigh].q_world_sensor, sensors[shank].q_world_sensor, hinge)
        sync = capacitive_sleeve_sync(data_dir, trial, side, cfg.source, rows=len(cs)) if cfg.sync else None
        if sync is not None and sync.applied_rows != sync.lag_rows:
            log.warning(
                "%s %s: the sleeve board matches the shank only at %.2f (at least %.2f): rows kept as the file "
                "pairs them",
                trial,
                side,
                sync.correlation,
                SYNC_MIN_CORRELATION,
            )
        cs, angle = synchronised(cs, angle, sync.applied_rows if sync else 0)
        x = resample_uniform(cs, rate, cfg.rate_hz)
        y = resample_uniform(angle[:, None], sensors[thigh].rate_hz, cfg.rate_hz)[:, 0]
        m = min(len(x), len(y))
        lag_s = sync.applied_rows / sync.rate_hz if sync else 0.0
        out[trial] = LegRecording(trial, side, x[:m].astype(np.float32), y[:m].astype(np.float32), lag_s)
    return out


def synchronised(sleeve: np.ndarray, reference: np.ndarray, lag_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows of both that were read at the same moment, given that the sleeve's row t + ``lag_rows`` was read
    at the reference's row t (``service.core.recordings.SleeveSync``)."""
    first = max(0, -lag_rows)
    last = min(len(reference), len(sleeve) - lag_rows)
    return sleeve[first + lag_rows : last + lag_rows], reference[first:last]


def _clip(rec: LegRecording, window: int, part: str) -> FlexClip:
    return FlexClip(
        f"{rec.trial}/{rec.side}{part}",
        "capacitive_sub01",
        "capacitive_Sub01",
        "walk_stiffknee" if "Stiff" in rec.trial else "walk",
        rec.flexion_deg[:, None, None],
        np.zeros((len(rec.readings), 0), np.float32),
        window - 1,  # the first window - 1 samples only fill the calibration window: no answer there
    )


def leg_sets(recs: list[LegRecording], window: int, val_share: float | None) -> dict[str, WindowSet]:
    """Window sets over the legs: ``train`` and ``val`` (the last ``val_share`` of each leg), or ``test``."""
    parts: dict[str, list[tuple[FlexClip, np.ndarray]]] = {}
    for rec in recs:
        if val_share is None:
            parts.setdefault("test", []).append((_clip(rec, window, ""), rec.readings))
            continue
        cut = int(len(rec.readings) * (1.0 - val_share))
        head = LegRecording(rec.trial, rec.side, rec.readings[:cut], rec.flexion_deg[:cut])
        tail = LegRecording(rec.trial, rec.side, rec.readings[cut:], rec.flexion_deg[cut:])
        parts.setdefault("train", []).append((_clip(head, window, ""), head.readings))
        parts.setdefault("val", []).append((_clip(tail, window, " (last part)"), tail.readings))
    out = {}
    for name, items in parts.items():
        readings = {c.path: r for c, r in items}
        out[name] = window_set([c for c, _ in items], 1, 0, window, counts_fn=lambda c, k, r=readings: r[c.path])
    return out


def run_capacitive_experiment(
    cfg: CapacitiveConfig,
    data_dir: Path,
    ship_to: Path | None = None,
    version: str | None = None,
    held_out_runs: Sequence[str] = (),
) -> dict:
    """Train one network on the training trials' sleeves, report the held-out trial (if any), log, register, ship.
    ``held_out_runs``: runs of the same recipe that held a trial out, whose figures the manifest carries
    (``held_out_evaluation``); for a model that trains on every trial."""
    trials = read_trials(cfg, data_dir)
    W = cfg.model.window
    training = [r for t in cfg.training_trials for r in trials[t]]
    if cfg.held_out_leg:
        sets = leg_sets([r for r in training if r.side != cfg.held_out_leg], W, cfg.val_share)
        sets |= leg_sets([r for r in training if r.side == cfg.held_out_leg], W, None)
    else:
        sets = leg_sets(training, W, cfg.val_share)
    if cfg.test_trial:
        sets |= leg_sets(trials[cfg.test_trial], W, None)
    held_out = f"the {cfg.held_out_leg} leg's sleeve" if cfg.held_out_leg else cfg.test_trial
    recipe_figures = [held_out_evaluation(run_id, cfg) for run_id in held_out_runs]
    trained_on = " and ".join(cfg.training_trials)
    setup_tracking(cfg.tracking.experiment)
    with mlflow.start_run(run_name=cfg.name) as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.set_tags(
            {
                "task": "flex_pose",
                "variant": cfg.variant,
                "mlflow.note.content": f"{cfg.variant} on real capacitive sleeves ({cfg.source}): trained on "
                f"{trained_on}, "
                + (f"tested on {held_out}" if held_out else "nothing held out")
                + ", knee flexion of both legs.",
            }
        )
        mlflow.log_params({k: str(v) for k, v in flatten(cfg.model_dump()).items()})
        lags = {f"{r.trial}/{r.side}": round(r.sleeve_lag_s, 3) for recs in trials.values() for r in recs}
        mlflow.log_params({f"sleeve_lag_s.{k}": v for k, v in lags.items()})
        log_datasets(sleeve_tables(cfg, sets), str(data_dir), "flex-capacitive")
        result = train_flex(
            cfg,
            sets["train"],
            sets["val"],
            on_epoch=lambda e, row: mlflow.log_metrics(
                {"train_loss": row["train_loss"], "val_mae_deg_epoch": row["val_mae_deg"]}, step=e
            ),
        )
        net, lat = result.net, result.net.latency_samples
        predict = torch_predictor(net)
        val = clip_metrics(predict, sets["val"], 0, lat, cfg.joints, [])
        metrics = {"val_mae_deg": val["mae_deg"], "train_wall_time_s": result.wall_s, "best_epoch": result.best_epoch}
        # the part each scored trial reads (here the validation parts: the last val_share of each trial and leg)
        scored = "test" if held_out else "val"
        traces = _per_clip(predict, sets[scored], lat)
        if held_out:
            test = clip_metrics(predict, sets["test"], 0, lat, cfg.joints, [])
            mean = mean_pose_predictor(sets["train"].angles.mean(axis=0))
            baseline = clip_metrics(mean, sets["test"], 0, lat, cfg.joints, [])
            metrics |= {
                "test_mae_deg": test["mae_deg"],
                "test_jitter_deg_s3": test["jitter_deg_s3"],
                "test_mean_flexion_mae_deg": baseline["mae_deg"],
            } | {_part_metric("test", part): float(np.abs(p - t).mean()) for part, (p, t) in traces.items()}
            if not cfg.held_out_leg:
                metrics |= beyond_training_range(traces, sets["train"])
        else:
            metrics |= {_part_metric("val", part): float(np.abs(p - t).mean()) for part, (p, t) in traces.items()}
        mlflow.log_metrics(metrics)
        mlflow.set_tag("stopped", result.stopped)
        label_run(MlflowClient(), run.info.run_id)  # its name and description in the UI
        mlflow.log_artifact(str(flex_learning_curve_png(result.history, tmp / "learning_curve.png", cfg.name)), "plots")
        n = min(len(p) for p, _ in traces.values())
        n = min(n, int(20 * cfg.rate_hz))
        mlflow.log_artifact(
            str(
                traces_png(
                    np.arange(n) / cfg.rate_hz,
                    {f"{leg} knee": t[:n] for leg, (_, t) in traces.items()},
                    {f"{leg} knee": p[:n] for leg, (p, _) in traces.items()},
                    tmp / f"trace_{scored}.png",
                    f"{cfg.name}: held-out {held_out}" if held_out else f"{cfg.name}: validation parts",
                )
            ),
            "plots",
        )
        summary = {"variant": cfg.variant, "run_id": run.info.run_id, "metrics": metrics, "stopped": result.stopped}
        (tmp / "summary.json").write_text(json.dumps(summary, indent=1))
        mlflow.log_artifact(str(tmp / "summary.json"), "evaluation")

        onnx_path = export_flex_onnx(net, tmp / "model.onnx")
        x, _ = sets[scored].batch(np.zeros(8, int), sets[scored].ends[:: len(sets[scored].ends) // 8][:8], 1)
        golden = {"counts": x.astype(np.float32), "expected": predict(x).astype(np.float32)}
        parity = onnx_parity(onnx_path, golden)
        if parity > 1e-3:
            raise RuntimeError(f"onnxruntime differs from torch by {parity:.2e} deg on the golden input")
        np.savez(tmp / "golden.npz", **golden)
        version = version or "0.0.0+" + run.info.run_id[:8]
        evaluations = recipe_figures
        if held_out:
            scored_data = (
                f"{cfg.source} {trained_on}, the {cfg.held_out_leg} leg (trained on the other leg's sleeve only)"
                if cfg.held_out_leg
                else f"{cfg.source} {cfg.test_trial}, both legs (trained on {trained_on} only)"
            )
            evaluations = [
                Evaluation(
                    name=f"held-out leg {cfg.held_out_leg}" if cfg.held_out_leg else f"held-out trial {cfg.test_trial}",
                    command=f"python -m training.cli evaluate-capacitive --model onnx_models/{cfg.name}/{version}",
                    data=f"{scored_data}; reference: the functional knee hinge angle between the Xsens femur and "
                    "tibia sensors",
                    metrics={k: round(v, 4) for k, v in metrics.items() if k.startswith("test_")},
                ),
                *evaluations,
            ]
        manifest = build_flex_manifest(
            cfg,
            net,
            version,
            sha256_file(onnx_path),
            {
                "sources": [cfg.source],
                "train_trials": cfg.training_trials,
                "test_trial": cfg.test_trial,
                "held_out_leg": cfg.held_out_leg,
                "subjects": ["Sub01"],
                "sleeve_lag_s": lags if cfg.sync else None,  # undone before training (capacitive_sleeve_sync)
                "licence": "capacitive sensing dataset of Pearl et al. 2022 (see the data's LICENSE)",
                "train_wall_time_s": round(result.wall_s, 1),
                "best_epoch": result.best_epoch,
                "stopped": result.stopped,
            }
            | ({"member_best_epochs": result.member_best_epochs} if cfg.train.members > 1 else {}),
            evaluations,
            {"run_id": run.info.run_id, "experiment_id": run.info.experiment_id},
            channels=list(CAPACITIVE_CHANNELS),
            units={c: CHANNEL_UNITS for c in CAPACITIVE_CHANNELS},
            value_range=None,
            sample_rate_hz=cfg.rate_hz,
            joints=["Knee"],
            components=["flexion"],
            simulated_sensor="",
            angle_convention=HINGE_CONVENTION,
            readout_check=ReadoutCheckSpec(reference_s=CAPACITIVE_REFERENCE_S, max_deviation=CAPACITIVE_FAILURE),
        )
        proto = onnx.load(str(onnx_path))
        info = log_onnx_model(proto, golden, manifest, input_key="counts")
        registered = register_model(info.model_uri, cfg.registered_model)
        # the reference's version too: a validation figure on the repaired left femur rows is not comparable with one
        # on the spiky reference before (docs/flex.md)
        digest = f"{cfg.source}|{'+'.join(cfg.training_trials)}|val{cfg.val_share}|{cfg.rate_hz}|{REFERENCE_VERSION}"
        maybe_promote(cfg.registered_model, registered.version, "val_mae_deg", val["mae_deg"], False, digest)
        manifest = with_registry(manifest, info, registered)
        if ship_to is not None:
            shipped = ship_files(ship_to, manifest, onnx_path, tmp / "golden.npz")
            served = load_model(shipped, 2)
            a = clip_metrics(served.run, sets[scored], 0, lat, cfg.joints, [])["mae_deg"]
            b = metrics[f"{scored}_mae_deg"]
            if abs(a - b) > 0.02:
                raise RuntimeError(f"the shipped model scores {a:.3f}° where torch scored {b:.3f}°")
            summary["shipped"] = str(shipped)
        return summary


def held_out_evaluation(run_id: str, cfg: CapacitiveConfig) -> Evaluation:
    """The held-out-trial figures of a ``capacitive-train`` run of the same recipe (network and inputs) as
    ``cfg``, for the manifest of a model trained on every trial."""
    run = mlflow.get_run(local_run_id(run_id))  # the id a manifest names may be restored
    params, metrics = run.data.params, run.data.metrics
    recipe = {
        k: str(v)
        for k, v in flatten(cfg.model_dump()).items()
        if k.startswith("model.") or k in ("sync", "train.members")
    }
    # parameters added since a run was logged (absent there) had their default then; the sleeves were not
    # synchronised before ``sync`` was, and every run was one network before ``train.members``
    logged = {"sync": "False", "train.members": "1"} | dict(params)
    differs = {k: (logged[k], v) for k, v in recipe.items() if k in logged and logged[k] != v}
    if "model.kind" not in params or differs:
        raise ValueError(f"run {run_id} is not this recipe: (its, ours) {differs}")
    if "test_mae_deg" not in metrics:
        raise ValueError(f"run {run_id} held nothing out")
    trained, held_out = params.get("train_trial"), params.get("test_trial")
    also = "" if params.get("also_train", "[]") == "[]" else f" and {params['also_train']}"
    leg = params.get("held_out_leg", "None")
    if leg != "None":  # a sleeve it never saw, over the trials it trained on
        name, scored = f"recipe held out on the {leg} leg's sleeve", f"{trained}{also}, the {leg} leg"
        overrides = f"-s also_train={params['also_train']} -s test_trial=null -s held_out_leg={leg}"
        why = "not this file: it trained on that sleeve too"
    else:
        name, scored = f"recipe held out on {held_out}", f"{held_out}, both legs"
        overrides = f"-s train_trial={trained} -s test_trial={held_out}"
        why = f"trained on {trained}{also} only; not this file: it trained on that trial too"
    return Evaluation(
        name=name,
        command=f"python -m training.cli capacitive-train <this model's config> {overrides} (MLflow run {run_id}, "
        f"{run.info.run_name})",
        data=f"{params.get('source')} {scored}, scored by the same recipe ({why}); reference: the functional knee "
        "hinge angle between the Xsens femur and tibia sensors",
        metrics={k: round(v, 4) for k, v in metrics.items() if k.startswith("test_")},
    )


def _part_metric(prefix: str, part: str) -> str:
    """``test``, ``Left`` → ``test_left_knee_mae_deg``; ``val``, ``CSBaseline/Left (last part)`` →
    ``val_csbaseline_left_mae_deg``."""
    if "/" not in part:
        return f"{prefix}_{part.lower()}_knee_mae_deg"
    return f"{prefix}_{part.removesuffix(' (last part)').replace('/', '_').lower()}_mae_deg"


def sleeve_tables(cfg: CapacitiveConfig, sets: dict[str, WindowSet]) -> dict[str, pd.DataFrame]:
    """The recordings of each part (train, validation, test) as MLflow dataset tables."""
    out = {}
    for context, key in (("train", "train"), ("validation", "val"), ("test", "test")):
        if key not in sets:
            continue
        ws = sets[key]
        out[context] = pd.DataFrame(
            {
                "recording": [f"{cfg.source}/{c.path}" for c in ws.clips],
                "activity": [c.activity for c in ws.clips],
                "samples": [len(c.angles) for c in ws.clips],
                "rate_hz": [cfg.rate_hz] * len(ws.clips),
            }
        )
    return out


def beyond_training_range(traces: dict[str, tuple[np.ndarray, np.ndarray]], training: WindowSet) -> dict[str, float]:
    """How a held-out trial's error splits at the training range: per leg, the samples whose reference flexion
    lies above the most that leg bent in the training part, their share and mean absolute error, and the error of
    the rest. A network trained on a stiff-knee gait has never seen the baseline gait's fuller flexion; this says
    how much of its held-out error is that extrapolation (docs/flex.md)."""
    within, beyond = [], []
    for leg, (p, t) in traces.items():
        side = leg.split("/")[-1]
        top = max(float(c.angles[c.pad :].max()) for c in training.clips if c.path.split("/")[-1].startswith(side))
        out = t > top
        beyond.append(np.abs(p - t)[out])
        within.append(np.abs(p - t)[~out])
    b, w = np.concatenate(beyond), np.concatenate(within)
    out = {"test_beyond_training_share": float(len(b) / (len(b) + len(w)))}
    for key, errors in (("test_beyond_training_mae_deg", b), ("test_within_training_mae_deg", w)):
        if len(errors):  # an empty part has no mean (and a manifest no NaN)
            out[key] = float(errors.mean())
    return out


def _per_clip(predict, ws: WindowSet, latency: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Leg ("Left", "Right"), or trial and leg where several trials are scored, → predicted and reference knee
    flexion over every answered sample."""
    out = {}
    several = len({c.path.split("/")[0] for c in ws.clips}) > 1
    for i, c in enumerate(ws.clips):
        ends = ws.ends[ws.clip_of_end == i]
        x, _ = ws.batch(np.zeros(len(ends), int), ends, 1)
        out[c.path if several else c.path.split("/")[-1]] = (
            predict(x)[:, 0, 0],
            ws.angles[ends - 1 - latency][:, 0, 0],
        )
    return out


def evaluate_capacitive(
    loaded, data_dir: Path, trial: str, hinge_trial: str | None = None, source: str = "capacitive_sub01"
) -> dict:
    """A shipped capacitive model (through onnxruntime) on one trial of a capacitive-study subject (``source``: the
    folder under ``imu_real``, e.g. another subject's ``capacitive_sub02`` in the same layout), per leg and both, and
    whether the model trained on that trial (then the figure is not a held-out one). ``hinge_trial``: the trial of
    the same session the knee hinge reference is fitted on (default: ``trial`` itself; only its orientations are
    read). A leg that cannot be scored is left out with the reason (``skipped_legs``, ``read_trials``); where
    neither can, ``UnscorableSubject`` says why."""
    hinge_trial = hinge_trial or trial
    cfg = CapacitiveConfig(
        name=loaded.manifest.name,
        source=source,
        train_trial=hinge_trial,
        test_trial=None if trial == hinge_trial else trial,
        rate_hz=loaded.manifest.sample_rate_hz,
    )
    skipped: dict[str, str] = {}
    trials = read_trials(cfg, data_dir, skipped, {trial})  # the hinge trial's orientations, not its sleeves
    window = loaded.manifest.window_samples
    legs_read = []
    for rec in trials[trial]:
        if len(rec.readings) < window:  # the file ends, or the read-out fails, within the first window
            skipped[rec.side] = (
                f"only {len(rec.readings) / cfg.rate_hz:.1f} s of readings in step with the Xsens sensors: the "
                f"model answers after its {window / cfg.rate_hz:.1f} s window"
            )
        else:
            legs_read.append(rec)
    if not legs_read:
        raise UnscorableSubject(f"{source}/{trial}: no leg can be scored: {skipped}")
    test = leg_sets(legs_read, window, None)["test"]
    lat = loaded.manifest.flex.latency_samples
    legs = {leg: float(np.abs(p - t).mean()) for leg, (p, t) in _per_clip(loaded.run, test, lat).items()}
    both = clip_metrics(loaded.run, test, 0, lat, ["Knee"], [])
    data = loaded.manifest.training_data
    trained = data.get("train_trials") or [data.get("train_trial")]
    return {
        "source": source,
        "trial": trial,
        "hinge_fitted_on": hinge_trial,
        "trained_on_this_trial": source in data.get("sources", []) and trial in trained,
        "mae_deg": both["mae_deg"],
        "jitter_deg_s3": both["jitter_deg_s3"],
        "per_leg_mae_deg": legs,
        "skipped_legs": skipped,  # a leg that could not be scored, with the reason
    }
