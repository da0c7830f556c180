"""One pose experiment as one MLflow run: data, training, evaluation on validation and held-out subjects, the
mean-pose baseline, plots, ONNX export with parity, the logged model, the registry, and optionally shipping.

The validation subjects decide (the epoch; the ``champion`` alias between versions); the held-out subjects are
reported and never used to choose.
"""

from __future__ import annotations

import json
import logging
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import mlflow
import numpy as np
import onnx
import pandas as pd
import torch
from mlflow.tracking import MlflowClient

from service.core.body import BODY_SEGMENTS, PARENT_INDEX, Body, clip_body
from service.core.calibration import features_per_frame
from service.core.manifest import Evaluation, read_manifest, sha256_file
from service.inference.pose import PoseModel, assembly, hinge_joints, whole_body
from service.inference.registry import load_model
from training.config import flatten
from training.data.catalog import mocap_entries
from training.plots import (
    data_selection_png,
    placement_png,
    pose_learning_curve_png,
    pose_segment_errors_png,
    skeleton_snapshots_png,
)
from training.pose.config import PoseConfig, is_streaming, served_chunks
from training.pose.data import (
    MODEL_RATE_HZ,
    OWN_SOURCE,
    MotionClip,
    build_motions,
    dataset_digest,
    held_out_split,
    pose_evaluation_digest,
    seen_split,
    shipped_split_and_frames,
    trains_on_bandai,
)
from training.pose.evaluate import (
    ClipResult,
    draws_mean,
    evaluate_clips,
    flat_metrics,
    joint_flexion_metrics,
    mean_pose_predictor,
    per_joint_mean,
    per_segment_mean,
    summarise,
)
from training.pose.export import build_pose_manifest, export_pose_onnx, golden_pair, onnx_parity
from training.pose.models import Mirror, PoseEnsemble
from training.pose.placement import CANDIDATES, search_placement
from training.pose.selection import Selection, select, selected_clips
from training.pose.simulate import Session
from training.pose.train import PoseTrainResult, build_net, fixed_sessions, torch_predictor, train_pose
from training.pose.user_mocap import user_clips
from training.pose.warmstart import warm_start_from_shipped
from training.run_labels import label_run
from training.shipping import ship_files, with_registry
from training.tracking import log_onnx_model, maybe_promote, register_model, setup_tracking

log = logging.getLogger(__name__)

VAL_SEED, TEST_SEED, BASELINE_SEED = 1, 2, 3
SELECTION_METRIC = "val_angle_unsensed_deg"
HELD_OUT = "held-out subjects (simulated sensors)"
OWN_HELD_OUT = "own held-out people (simulated sensors)"


@dataclass(frozen=True)
class PoseData:
    train: list[MotionClip]
    val: list[MotionClip]
    test: list[MotionClip]
    selection: Selection | None = None  # with ``data.selection``: how ``train`` was chosen
    # with ``data.seen_share``: training clips held back (Zheng et al. 2021 §7's protocol)
    seen: list[MotionClip] = field(default_factory=list)
    # with ``data.own.test_people``: the user's held-out people, scored apart from the data directory's
    own_test: list[MotionClip] = field(default_factory=list)


def load_pose_data(cfg: PoseConfig, data_dir: Path, cache_dir: Path, workers: int = 2) -> PoseData:
    d = cfg.data
    entries = mocap_entries(data_dir, sources=d.sources)
    clips = build_motions(data_dir, entries, cache_dir, workers, limb_twist=d.limb_twist, trunk_axes=d.trunk_axes)
    train, val, test = held_out_split(clips, d.test_subjects, d.val_subjects, d.test_activities_of_unlabelled)
    log.info("pose split: %d train, %d validation, %d test clips", len(train), len(val), len(test))
    seen: list[MotionClip] = []
    if d.seen_share > 0:
        train, seen = seen_split(train, d.seen_share)
        log.info("seen people: %d training clips held back", len(seen))
    own_test: list[MotionClip] = []
    if d.own is not None:
        own_train, own_val, own_test = own_clips(cfg, data_dir, cache_dir)
        log.info(
            "own motion capture: %d train, %d validation, %d test clips", len(own_train), len(own_val), len(own_test)
        )
        train, val = with_own(train, val, own_train, own_val, d.own.share)
    if d.selection is None:
        return PoseData(train, val, test, seen=seen, own_test=own_test)
    s = d.selection
    is_ref = [
        c.activity in s.reference_activities and (s.reference_sources is None or c.source in s.reference_sources)
        for c in train
    ]
    reference = [c for c, r in zip(train, is_ref, strict=True) if r]
    rest = [c for c, r in zip(train, is_ref, strict=True) if not r]
    if not reference:
        raise ValueError(
            f"no training clip is a reference: activities {s.reference_activities}, sources {s.reference_sources}"
        )
    unit = max(1, round(s.unit_s * MODEL_RATE_HZ))
    selection = select(rest, reference, unit, s.eta0, cfg.train.sequence_frames, s.weights, s.optimise)
    # Zheng et al. 2021 §5.1: the selected data and the reference data are trained on
    return PoseData(reference + selected_clips(rest, selection.runs), val, test, selection, seen, own_test)


def with_own(
    train: list[MotionClip],
    val: list[MotionClip],
    own_train: list[MotionClip],
    own_val: list[MotionClip],
    share: float,
) -> tuple[list[MotionClip], list[MotionClip]]:
    """The training and validation clips with the user's own: their training clips beside the data directory's
    (instead of them with ``share`` 1.0, as they would draw nothing), their validation people instead of its
    validation subjects where any are named (a model for the user's people is judged on them)."""
    return (own_train if share == 1.0 else train + own_train), (own_val or val)


def own_clips(
    cfg: PoseConfig, data_dir: Path, cache_dir: Path
) -> tuple[list[MotionClip], list[MotionClip], list[MotionClip]]:
    """``data.own``'s clips as (train, validation, test) by their first-level folders (``PoseOwnDataConfig``), on
    the canonical body in the config's segment frames: a skeleton of one of the data directory's rigs gets that
    rig's frames, any other frames fitted on its own walks (``user_clips``). A file that cannot be read is left out
    with its reason; a folder named for validation or test that holds none raises."""
    own = cfg.data.own
    assert own is not None
    root = Path(own.path)
    if not root.is_dir():
        raise ValueError(f"data.own.path {str(root)!r} is not a folder")
    people = sorted(p for p in root.iterdir() if p.is_dir())
    if not people:
        raise ValueError(f"data.own.path {str(root)!r} holds no folders: put each person's BVH files in one")
    loose = sorted(p.name for p in root.iterdir() if p.is_file() and p.name.endswith((".bvh", ".bvh.gz")))
    if loose:
        log.warning(
            "data.own: %d BVH files lie in no person's folder of %s and are left out: %s", len(loose), root, loose
        )
    names = [p.name for p in people]
    missing = sorted(set(own.val_people + own.test_people) - set(names))
    if missing:
        raise ValueError(f"data.own names {missing}, which are not folders of {str(root)!r} (it has {names})")
    mapping = Path(own.mapping) if own.mapping else None
    clips = user_clips(people, mapping, cfg.data.limb_twist, data_dir, cache_dir, trunk_axes=cfg.data.trunk_axes)
    parts: dict[str, list[MotionClip]] = {"train": [], "val": [], "test": []}
    for c in clips:
        inner = Path(c.path).relative_to(root).parts
        person = inner[0]
        activity = inner[-2] if len(inner) > 2 else "unlabelled"
        part = "val" if person in own.val_people else "test" if person in own.test_people else "train"
        parts[part].append(replace(c, source=OWN_SOURCE, subject=person, activity=activity))
    for part, folders in (("val", own.val_people), ("test", own.test_people)):
        empty = sorted(set(folders) - {c.subject for c in parts[part]})
        if empty:
            raise ValueError(f"data.own: {empty} hold no clip that could be read")
    if not parts["train"]:
        raise ValueError(f"data.own: no clip of {str(root)!r} is left to train on (every folder validates or tests)")
    return parts["train"], parts["val"], parts["test"]


def carries_bandai(cfg: PoseConfig, clips: list[MotionClip]) -> bool:
    """Whether a model trained on ``clips`` carries Bandai-Namco's CC BY-NC 4.0 licence: its own clips, or the
    shipped file it starts from (``train.init_from_onnx``: a fine-tune of a Bandai-trained network is one too)."""
    if trains_on_bandai(clips):
        return True
    start = cfg.train.init_from_onnx
    return bool(start and read_manifest(Path(start) / "manifest.json").training_data.get("bandai_namco"))


def own_summary(cfg: PoseConfig, data: PoseData) -> dict:
    """What a model trained on ``data.own`` says of it in its manifest."""
    own = cfg.data.own
    assert own is not None
    trained = [c for c in data.train if c.source == OWN_SOURCE]
    return {
        "train_people": sorted({c.subject for c in trained}),
        "train_clips": len(trained),
        "train_frames_60hz": int(sum(c.motion.n_frames for c in trained)),
        "share_of_draws": own.share,
        "validation_people": own.val_people,
        "test_people": own.test_people,
        "mapping": Path(own.mapping).name if own.mapping else None,
    }


def default_body(clips: list[MotionClip]) -> Body:
    """The served default skeleton: the median bone vectors of the CMU training clips (real people's proportions;
    Bandai-Namco shares one retargeted rig); of all training clips where none is CMU's (a model trained on one's
    own clips alone, ``data.own.share`` 1.0: its people's body)."""
    cmu = [c for c in clips if c.source.startswith("cmu")] or clips
    return Body(np.median(np.stack([clip_body(c.motion).offsets_m for c in cmu]), axis=0))


def _clip_table(clips: list[MotionClip]) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "path": [c.path for c in clips],
            "source": [c.source for c in clips],
            "subject": [c.group for c in clips],
            "activity": [c.activity for c in clips],
            "frames_60hz": [c.motion.n_frames for c in clips],
            "digest": [c.digest for c in clips],
        }
    )


def log_datasets(data: PoseData, data_dir: Path) -> None:
    """The run's training, validation and held-out clips as MLflow datasets (path, source, subject, activity, frames,
    digest per clip)."""
    for context, clips in (("train", data.train), ("validation", data.val), ("test", data.test)):
        ds = mlflow.data.from_pandas(
            _clip_table(clips), source=str(data_dir), name=f"pose-{context}-{dataset_digest(clips)}"
        )
        mlflow.log_input(ds, context=context)


def _snapshot(net_predict, clip: MotionClip, session: Session, cfg: PoseConfig, path: Path) -> Path:
    sensors = [BODY_SEGMENTS.index(s) for s in cfg.sensors]
    outputs = [BODY_SEGMENTS.index(s) for s in cfg.outputs]
    hinges = hinge_joints(cfg.data.limb_twist)
    R_pred = whole_body(session.R_world_sensor_segment, net_predict(session.features), sensors, outputs, hinges=hinges)
    from scipy.spatial.transform import Rotation

    Rz = Rotation.from_rotvec([0.0, 0.0, session.heading_rad]).as_matrix()
    R_true = np.einsum("ij,tsjk->tsik", Rz, clip.motion.R_world_segment)
    body = clip_body(clip.motion)
    # into the pelvis's heading frame at each frame, so that the views are front and side
    yaw = np.arctan2(R_true[:, 0, 1, 0], R_true[:, 0, 0, 0])
    undo = Rotation.from_rotvec(np.outer(-yaw, [0.0, 0.0, 1.0])).as_matrix()
    p_t = np.einsum("tij,tsj->tsi", undo, body.forward(R_true))
    p_p = np.einsum("tij,tsj->tsi", undo, body.forward(R_pred))
    frames = [int(f) for f in np.linspace(0, clip.motion.n_frames - 1, 6)]
    return skeleton_snapshots_png(
        p_t, p_p, PARENT_INDEX, frames, path, f"{cfg.name}: {clip.path} (grey truth, blue model)"
    )


# What an ensemble's members may differ in from its config (their seed, what they are called and where they are
# tracked, how long they may run and on how many threads); every other parameter of the recipe must be the same.
MEMBER_FREEDOMS = (
    "name",
    "seed",
    "tracking.",
    "train.ensemble_of",
    "train.ensemble_mirror",
    "train.time_budget_s",
    "train.threads",
)


def assembled(cfg: PoseConfig) -> PoseTrainResult:
    """``train.ensemble_of``: the finished runs' networks (their logged checkpoints) averaged, not trained; each run
    must have ``cfg``'s recipe but for ``MEMBER_FREEDOMS`` (a run older than an option ran as its default does)."""
    assert cfg.train.ensemble_of is not None
    client, own = MlflowClient(), {k: str(v) for k, v in flatten(cfg.model_dump()).items()}
    default = {k: str(v) for k, v in flatten(PoseConfig(name=cfg.name).model_dump()).items()}
    members = []
    for run_id in cfg.train.ensemble_of:
        params = client.get_run(run_id).data.params
        if params.get("train.ensemble_of", "None") != "None":
            raise ValueError(f"run {run_id} is itself an ensemble; name its members")
        differ = sorted(
            k for k, v in own.items() if not k.startswith(MEMBER_FREEDOMS) and params.get(k, default.get(k)) != v
        )
        if differ:
            raise ValueError(f"run {run_id} is not of this recipe: {[(k, params.get(k), own[k]) for k in differ]}")
        path = mlflow.artifacts.download_artifacts(f"runs:/{run_id}/checkpoint/model_state.pt")
        net = build_net(cfg, features_per_frame(len(cfg.sensors)))
        net.load_state_dict(torch.load(path, weights_only=True))
        members.append(net.eval())
    mlflow.set_tag("ensemble_of", ",".join(cfg.train.ensemble_of))
    mirror = Mirror(cfg.sensors, cfg.outputs) if cfg.train.ensemble_mirror else None
    return PoseTrainResult(PoseEnsemble(members, mirror).eval(), stopped="assembled")


def _log_epoch(epoch: int, row: dict[str, float]) -> None:
    """One epoch's figures on the learning curves (a warm start's epoch 0 has only its validation angle)."""
    names = {
        "train_loss": "train_loss",
        # comparable across recipes with and without the joint-position term
        "train_rotation_loss": "train_rotation_loss",
        "val_angle_deg": "val_angle_deg_epoch",
        "lr": "lr",
    }
    mlflow.log_metrics({metric: row[key] for key, metric in names.items() if key in row}, step=epoch)


def _judging(data: PoseData, cfg: PoseConfig, val_sessions: list[Session]) -> list[Session]:
    """The validation sessions that choose the epoch: a model for one scenario is judged on that scenario's
    validation clips (its reference activities), where the validation subjects have any."""
    if data.selection is None:
        return val_sessions
    wanted = cfg.data.selection.reference_activities
    scenario = [s for c, s in zip(data.val, val_sessions, strict=True) if c.activity in wanted]
    return scenario or val_sessions


def _log_selection(sel: Selection, cfg: PoseConfig, tmp: Path) -> None:
    """How Zheng et al. 2021 §5 chose the training data: sizes, the score per deletion, frames per activity."""
    mlflow.log_metrics(
        {
            "selection_reference_frames": sel.reference_frames,
            "selection_similar_frames": sum(r.frames for r in sel.candidates),
            "selection_selected_frames": sum(r.frames for r in sel.runs),
            "selection_similar_runs": len(sel.candidates),
            "selection_selected_runs": len(sel.runs),
            "selection_deletions": len(sel.trace) - 1,
        }
    )
    for step, f in enumerate(sel.trace):
        mlflow.log_metric("selection_score", f, step=step)
    by_label = sel.frames_by_label()
    mlflow.log_dict({k: {"similar": v[0], "selected": v[1]} for k, v in by_label.items()}, "selection/frames.json")
    title = f"{cfg.name}: data selected for {', '.join(cfg.data.selection.reference_activities)}"
    mlflow.log_artifact(str(data_selection_png(sel.trace, by_label, tmp / "data_selection.png", title)), "plots")


def evaluation_record(
    name: str,
    command: str,
    data: str,
    summary: dict,
    intervals: dict[str, tuple[float, float]] | None = None,
    joints: dict[str, dict[str, float]] | None = None,
) -> Evaluation:
    """A manifest's evaluation from a summary; ``intervals`` (``clip_intervals``) add each motion type's 95 %
    interval of the mean segment-angle error (``test_walk_angle_all_deg_low`` / ``_high``; ``test_angle_all_…`` over
    every clip), ``joints`` (``per_joint_mean``) the hip, knee and ankle flexion errors (``joint_flexion_metrics``)."""
    metrics = {k: round(v, 4) for k, v in flat_metrics(summary, "test").items()}
    metrics |= {k: round(v, 4) for k, v in joint_flexion_metrics(joints or {}).items()}
    for key, (low, high) in (intervals or {}).items():
        stem = "test_angle_all_deg" if key == "all" else f"test_{key}_angle_all_deg"
        metrics |= {f"{stem}_low": round(low, 4), f"{stem}_high": round(high, 4)}
    return Evaluation(name=name, command=command, data=data, metrics=metrics)


def run_pose_experiment(
    cfg: PoseConfig,
    data_dir: Path,
    cache_dir: Path,
    ship_to: Path | None = None,
    version: str | None = None,
    workers: int = 2,
) -> dict:
    """Train, evaluate, export, log and register one pose model; ship it under ``ship_to/<name>/<version>``."""
    data = load_pose_data(cfg, data_dir, cache_dir, workers)
    val_sessions = fixed_sessions(data.val, cfg, VAL_SEED)
    test_sessions = fixed_sessions(data.test, cfg, TEST_SEED)
    setup_tracking(cfg.tracking.experiment)
    with mlflow.start_run(run_name=cfg.name) as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.set_tags(
            {
                "task": "imu_pose",
                "model_kind": cfg.model.kind,
                "mlflow.note.content": f"{cfg.model.kind} ({cfg.model.representation}) from {len(cfg.sensors)} IMUs "
                f"({', '.join(cfg.sensors)}) to {len(cfg.outputs)} segments; look-ahead {cfg.model.look_ahead} frames. "
                "Validation subjects choose, held-out subjects are reported.",
                "trains_on_bandai_namco": str(carries_bandai(cfg, data.train)),
            }
        )
        mlflow.log_params({k: str(v) for k, v in flatten(cfg.model_dump()).items()})
        log_datasets(data, data_dir)
        if data.selection is not None:
            _log_selection(data.selection, cfg, tmp)
        init_state = None
        if cfg.train.init_from_onnx:  # fine-tuning a shipped file (training.pose.warmstart)
            mlflow.set_tag("init_from_onnx", cfg.train.init_from_onnx)
            init_state = warm_start_from_shipped(
                Path(cfg.train.init_from_onnx), cfg, build_net(cfg, features_per_frame(len(cfg.sensors)))
            )
        result: PoseTrainResult = (
            assembled(cfg)
            if cfg.train.ensemble_of
            else train_pose(cfg, data.train, _judging(data, cfg, val_sessions), _log_epoch, init_state)
        )
        net = result.net
        mlflow.log_metrics(
            {"best_epoch": result.best_epoch, "train_wall_time_s": result.wall_s, "epochs_run": len(result.history)}
        )
        mlflow.set_tag("stopped", result.stopped)
        label_run(MlflowClient(), run.info.run_id)  # its name and description in the UI
        torch.save(net.state_dict(), tmp / "model_state.pt")
        mlflow.log_artifact(str(tmp / "model_state.pt"), "checkpoint")
        if result.history:  # an assembled ensemble has no epochs
            curve = pose_learning_curve_png(result.history, tmp / "learning_curve.png", cfg.name)
            mlflow.log_artifact(str(curve), "plots")

        predict = torch_predictor(net, served_chunks(cfg))  # as the service runs it
        hinges = hinge_joints(cfg.data.limb_twist)  # as the service answers the shipped file
        val_results = evaluate_clips(predict, data.val, val_sessions, cfg.sensors, cfg.outputs, hinges=hinges)
        val_summary = summarise(val_results)
        mlflow.log_metrics(flat_metrics(val_summary, "val"))
        test_results = evaluate_clips(predict, data.test, test_sessions, cfg.sensors, cfg.outputs, hinges=hinges)
        test_summary = summarise(test_results)
        mlflow.log_metrics(flat_metrics(test_summary, "test"))
        # Vlutters 2016 §IV-F: the training set's mean pose, whatever the input
        baseline_sessions = fixed_sessions(data.train[:: max(1, len(data.train) // 400)], cfg, BASELINE_SEED)
        mean_pose = mean_pose_predictor(baseline_sessions)
        baseline = summarise(
            evaluate_clips(mean_pose, data.test, test_sessions, cfg.sensors, cfg.outputs, hinges=False)
        )
        mlflow.log_metrics(flat_metrics(baseline, "test_meanpose"))
        if data.seen:  # other takes of the training people: Zheng et al. 2021 §7's test, not ours
            seen_sessions = fixed_sessions(data.seen, cfg, TEST_SEED)
            seen = summarise(evaluate_clips(predict, data.seen, seen_sessions, cfg.sensors, cfg.outputs, hinges=hinges))
            mlflow.log_metrics(flat_metrics(seen, "seen"))
            for a, v in sorted(seen["activity"].items()):
                log.info("seen people, %s: %.2f° over all segments", a, v["angle_all_deg"])
        own_test_summary, own_joints = None, None
        if data.own_test:  # the user's held-out people, apart from the data directory's
            own_sessions = fixed_sessions(data.own_test, cfg, TEST_SEED)
            own_results = evaluate_clips(predict, data.own_test, own_sessions, cfg.sensors, cfg.outputs, hinges=hinges)
            own_test_summary, own_joints = summarise(own_results), per_joint_mean(own_results)
            mlflow.log_metrics(
                flat_metrics(own_test_summary, "test_own") | joint_flexion_metrics(own_joints, "test_own")
            )
        test_joints = per_joint_mean(test_results)
        mlflow.log_metrics(joint_flexion_metrics(test_joints))
        seg = per_segment_mean(test_results)
        mlflow.log_artifact(
            str(
                pose_segment_errors_png(
                    seg, cfg.sensors, tmp / "segment_errors_test.png", f"{cfg.name}: held-out subjects"
                )
            ),
            "plots",
        )
        walk = next((i for i, c in enumerate(data.test) if c.activity == "walk"), 0)
        mlflow.log_artifact(
            str(_snapshot(predict, data.test[walk], test_sessions[walk], cfg, tmp / "skeleton_walk.png")), "plots"
        )
        bb = next((i for i, c in enumerate(data.test) if c.activity == "basketball"), None)
        if bb is not None:
            mlflow.log_artifact(
                str(_snapshot(predict, data.test[bb], test_sessions[bb], cfg, tmp / "skeleton_basketball.png")), "plots"
            )
        (tmp / "summary_test.json").write_text(json.dumps({"model": test_summary, "mean_pose": baseline}, indent=1))
        mlflow.log_artifact(str(tmp / "summary_test.json"), "evaluation")

        onnx_path = export_pose_onnx(net, cfg, tmp / "model.onnx")
        golden = golden_pair(net, test_sessions[walk].features[:120], cfg)
        parity = onnx_parity(onnx_path, golden, cfg, net)
        mlflow.log_metric("onnx_parity_max_abs", parity)
        if parity > 1e-4:
            raise RuntimeError(f"onnxruntime differs from torch by {parity:.2e} on the golden input")
        np.savez(tmp / "golden.npz", **golden)
        body = default_body(data.train)
        version = version or "0.0.0+" + run.info.run_id[:8]
        training_data = {
            "sources": sorted({c.source for c in data.train}),
            "train_clips": len(data.train),
            "train_frames_60hz": int(sum(c.motion.n_frames for c in data.train)),
            "validation_subjects": cfg.data.val_subjects,
            "test_subjects": cfg.data.test_subjects,
            "test_unlabelled_clips": cfg.data.test_activities_of_unlabelled,
            # the segment frames it answers in (evaluate-pose scores in the same)
            "limb_twist": cfg.data.limb_twist,
            "trunk_axes": cfg.data.trunk_axes,
            "bandai_namco": carries_bandai(cfg, data.train),
            "train_wall_time_s": round(result.wall_s, 1),
            "best_epoch": result.best_epoch,
            "epochs_run": len(result.history),
            "stopped": result.stopped,
        }
        if cfg.train.ensemble_of:  # assembled from these runs' networks, not trained
            training_data["ensemble_of"] = cfg.train.ensemble_of
            if cfg.train.ensemble_mirror:
                training_data["ensemble_mirror"] = True
        if cfg.train.init_from_onnx:  # fine-tuned from a shipped file
            shipped_from = read_manifest(Path(cfg.train.init_from_onnx) / "manifest.json")
            training_data["init_from"] = f"{shipped_from.name} {shipped_from.version}"
        if cfg.data.own is not None:  # the user's own motion capture (folder names, not paths)
            training_data["own"] = own_summary(cfg, data)
        if cfg.data.seen_share:  # trained without a share of the training clips
            training_data["seen_share"] = cfg.data.seen_share
        if data.selection is not None:  # a model for one scenario (Zheng et al. 2021 §5)
            training_data["selected_for"] = {
                "reference_activities": cfg.data.selection.reference_activities,
                "reference_sources": cfg.data.selection.reference_sources,
                "reference_frames": data.selection.reference_frames,
                "selected_frames": sum(r.frames for r in data.selection.runs),
                "greedy_deletion": cfg.data.selection.optimise,
            }
        evaluation = evaluation_record(
            HELD_OUT,
            f"python -m training.cli evaluate-pose --model onnx_models/{cfg.name}/{version}",
            f"CMU subjects {', '.join(cfg.data.test_subjects)} and the li2018 run clips, never trained on or "
            "chosen by; one simulated session per clip (seed 2)",
            test_summary,
            joints=test_joints,
        )
        evaluations = [evaluation]
        if own_test_summary is not None:
            assert cfg.data.own is not None
            evaluations.append(
                evaluation_record(
                    OWN_HELD_OUT,
                    f"python -m training.cli evaluate-pose <data.own.path>/<folder> --model onnx_models/{cfg.name}/"
                    f"{version}",
                    f"the own folders {', '.join(cfg.data.own.test_people)} (data.own), never trained on or chosen "
                    "by; one simulated session per clip (seed 2)",
                    own_test_summary,
                    joints=own_joints,
                )
            )
        manifest = build_pose_manifest(
            cfg,
            net,
            version,
            sha256_file(onnx_path),
            body,
            training_data,
            evaluations,
            {"run_id": run.info.run_id, "experiment_id": run.info.experiment_id},
        )
        proto = onnx.load(str(onnx_path))
        info = log_onnx_model(proto, golden, manifest, input_key="features")
        mlflow.set_tag("model_uri", info.model_uri)
        registered = register_model(info.model_uri, cfg.registered_model)
        val_value = flat_metrics(val_summary, "val")["val_angle_unsensed_deg"]
        digest = pose_evaluation_digest(data.val, assembly(hinges, cfg.sensors, cfg.outputs))
        promoted = maybe_promote(cfg.registered_model, registered.version, SELECTION_METRIC, val_value, False, digest)
        mlflow.set_tag("promoted_to_champion", str(promoted))
        manifest = with_registry(manifest, info, registered)
        shipped = None
        if ship_to is not None:
            shipped = ship_files(ship_to, manifest, onnx_path, tmp / "golden.npz")
            served = PoseModel(load_model(shipped, 2))  # the served path: its numbers must equal torch's
            served_summary = summarise(
                evaluate_clips(served.predict, data.test, test_sessions, cfg.sensors, cfg.outputs, hinges=hinges)
            )
            a = served_summary["overall"]["all"]["angle_all_deg"]
            b = test_summary["overall"]["all"]["angle_all_deg"]
            if abs(a - b) > 0.05:
                raise RuntimeError(f"the shipped model scores {a:.3f}° where torch scored {b:.3f}°")
            log.info("shipped %s", shipped)
        return {
            "run_id": run.info.run_id,
            "test": test_summary,
            "test_own": own_test_summary,
            "mean_pose": baseline,
            "val": val_summary,
            "shipped": str(shipped) if shipped else None,
            "history": result.history,
            "streaming": is_streaming(cfg),
        }


def run_placement_search(
    cfg: PoseConfig, data_dir: Path, cache_dir: Path, n_sensors: int, frames: int, workers: int = 2
) -> dict:
    """Zheng et al. 2021 §6 on a config's training clips, as one MLflow run (experiment ``pose_placement``): the
    greedy placement of up to ``n_sensors`` sensors (``training.pose.placement``), Φ per step, the relevance
    between positions (JSON and a plot)."""
    data = load_pose_data(cfg, data_dir, cache_dir, workers)
    setup_tracking("pose_placement")
    with mlflow.start_run(run_name=f"placement_{cfg.name}") as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.set_tags(
            {
                "task": "imu_pose_placement",
                "mlflow.note.content": f"Zheng et al. 2021 §6 (mRMR over MIC) on the training clips of {cfg.name}: "
                f"where to put {n_sensors} sensors, the pelvis first.",
            }
        )
        mlflow.log_params(
            {
                "config": cfg.name,
                "n_sensors": n_sensors,
                "frames": frames,
                "seed": cfg.seed,
                "bandai_share": str(cfg.data.bandai_share),
                "candidates": ",".join(CANDIDATES),
            }
        )
        log_datasets(data, data_dir)
        placement, mic = search_placement(data.train, n_sensors, frames, cfg.data.bandai_share, cfg.seed)
        for k, (value, gain) in enumerate(zip(placement.phi, placement.gain, strict=True), start=1):
            mlflow.log_metric("phi", value, step=k)
            if gain is not None:
                mlflow.log_metric("mrmr_gain", gain, step=k)
        result = {
            "order": placement.order,
            "phi": placement.phi,
            "gain": placement.gain,
            "positions": list(placement.positions),
            "relevance": np.round(placement.relevance, 5).tolist(),
        }
        mlflow.log_dict(result, "placement/placement.json")
        np.save(tmp / "mic.npy", mic.astype(np.float32))
        mlflow.log_artifact(str(tmp / "mic.npy"), "placement")
        title = f"{cfg.name}: sensor placement (Zheng et al. 2021 §6), {frames} frames"
        png = placement_png(
            placement.relevance, placement.positions, placement.order, placement.phi, tmp / "placement.png", title
        )
        mlflow.log_artifact(str(png), "plots")
        return {"run_id": run.info.run_id, **result}


def results_table(results: list[ClipResult]) -> str:
    lines = [f"{'clip':60s} {'frames':>6s} {'all°':>6s} {'unsensed°':>9s} {'SIP°':>6s} {'JPE cm':>7s} {'jitter':>8s}"]
    for r in results:
        m = r.metrics
        lines.append(
            f"{r.path[-60:]:60s} {r.frames:6d} {m['angle_all_deg']:6.2f} {m['angle_unsensed_deg']:9.2f} "
            f"{m['sip_deg']:6.2f} {m['jpe_cm']:7.2f} {m['jitter_mps3']:8.1f}"
        )
    return "\n".join(lines)


def shipped_config(m) -> PoseConfig:
    """The config a shipped pose model's clips are built and scored with, from its manifest: its sensors, the split
    its run had and the segment frames it answers in ("rig" and "spine" where the manifest does not say)."""
    return PoseConfig(name=m.name, sensors=m.pose.sensors, data=shipped_split_and_frames(m.training_data))


def evaluate_shipped_pose(
    model_dir: Path, clips: list[MotionClip], seed: int = TEST_SEED, sessions: int = 1
) -> tuple[list[ClipResult], dict]:
    """A shipped ``imu_pose`` model through the served path (onnxruntime, ``PoseModel``) on simulated sessions of
    ``clips``, the same sensors, noise and seeds as training's evaluation (``TEST_SEED`` held out, ``VAL_SEED`` for
    the validation subjects). With ``sessions`` > 1 each clip is scored on that many sessions (the first the one
    training scored) and its figures are their mean (``draws_mean``)."""
    model = PoseModel(load_model(model_dir, 2))
    cfg = PoseConfig(name=model.name, sensors=model.spec.sensors, output_segments=model.spec.output_segments)
    draws = [
        evaluate_clips(model.predict, clips, drawn, cfg.sensors, cfg.outputs, hinges=model.hinge_joints)
        for drawn in (fixed_sessions(clips, cfg, seed, k) for k in range(sessions))
    ]
    results = draws_mean(draws)
    return results, summarise(results)
