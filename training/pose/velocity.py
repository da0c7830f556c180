"""A learned pelvis velocity for the body's translation (TransPose, Yi et al. 2021 §3.3).

TransPose moves the root by the supporting foot when its contact probability is high and otherwise by a root
velocity that a second network regresses from the sensors (its "fallback" branch, trained with an accumulated
loss over windows of 1, 3, 9 and 27 frames, §3.3). Here the same kind of network reads the pose model's own
features (``service.core.calibration.pose_features``: pelvis-relative, so independent of heading) and answers the
pelvis velocity in the pelvis frame; the service turns it into the world with the pelvis sensor's calibrated
orientation. A unidirectional LSTM seeing ``look_ahead`` frames ahead (TransPose's online mode), so that the same
network can serve a live stream.

``service.core.translation`` combines it with the supporting-foot rule; which combination is served was chosen on
the validation subjects (docs/pose.md, "Translation").
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import mlflow
import numpy as np
import onnx
import onnxruntime as ort
import torch
from mlflow.tracking import MlflowClient
from scipy.spatial.transform import Rotation
from torch import nn
from tqdm import tqdm

from service.core.body import BODY_SEGMENTS, BodyMotion, clip_body, feet_of
from service.core.calibration import ACC_SCALE_MPS2, FEATURE_VERSION, features_per_frame
from service.core.manifest import Evaluation, Manifest, TensorSpec, VelocitySpec, sha256_file
from service.core.translation import Feet, RootTracker
from service.inference.pose import PoseModel, assembly, whole_body
from service.inference.registry import load_model
from service.inference.velocity import VelocityModel, world_velocity
from training.config import flatten
from training.plots import translation_bars_png, velocity_learning_curve_png
from training.pose.config import PoseConfig, PoseVelocityConfig, load_pose_config
from training.pose.data import MotionClip
from training.pose.evaluate import pelvis_free_acc
from training.pose.export import PARITY_ATOL, export_stateful, pose_feature_fields, state_specs
from training.pose.simulate import Session
from training.pose.train import (
    BestEpoch,
    _crop,
    _length_buckets,
    clip_weights,
    feature_stats,
    fixed_sessions,
    session_of,
)

log = logging.getLogger(__name__)

ACCUMULATED_WINDOWS = (1, 3, 9, 27)  # TransPose 2021 §3.3: frames over which the velocity error is summed
SELECTION_METRIC = "val_trans_learned_1s_cm"  # the registry's: the chosen share's validation figure


class VelocityNet(nn.Module):
    """Features ``(B, T, F)`` → the pelvis velocity in the pelvis frame ``(B, T, 3)``, m/s; with look-ahead L the
    output at frame t answers frame t − L."""

    def __init__(self, n_features: int, hidden: int = 128, layers: int = 2, look_ahead: int = 5) -> None:
        super().__init__()
        self.hidden, self.layers, self.look_ahead = hidden, layers, look_ahead
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("std", torch.ones(n_features))
        self.embed = nn.Sequential(nn.Linear(n_features, hidden), nn.ReLU())
        self.rnn = nn.LSTM(hidden, hidden, layers, batch_first=True)
        self.out = nn.Linear(hidden, 3)

    def set_normalisation(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        self.mean.copy_(mean)
        self.std.copy_(torch.clamp(std, min=1e-3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.rnn(self.embed((x - self.mean) / self.std))
        return self.out(h)

    def step(
        self, x: torch.Tensor, h0: torch.Tensor, c0: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Streaming: frames ``(B, T, F)`` with the state ``(layers, B, hidden)`` in and out."""
        h, (h1, c1) = self.rnn(self.embed((x - self.mean) / self.std), (h0, c0))
        return self.out(h), h1, c1


def pelvis_velocity(motion: BodyMotion) -> np.ndarray:
    """The true pelvis velocity in the pelvis frame ``(T, 3)``, m/s (central differences of the hip centre)."""
    v_world = np.gradient(motion.origin_m[:, 0], 1.0 / motion.sample_rate_hz, axis=0)
    return np.einsum("tji,tj->ti", motion.R_world_segment[:, 0], v_world).astype(np.float32)


def predict_velocity(net: VelocityNet, features: np.ndarray) -> np.ndarray:
    """One clip's features ``(T, F)`` → its velocities ``(T, 3)``: the last frame repeated for the look-ahead, as a
    stream that ends does."""
    L = net.look_ahead
    x = np.concatenate([features, np.repeat(features[-1:], L, axis=0)]) if L else features
    with torch.no_grad():
        return net(torch.from_numpy(x[None].astype(np.float32)))[0, L:].numpy().astype(np.float64)


@dataclass
class VelocityTrainResult:
    net: VelocityNet
    best_val_cm: float = float("inf")  # the validation sessions' mean 1 s displacement error
    best_epoch: int = 0
    history: list[dict[str, float]] = field(default_factory=list)
    stopped: str = ""
    wall_s: float = 0.0


def _accumulated_loss(pred: torch.Tensor, target: torch.Tensor, R: torch.Tensor, mask: torch.Tensor, rate: float):
    """TransPose 2021 §3.3's accumulated loss: the squared error of the displacement over every window of n frames
    (sliding), summed over n, the per-frame errors turned into the world (``R``: world ← pelvis per frame) before
    they are added up."""
    e = torch.einsum("btij,btj->bti", R, (pred - target) * mask[..., None]) / rate
    c = torch.cumsum(torch.nn.functional.pad(e, (0, 0, 1, 0)), dim=1)
    loss = torch.zeros(())
    for n in ACCUMULATED_WINDOWS:
        if c.shape[1] > n:
            loss = loss + ((c[:, n:] - c[:, :-n]) ** 2).sum(-1).mean()
    return loss


def _batch(clips: list[MotionClip], sessions: list[Session], look_ahead: int):
    """Features (B, T, F), targets (B, T, 3) and the true pelvis frames (B, T, 3, 3), shifted by the look-ahead (the
    output at frame t answers frame t − L), and the mask of the frames judged; every sequence has the same length."""
    L = look_ahead
    x = torch.from_numpy(np.stack([s.features for s in sessions]).astype(np.float32))
    v = np.stack([pelvis_velocity(c.motion) for c in clips])
    R = np.stack([c.motion.R_world_segment[:, 0] for c in clips]).astype(np.float32)
    if L:
        v = np.concatenate([np.zeros_like(v[:, :L]), v[:, :-L]], axis=1)
        R = np.concatenate([np.repeat(R[:, :1], L, axis=1), R[:, :-L]], axis=1)
    mask = torch.ones(x.shape[:2])
    mask[:, :L] = 0.0
    return x, torch.from_numpy(v), torch.from_numpy(R), mask


def train_velocity(
    vcfg: PoseVelocityConfig,
    cfg: PoseConfig,
    train_clips: list[MotionClip],
    validation_cm: Callable[[VelocityNet], float],
    on_epoch: Callable[[int, dict[str, float]], None] | None = None,
) -> VelocityTrainResult:
    """The network of the best validation epoch (``validation_cm``: the validation subjects' mean horizontal
    displacement error over 1 s with the network's velocity alone). ``cfg``: the pose model's config (sensors,
    draws, sequence length)."""
    t0 = time.time()
    torch.manual_seed(vcfg.seed)
    torch.set_num_threads(cfg.train.threads)
    rng = np.random.default_rng(vcfg.seed)
    net = VelocityNet(features_per_frame(len(cfg.sensors)), vcfg.hidden, vcfg.layers, vcfg.look_ahead)
    net.set_normalisation(*feature_stats(train_clips, cfg, rng))
    opt = torch.optim.Adam(net.parameters(), lr=vcfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, vcfg.max_epochs, eta_min=vcfg.lr * cfg.train.lr_floor)
    weights = clip_weights(train_clips, cfg.data.activity_cap_frames, cfg.data.bandai_share)
    result = VelocityTrainResult(net)
    keeper = BestEpoch(net, vcfg.patience)
    W = cfg.train.sequence_frames
    for epoch in range(1, vcfg.max_epochs + 1):
        net.train()
        picks = rng.choice(len(train_clips), size=vcfg.sequences_per_epoch, p=weights)
        batches = _length_buckets(picks, [c.motion.n_frames for c in train_clips], cfg.train.batch_size, rng)
        losses = []
        bar = tqdm(batches, desc=f"{vcfg.name} epoch {epoch}", unit="batch", leave=False, mininterval=5.0)
        for batch in bar:
            n = min(W, min(train_clips[i].motion.n_frames for i in batch))
            clips = []
            for i in batch:
                start = int(rng.integers(0, train_clips[i].motion.n_frames - n + 1))
                clips.append(_crop(train_clips[i], start, start + n))
            sessions = [session_of(c, cfg, rng) for c in clips]
            x, v, R, mask = _batch(clips, sessions, vcfg.look_ahead)
            loss = _accumulated_loss(net(x), v, R, mask, clips[0].motion.sample_rate_hz)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            losses.append(loss.item())
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
        lr = opt.param_groups[0]["lr"]
        sched.step()
        net.eval()
        val = validation_cm(net)
        row = {"epoch": epoch, "train_loss": float(np.mean(losses)), "val_velocity_1s_cm": val, "lr": lr}
        row["wall_s"] = time.time() - t0
        result.history.append(row)
        log.info("%s epoch %d: loss %.4f, validation %.1f cm", vcfg.name, epoch, row["train_loss"], val)
        if on_epoch:
            on_epoch(epoch, row)
        result.stopped = keeper.record(epoch, val, time.time() - t0)
        if result.stopped:
            break
    else:
        result.stopped = f"max_epochs {vcfg.max_epochs} reached"
    keeper.restore()
    result.best_val_cm, result.best_epoch, result.wall_s = keeper.best, keeper.best_epoch, time.time() - t0
    return result


@dataclass(frozen=True)
class TranslationCase:
    """One clip's inputs to the translation: the pose model's answer as joint positions on the clip's own body,
    the simulated pelvis sensor's free acceleration and orientation, and the true pelvis, all in the session's
    world."""

    activity: str
    features: np.ndarray  # (T, F)
    joints_m: np.ndarray  # (T, S, 3) relative to the pelvis
    feet: Feet
    free_acc_mps2: np.ndarray  # (T, 3)
    R_world_pelvis: np.ndarray  # (T, 3, 3) the calibrated pelvis sensor's segment orientation
    root_true_m: np.ndarray  # (T, 3)
    rate_hz: float


def translation_cases(clips: list[MotionClip], sessions: list[Session], pose: PoseModel) -> list[TranslationCase]:
    sensor_index = [BODY_SEGMENTS.index(s) for s in pose.spec.sensors]
    output_index = [BODY_SEGMENTS.index(s) for s in pose.spec.output_segments]
    cases = []
    for clip, s in zip(clips, sessions, strict=True):
        body = clip_body(clip.motion)
        R = whole_body(
            s.R_world_sensor_segment, pose.predict(s.features), sensor_index, output_index, hinges=pose.hinge_joints
        )
        Rz = Rotation.from_rotvec([0.0, 0.0, s.heading_rad]).as_matrix()
        cases.append(
            TranslationCase(
                clip.activity,
                s.features,
                body.forward(R),
                feet_of(body),
                pelvis_free_acc(s),
                s.R_world_sensor_segment[:, 0],
                clip.motion.origin_m[:, 0] @ Rz.T,
                clip.motion.sample_rate_hz,
            )
        )
    return cases


def displacement_cm(case: TranslationCase, root_m: np.ndarray, seconds: float = 1.0, horizontal: bool = False):
    """The mean distance between the answer's and the truth's pelvis displacement over every window of
    ``seconds`` (``training.pose.evaluate.translation_metrics``' measure), and the number of windows."""
    n = int(round(seconds * case.rate_hz))
    if len(root_m) <= n:
        return float("nan"), 0
    d = (root_m[n:] - root_m[:-n]) - (case.root_true_m[n:] - case.root_true_m[:-n])
    return float(np.linalg.norm(d[:, :2] if horizontal else d, axis=-1).mean() * 100.0), len(d)


def integrated(case: TranslationCase, v_world: np.ndarray) -> np.ndarray:
    return np.concatenate([np.zeros((1, 3)), np.cumsum(v_world[1:], axis=0) / case.rate_hz])


def translation_errors(
    cases: list[TranslationCase], learned: list[np.ndarray] | None, shares: list[float], seconds: float = 1.0
) -> dict[str, dict[str, float]]:
    """Per activity (and ``all``), frame-weighted over the clips longer than the window: the rule (``rule``), the
    rule with the learned velocity (``learned`` per case, the world) at each share (``share_<s>``), the learned
    velocity alone (``velocity``, horizontal), a pelvis kept in place (``still``); centimetres over windows of
    ``seconds``."""
    rows: dict[str, list[tuple[int, dict[str, float]]]] = {}
    for k, case in enumerate(cases):
        rule = RootTracker(case.feet, case.rate_hz).advance(case.joints_m, case.free_acc_mps2)[0]
        errs = {"rule": displacement_cm(case, rule, seconds)}
        if learned is not None:
            for share in shares:
                tracker = RootTracker(case.feet, case.rate_hz, learned_share=share)
                root = tracker.advance(case.joints_m, case.free_acc_mps2, learned[k])[0]
                errs[f"share_{share:g}"] = displacement_cm(case, root, seconds)
            errs["velocity"] = displacement_cm(case, integrated(case, learned[k]), seconds, horizontal=True)
        errs["still"] = displacement_cm(case, np.zeros_like(case.root_true_m), seconds)
        if next(iter(errs.values()))[1]:  # weighted by frames, as ``training.pose.evaluate.summarise`` weighs
            row = {name: e for name, (e, _) in errs.items()}
            rows.setdefault(case.activity, []).append((len(case.root_true_m), row))
            rows.setdefault("all", []).append((len(case.root_true_m), row))
    return {
        activity: {name: float(np.average([r[name] for _, r in rs], weights=[w for w, _ in rs])) for name in rs[0][1]}
        | {"clips": float(len(rs))}
        for activity, rs in rows.items()
    }


def learned_velocities(predict: Callable[[np.ndarray], np.ndarray], cases: list[TranslationCase]) -> list[np.ndarray]:
    """Each case's learned velocity in its world (``predict``: features → the pelvis-frame velocity)."""
    return [world_velocity(c.R_world_pelvis, predict(c.features)) for c in cases]


class StreamingVelocityExport(nn.Module):
    """The graph the service runs: (features, h0, c0) → (velocity, h, c)."""

    def __init__(self, net: VelocityNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor, h0: torch.Tensor, c0: torch.Tensor):
        return self.net.step(x, h0, c0)


def export_velocity_onnx(net: VelocityNet, path: Path) -> Path:
    """TorchScript exporter (native ONNX LSTM ops), the batch and frames symbolic."""
    path.parent.mkdir(parents=True, exist_ok=True)
    x, h = torch.zeros(1, 16, int(net.mean.shape[0])), torch.zeros(net.layers, 1, net.hidden)
    return export_stateful(StreamingVelocityExport(net.eval()), x, h, "velocity", path)


def build_velocity_manifest(
    vcfg: PoseVelocityConfig,
    sensors: list[str],
    net: VelocityNet,
    version: str,
    sha256: str,
    share: float,
    chosen_with: str,
    training_data: dict,
    evaluations: list[Evaluation],
    mlflow_info: dict[str, str],
) -> Manifest:
    F = features_per_frame(len(sensors))
    state_in, state_out = state_specs(net.layers, net.hidden)
    return Manifest(
        name=vcfg.name,
        task="imu_pose_velocity",
        version=version,
        inputs=[
            TensorSpec(
                name="features",
                shape=["batch", "frames", F],
                dtype="float32",
                description=f"service.core.calibration.pose_features ({FEATURE_VERSION}) of the sensors in "
                "velocity.sensors order at 60 Hz, as the pose model of those sensors takes them",
            ),
            *state_in,
        ],
        outputs=[
            TensorSpec(
                name="velocity",
                shape=["batch", "frames", 3],
                dtype="float32",
                description=f"the pelvis velocity in the pelvis frame (m/s), each frame {net.look_ahead} frames late",
            ),
            *state_out,
        ],
        output_kind="velocity_mps",
        window_samples=1,
        classes=["vx", "vy", "vz"],
        velocity=VelocitySpec(
            sensors=list(sensors),
            feature_version=FEATURE_VERSION,
            acc_scale_mps2=ACC_SCALE_MPS2,
            architecture=f"lstm hidden {net.hidden} x {net.layers}, look-ahead {net.look_ahead} frames",
            look_ahead_frames=net.look_ahead,
            state_layers=net.layers,
            state_hidden=net.hidden,
            learned_share=share,
            chosen_with=chosen_with,
        ),
        sha256=sha256,
        **pose_feature_fields(sensors, training_data, evaluations, mlflow_info),
    )


def _table(errors: dict[str, dict[str, float]]) -> str:
    names = [k for k in errors["all"] if k != "clips"]
    lines = [f"{'activity':14s} {'clips':>5s} " + " ".join(f"{n:>10s}" for n in names)]
    for activity, row in sorted(errors.items()):
        lines.append(f"{activity:14s} {row['clips']:5.0f} " + " ".join(f"{row[n]:10.1f}" for n in names))
    return "\n".join(lines)


def run_velocity_experiment(
    vcfg: PoseVelocityConfig, data_dir: Path, cache_dir: Path, ship_to: Path | None = None, version: str | None = None
) -> dict:
    """Train the velocity network on the pose config's training clips, choose its epoch on the validation
    subjects (its velocity alone) and then its share on the ground (with the pose model's answers, against the
    rule), score the held-out subjects, export, log, register; ship it if it beats the rule on validation."""
    from training.pose.data import pose_evaluation_digest
    from training.pose.pipeline import TEST_SEED, VAL_SEED, carries_bandai, load_pose_data, log_datasets
    from training.run_labels import label_run
    from training.shipping import ship_files, with_registry
    from training.tracking import log_onnx_model, maybe_promote, register_model, setup_tracking

    cfg = load_pose_config(vcfg.pose_config)
    pose = PoseModel(load_model(Path(vcfg.pose_model), cfg.train.threads))
    if pose.spec.sensors != cfg.sensors:
        raise ValueError(f"{vcfg.pose_model} reads {pose.spec.sensors}, {vcfg.pose_config} {cfg.sensors}")
    chosen_with = f"{pose.name} {pose.loaded.manifest.version}"
    data = load_pose_data(cfg, data_dir, cache_dir)
    val_sessions = fixed_sessions(data.val, cfg, VAL_SEED)
    test_sessions = fixed_sessions(data.test, cfg, TEST_SEED)
    log.info("the pose model's answers on %d validation and %d held-out clips", len(data.val), len(data.test))
    val_cases = translation_cases(data.val, val_sessions, pose)
    test_cases = translation_cases(data.test, test_sessions, pose)

    def validation_cm(net: VelocityNet) -> float:  # the velocity alone, horizontal, frame-weighted
        v = learned_velocities(lambda f: predict_velocity(net, f), val_cases)
        scored = [
            (displacement_cm(c, integrated(c, w), horizontal=True)[0], len(w))
            for c, w in zip(val_cases, v, strict=True)
        ]
        scored = [(e, n) for e, n in scored if np.isfinite(e)]
        if not scored:
            raise ValueError("no validation clip is longer than the 1 s window the velocity is judged over")
        return float(np.average([e for e, _ in scored], weights=[n for _, n in scored]))

    setup_tracking(vcfg.tracking.experiment)
    with mlflow.start_run(run_name=vcfg.name) as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.set_tags(
            {
                "task": "imu_pose_velocity",
                "model_kind": "lstm",  # its description in the UI: training.run_labels, once the share is chosen
                "trains_on_bandai_namco": str(carries_bandai(cfg, data.train)),
            }
        )
        mlflow.log_params({k: str(v) for k, v in flatten(vcfg.model_dump()).items()})
        log_datasets(data, data_dir)

        def on_epoch(epoch: int, row: dict[str, float]) -> None:
            mlflow.log_metrics({k: v for k, v in row.items() if k != "epoch"}, step=epoch)

        result = train_velocity(vcfg, cfg, data.train, validation_cm, on_epoch)
        net = result.net
        mlflow.log_metrics(
            {"best_epoch": result.best_epoch, "train_wall_time_s": result.wall_s, "epochs_run": len(result.history)}
        )
        mlflow.set_tag("stopped", result.stopped)
        torch.save(net.state_dict(), tmp / "model_state.pt")
        mlflow.log_artifact(str(tmp / "model_state.pt"), "checkpoint")
        mlflow.log_artifact(str(velocity_learning_curve_png(result.history, tmp / "learning_curve.png")), "plots")

        predict = lambda f: predict_velocity(net, f)  # noqa: E731
        val = translation_errors(val_cases, learned_velocities(predict, val_cases), vcfg.shares)
        share = min(vcfg.shares, key=lambda s: val["all"][f"share_{s:g}"])
        beats_rule = val["all"][f"share_{share:g}"] < val["all"]["rule"]
        mlflow.log_metrics({f"val_trans_{k}_1s_cm": v for k, v in val["all"].items() if k != "clips"})
        mlflow.log_params({"chosen_share": share})
        mlflow.log_metric(SELECTION_METRIC, val["all"][f"share_{share:g}"])
        mlflow.set_tag("beats_rule_on_validation", str(beats_rule))
        rule, chosen = val["all"]["rule"], val["all"][f"share_{share:g}"]
        mlflow.set_tag(
            "note",
            f"Share {share:g} on the ground, chosen with {chosen_with} on the validation subjects ({chosen:.1f} cm "
            f"per 1 s against the rule's {rule:.1f} cm)",
        )
        log.info("validation, 1 s windows (cm):\n%s\nchosen share %g", _table(val), share)
        label_run(MlflowClient(), run.info.run_id)  # its name and description in the UI
        test = translation_errors(test_cases, learned_velocities(predict, test_cases), [share])
        test5 = translation_errors(test_cases, learned_velocities(predict, test_cases), [share], seconds=5.0)
        for activity, row in test.items():
            mlflow.log_metrics(
                {f"test_trans_{k}_1s_cm_{activity}": v for k, v in row.items() if k != "clips" and np.isfinite(v)}
            )
        log.info("held out, 1 s windows (cm):\n%s", _table(test))
        (tmp / "translation.json").write_text(
            json.dumps({"validation_1s": val, "test_1s": test, "test_5s": test5, "share": share}, indent=1)
        )
        mlflow.log_artifact(str(tmp / "translation.json"), "evaluation")
        mlflow.log_artifact(str(translation_bars_png(test, share, tmp / "translation_test.png")), "plots")

        onnx_path = export_velocity_onnx(net, tmp / "model.onnx")
        x = torch.from_numpy(test_cases[0].features[None, :120].astype(np.float32))
        h = torch.zeros(net.layers, 1, net.hidden)
        with torch.no_grad():
            expected = net.step(x, h, h.clone())[0].numpy()
        golden = {"features": x.numpy(), "expected": expected.astype(np.float32)}
        z = np.zeros((net.layers, 1, net.hidden), np.float32)
        got = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"]).run(
            None, {"features": golden["features"], "h0": z, "c0": z}
        )[0]
        parity = float(np.max(np.abs(got - expected)))
        mlflow.log_metric("onnx_parity_max_abs", parity)
        if parity > PARITY_ATOL:
            raise RuntimeError(f"onnxruntime differs from torch by {parity:.2e} on the golden input")
        np.savez(tmp / "golden.npz", **golden)
        version = version or "0.0.0+" + run.info.run_id[:8]
        training_data = {
            "sources": sorted({c.source for c in data.train}),
            "train_clips": len(data.train),
            "validation_subjects": cfg.data.val_subjects,
            "test_subjects": cfg.data.test_subjects,
            "bandai_namco": carries_bandai(cfg, data.train),
            "train_wall_time_s": round(result.wall_s, 1),
            "best_epoch": result.best_epoch,
            "epochs_run": len(result.history),
            "stopped": result.stopped,
            "validation_1s_cm": {k: round(v, 2) for k, v in val["all"].items()},
        }
        metrics = {
            f"trans_{k}_1s_cm_{a}": round(v, 2)
            for a, row in test.items()
            for k, v in row.items()
            if k in ("rule", f"share_{share:g}", "still") and np.isfinite(v)
        }
        evaluation = Evaluation(
            name="held-out subjects (simulated sensors)",
            command=f"python -m training.cli evaluate-pose --model {vcfg.pose_model} --velocity-model "
            f"onnx_models/{vcfg.name}/{version}",
            data=f"CMU subjects {', '.join(cfg.data.test_subjects)} and the li2018 run clips, never trained on or "
            f"chosen by; one simulated session per clip (seed {TEST_SEED}); the pose of {chosen_with}",
            metrics=metrics,
        )
        manifest = build_velocity_manifest(
            vcfg,
            cfg.sensors,
            net,
            version,
            sha256_file(onnx_path),
            share,
            chosen_with,
            training_data,
            [evaluation],
            {"run_id": run.info.run_id, "experiment_id": run.info.experiment_id},
        )
        info = log_onnx_model(onnx.load(str(onnx_path)), golden, manifest, input_key="features")
        mlflow.set_tag("model_uri", info.model_uri)
        registered_name = vcfg.tracking.registered_model or vcfg.name
        registered = register_model(info.model_uri, registered_name)
        # the registry's champion by the figure the share was chosen by, on the same validation sessions
        chosen = val["all"][f"share_{share:g}"]
        # the knees only: the elbows' plane turns upper arms about their own axes, which moves no joint the
        # translation reads
        digest = f"{pose_evaluation_digest(data.val, assembly(pose.hinge_joints, (), ()))}|{chosen_with}"
        promoted = beats_rule and maybe_promote(
            registered_name, registered.version, SELECTION_METRIC, chosen, False, digest
        )  # a network that loses to the rule is not served from the registry either
        mlflow.set_tag("promoted_to_champion", str(promoted))
        manifest = with_registry(manifest, info, registered)
        shipped = None
        if ship_to is not None and not beats_rule:
            log.warning("not shipped: on the validation subjects it does not beat the rule (%s)", val["all"])
        elif ship_to is not None:
            shipped = ship_files(ship_to, manifest, onnx_path, tmp / "golden.npz")
            served = VelocityModel(load_model(shipped, 2))  # the served path must give torch's numbers
            a = translation_errors(test_cases, learned_velocities(served.predict, test_cases), [share])
            key = f"share_{share:g}"
            if abs(a["all"][key] - test["all"][key]) > 0.05:
                got, want = a["all"][key], test["all"][key]
                raise RuntimeError(f"the shipped model reads {got:.2f} cm where torch read {want:.2f} cm")
            log.info("shipped %s", shipped)
        return {"run_id": run.info.run_id, "validation": val, "test": test, "share": share, "shipped": shipped}
