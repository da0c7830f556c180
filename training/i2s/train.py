"""Training loop for the Zimmermann et al. 2018 networks: fresh simulated windows every step, Adam with L2,
early stopping on a fixed validation set, seeded and reproducible (fixed thread count, device and loader workers).

``save_fitted`` / ``load_fitted`` carry a finished training from a machine without the tracking store (a GPU box
running ``training.cli fit``) to ``training.cli train --fitted``, which tracks, exports and evaluates it here.
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from tqdm import tqdm

from service.core.manifest import read_manifest
from training.config import flatten
from training.i2s.config import ExperimentConfig
from training.i2s.data.mocap import Clip
from training.i2s.data.split import recordings_digest
from training.i2s.data.windows import Augmentation, Batch, RealWindowSampler, WindowSampler, concat_batches
from training.i2s.models import AlignmentNet, AssignmentNet
from training.i2s.warmstart import (
    alignment_teacher_from_shipped,
    assignment_ensemble,
    check_real_recordings_declared,
    teacher_from_shipped,
)

log = logging.getLogger(__name__)

MetricLogger = Callable[[dict[str, float], int], None]


def build_model(cfg: ExperimentConfig) -> nn.Module:
    t = cfg.train
    if t.rnn_stride != 1 and cfg.task != "alignment":
        raise ValueError("rnn_stride pools the alignment network's features; the assignment network has none")
    if cfg.task == "assignment" and t.ensemble_of:
        return assignment_ensemble(t.ensemble_of, t.hidden, t.channels, t.kernel, t.keep_prob)
    if cfg.task == "assignment":
        return AssignmentNet(
            t.hidden,
            t.channels,
            t.kernel,
            t.keep_prob,
            canonical=t.canonical_frame,
            quarter_turns=t.quarter_turns,
            gravity_turns=t.gravity_turns,
            gravity_turn_segments=t.gravity_turn_segments,
        )
    if t.functional_axes is not None and cfg.task != "alignment":
        raise ValueError("functional_axes turns alignment predictions; the assignment task has none")
    return AlignmentNet(
        t.hidden,
        t.channels,
        t.kernel,
        t.keep_prob,
        canonical=t.canonical_frame,
        functional_axes=t.functional_axes,
        pelvis_half_turn=t.pelvis_half_turn,
        rnn_stride=t.rnn_stride,
    )


def quat_distance(q_pred: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
    """Sign-invariant squared chordal distance min |q ± q_true|² = 2 - 2|q·q_true|, ``(B,)``."""
    return 2.0 - 2.0 * (q_pred * q_true).sum(-1).abs()


def task_loss(task: str, output: torch.Tensor, segment: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
    """Cross entropy of the logits (assignment, §2.2.5), or the sign-invariant quaternion distance of the true
    segment's row of the predicted quaternions (alignment).

    The paper regresses the stereographic projection with an L2 loss (``stereographic_l2_loss``); with w ≥ 0
    canonical targets that loss jumps at 180° rotations, which eq. 8's full circles produce, so the default
    compares the mapped quaternions sign-invariantly. The parametrisation (3 values, stereographic) is the paper's.
    """
    if task == "assignment":
        return nn.functional.cross_entropy(output, segment)
    return quat_distance(output[torch.arange(len(segment)), segment], q_true).mean()


def distillation_loss(
    logits: torch.Tensor,
    teacher_log_p: torch.Tensor,
    segment: torch.Tensor,
    weight: float,
    temperature: float,
    taught: torch.Tensor | None = None,
) -> torch.Tensor:
    """Knowledge distillation (Hinton et al. 2015 §2): (1 − weight) × the cross entropy with the labels plus
    weight × τ² × KL(teacher ‖ student) between the class distributions softened at temperature τ (the τ² keeps the
    soft term's gradients at the hard term's scale as τ changes), averaged over the windows. ``teacher_log_p``: the
    teacher's log class probabilities (``build_teacher``) for the ``taught`` windows ``(B,)`` bool (None: all); the
    others train on their labels alone."""
    hard = nn.functional.cross_entropy(logits, segment, reduction="none")
    if taught is None:
        taught = torch.ones_like(segment, dtype=torch.bool)
    soft_student = torch.log_softmax(logits[taught] / temperature, -1)
    soft_teacher = torch.log_softmax(teacher_log_p / temperature, -1)
    kl = nn.functional.kl_div(soft_student, soft_teacher, log_target=True, reduction="none").sum(-1)
    share = torch.zeros_like(hard)
    share[taught] = weight
    soft = torch.zeros_like(hard)
    soft[taught] = temperature**2 * kl
    return ((1.0 - share) * hard + share * soft).mean()


def alignment_distillation_loss(
    q_student: torch.Tensor,
    q_teacher: torch.Tensor,
    segment: torch.Tensor,
    q_true: torch.Tensor,
    weight: float,
    taught: torch.Tensor | None = None,
) -> torch.Tensor:
    """An alignment network taught by another (``train.distill_from``; Hinton et al. 2015 carried over to a
    regression): per window, the sign-invariant quaternion distance of the true segment's row to the label and to
    the teacher's row, in shares (1 − weight) and weight, averaged over the windows. A window without a label (real:
    ``q_true`` NaN) learns the teacher's row alone; one the teacher does not speak for (``taught`` False, ``(B,)``
    bool; None: all) its label alone. ``q_student``, ``q_teacher``: ``(B, 7, 4)``."""
    rows = torch.arange(len(segment))
    student, teacher = q_student[rows, segment], q_teacher[rows, segment]
    labelled = torch.isfinite(q_true).all(-1)
    if taught is None:
        taught = torch.ones_like(labelled)
    if bool((~labelled & ~taught).any()):
        raise ValueError("a window without an alignment label must be one the teacher speaks for")
    to_label = quat_distance(student, torch.where(labelled[:, None], q_true, teacher))
    to_teacher = quat_distance(student, teacher)
    share = torch.where(labelled, torch.where(taught, weight, 0.0), 1.0)
    return ((1.0 - share) * to_label + share * to_teacher).mean()


def build_teacher(cfg: ExperimentConfig) -> nn.Module | None:
    """The frozen network ``train.distill_from`` names (None without one), of this run's task; the real recordings
    it trained on must be this run's training recordings too."""
    t = cfg.train
    if t.distill_from is None:
        return None
    teacher_task = read_manifest(Path(t.distill_from) / "manifest.json").task
    if teacher_task != f"i2s_{cfg.task}":
        raise ValueError(f"train.distill_from {t.distill_from} is an {teacher_task} model; this run trains {cfg.task}")
    check_real_recordings_declared([t.distill_from], cfg.data.real_train_recordings, "teacher")
    if cfg.task == "alignment":
        return alignment_teacher_from_shipped(Path(t.distill_from), t.keep_prob)
    return teacher_from_shipped(Path(t.distill_from), t.keep_prob)


def stereographic_l2_loss(
    model: AlignmentNet, imu: torch.Tensor, segment: torch.Tensor, q_true: torch.Tensor
) -> torch.Tensor:
    """Zimmermann et al. 2018 §2.2.5: L2 on the stereographic projection p, target from the w ≥ 0 quaternion."""
    p, R_c = model.stereographic(imu)
    if R_c is not None:
        raise ValueError("alignment_loss stereographic_l2 needs a net without canonical frame (train.canonical_frame)")
    p_true = q_true[:, 1:] / (1.0 + q_true[:, :1])
    return ((p[torch.arange(len(segment)), segment] - p_true) ** 2).sum(-1).mean()


def to_tensors(batch: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """imu, segment, q_segment_imu and the taught mask (all True where the batch carries none)."""
    taught = np.ones(len(batch.segment), bool) if batch.taught is None else batch.taught
    return (
        torch.from_numpy(batch.imu),
        torch.from_numpy(batch.segment),
        torch.from_numpy(batch.q_segment_imu),
        torch.from_numpy(taught),
    )


def _draw(
    sampler: WindowSampler,
    real: RealWindowSampler | None,
    real_fraction: float,
    rng: np.random.Generator,
    batch_size: int,
) -> Batch:
    n_real = int(round(real_fraction * batch_size)) if real is not None else 0
    batch = sampler.sample(rng, batch_size - n_real)
    return concat_batches(batch, real.sample(rng, n_real)) if n_real else batch


class _SimulatedBatches(torch.utils.data.IterableDataset):
    """Endless training batches for a DataLoader worker, each worker with generator ``(seed, worker id)``."""

    def __init__(self, sampler: WindowSampler, real: RealWindowSampler | None, cfg: ExperimentConfig) -> None:
        self.sampler, self.real, self.cfg = sampler, real, cfg

    def __iter__(self) -> Iterator[tuple[torch.Tensor, ...]]:
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng([self.cfg.seed, info.id if info is not None else 0])
        while True:
            yield to_tensors(
                _draw(self.sampler, self.real, self.cfg.data.real_fraction, rng, self.cfg.train.batch_size)
            )


def _training_batches(
    sampler: WindowSampler, real: RealWindowSampler | None, cfg: ExperimentConfig, rng: np.random.Generator
) -> Iterator[tuple[torch.Tensor, ...]]:
    if cfg.train.loader_workers == 0:
        while True:
            yield to_tensors(_draw(sampler, real, cfg.data.real_fraction, rng, cfg.train.batch_size))
    loader = torch.utils.data.DataLoader(
        _SimulatedBatches(sampler, real, cfg),
        batch_size=None,
        num_workers=cfg.train.loader_workers,
        prefetch_factor=4,
        persistent_workers=True,
        pin_memory=cfg.train.device != "cpu",
    )
    yield from loader


@dataclass
class TrainResult:
    model: nn.Module
    best_epoch: int
    history: list[dict[str, float]] = field(default_factory=list)
    wall_time_s: float = 0.0
    warm_start: dict[str, float] | None = None  # the warm-start weights' validation (epoch 0), if there were any


@torch.no_grad()
def _validate(model: nn.Module, task: str, batches: list[Batch], device: torch.device) -> dict[str, float]:
    model.eval()
    losses, correct, angles = [], 0, []
    for b in batches:
        imu, seg, q, _ = (x.to(device) for x in to_tensors(b))
        out = model(imu)
        losses.append(float(task_loss(task, out, seg, q)) * len(seg))
        if task == "assignment":
            correct += int((out.argmax(-1) == seg).sum())
        else:
            qp = out[torch.arange(len(seg)), seg]
            angles.append(torch.rad2deg(2 * torch.acos((qp * q).sum(-1).abs().clamp(max=1.0))))
    n = sum(len(b.segment) for b in batches)
    metrics = {"val_loss": sum(losses) / n}
    if task == "assignment":
        metrics["val_accuracy"] = correct / n
    else:
        metrics["val_angle_error_deg"] = float(torch.cat(angles).mean())
    return metrics


def _validation(
    model: nn.Module,
    task: str,
    simulated: list[Batch],
    real: list[Batch],
    device: torch.device,
    real_weight: float | None = None,
) -> dict[str, float]:
    """Validation over the simulated and real batches together (what selects the epoch), and the real ones alone.
    Each set runs once; the joint figures are their means weighted by window count, or with ``real_weight`` on
    the real set's (``data.real_val_weight``)."""
    metrics = _validate(model, task, simulated, device)
    if not real:
        return metrics
    alone = _validate(model, task, real, device)
    if real_weight is None:
        n_sim, n_real = (sum(len(b.segment) for b in batches) for batches in (simulated, real))
        real_weight = n_real / (n_sim + n_real)
    joint = {k: metrics[k] * (1.0 - real_weight) + alone[k] * real_weight for k in metrics}
    return joint | {k.replace("val_", "val_real_", 1): v for k, v in alone.items()}


def train(
    cfg: ExperimentConfig,
    train_clips: list[Clip],
    val_clips: list[Clip],
    log_metrics: MetricLogger | None = None,
    init_state: dict | None = None,
    real: RealWindowSampler | None = None,
    real_val: RealWindowSampler | None = None,
) -> TrainResult:
    """Train one model; ``init_state`` warm-starts it and ``real`` mixes real windows into every batch
    (``cfg.data.real_fraction`` of it): pre-training then fine-tuning as in Zimmermann et al. 2018 §4.3. ``real_val``
    joins the validation in the same share, so early stopping and the warm start's epoch 0 are judged on real windows
    too (reported alone as ``val_real_*``)."""
    if cfg.task == "alignment" and (real_val is not None or (real is not None and cfg.train.distill_from is None)):
        raise ValueError(
            "real recordings carry no alignment labels: an alignment network learns from them only through a teacher "
            "(train.distill_from), and validates on simulated windows alone"
        )
    t = cfg.train
    device = torch.device(t.device)
    teacher = build_teacher(cfg)  # before the seed: building it draws torch's random numbers, training must not see
    if teacher is not None:
        teacher.to(device)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(t.threads)
    rng = np.random.default_rng(cfg.seed)
    model = build_model(cfg)
    if init_state is not None:
        model.load_state_dict(init_state)
    model.to(device)
    optimiser = torch.optim.Adam(model.parameters(), lr=t.lr, weight_decay=t.weight_decay)
    sampler = WindowSampler(train_clips, cfg.augmentation, taught_activities=t.distill_activities)
    # Validation: the training distribution of alignments, with only the paper's noise (no other augmentation).
    # The clips' variants keep their share, so that validation sees the gaits training does, and with
    # ``moving_only`` it is scored on the windows the service answers, as training draws them.
    val_aug = Augmentation(
        alignment=cfg.augmentation.alignment,
        acc_noise_std_mps2=cfg.augmentation.acc_noise_std_mps2,
        stiff_knee_share=cfg.augmentation.stiff_knee_share,
        moving_only=cfg.augmentation.moving_only,
    )
    val_sampler = WindowSampler(val_clips, val_aug)
    val_rng = np.random.default_rng(cfg.seed + 1)
    val_batches = [val_sampler.sample(val_rng, t.batch_size) for _ in range(max(1, t.val_windows // t.batch_size))]
    real_batches = []
    if real_val is not None:  # as many real windows as the training batches' share: f / (1 - f) per simulated one
        share = cfg.data.real_fraction / (1.0 - cfg.data.real_fraction)
        real_batches = [real_val.sample(val_rng, t.batch_size) for _ in range(max(1, round(len(val_batches) * share)))]
    # With ``ema_decay`` the weights that are validated, kept and returned are the moving average (``scored``);
    # it starts at the initial (or warm-start) weights. Without it ``scored`` is the trained model itself.
    ema = None
    if t.ema_decay is not None:
        ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(t.ema_decay), use_buffers=True)
        ema.update_parameters(model)
    scored = model if ema is None else ema.module
    best, best_state, best_epoch, stale = float("inf"), copy.deepcopy(model.state_dict()), 0, 0
    result = TrainResult(model, 0)
    start = time.monotonic()
    if init_state is not None:
        # The warm-start weights compete as epoch 0: fine-tuning that never beats them returns them unchanged
        # (and max_epochs 0 wraps them as they are, e.g. in a new turn average).
        start_metrics = _validation(model, cfg.task, val_batches, real_batches, device, cfg.data.real_val_weight)
        best, result.warm_start = start_metrics["val_loss"], start_metrics
        if log_metrics:  # step 0 of the learning curves: what the warm start scored
            log_metrics(start_metrics, 0)
        log.info("epoch 0 (warm start) %s", {k: round(v, 5) for k, v in start_metrics.items()})
    batches = _training_batches(sampler, real, cfg, rng)
    for epoch in range(1, t.max_epochs + 1):
        model.train()
        running = 0.0
        bar = tqdm(range(t.steps_per_epoch), desc=f"{cfg.name} epoch {epoch}/{t.max_epochs}", unit="step", leave=False)
        for _ in bar:
            imu, seg, q, taught = (x.to(device, non_blocking=True) for x in next(batches))
            if t.alignment_loss == "stereographic_l2" and isinstance(model, AlignmentNet):
                loss = stereographic_l2_loss(model, imu, seg, q)
            elif teacher is not None and cfg.task == "alignment":
                q_student = model(imu)
                with torch.no_grad():
                    q_teacher = teacher(imu)
                loss = alignment_distillation_loss(q_student, q_teacher, seg, q, t.distill_weight, taught)
            elif teacher is not None:
                logits = model(imu)
                with torch.no_grad():  # a batch without a taught window (rare with few of them) asks nothing
                    teacher_log_p = (
                        teacher(imu[taught]) if bool(taught.any()) else logits.new_zeros(0, logits.shape[-1])
                    )
                loss = distillation_loss(logits, teacher_log_p, seg, t.distill_weight, t.distill_temperature, taught)
            else:
                loss = task_loss(cfg.task, model(imu), seg, q)
            optimiser.zero_grad()
            loss.backward()
            if t.grad_clip_norm is not None:
                nn.utils.clip_grad_norm_(model.parameters(), t.grad_clip_norm)
            optimiser.step()
            if ema is not None:
                ema.update_parameters(model)
            running += float(loss.detach())
            bar.set_postfix(loss=f"{running / (bar.n + 1):.4f}")
        metrics = {
            "train_loss": running / t.steps_per_epoch,
            **_validation(scored, cfg.task, val_batches, real_batches, device, cfg.data.real_val_weight),
        }
        metrics["wall_time_s"] = time.monotonic() - start
        result.history.append(metrics)
        if log_metrics:
            log_metrics(metrics, epoch)
        log.info("epoch %d %s", epoch, {k: round(v, 4) for k, v in metrics.items()})
        if metrics["val_loss"] < best:
            best, best_state, best_epoch, stale = metrics["val_loss"], copy.deepcopy(scored.state_dict()), epoch, 0
        else:
            stale += 1
        if t.keep == "last":
            best_state, best_epoch = copy.deepcopy(scored.state_dict()), epoch
        elif stale >= t.patience:
            log.info("early stopping after epoch %d (best %d)", epoch, best_epoch)
            break
        if t.max_minutes is not None and metrics["wall_time_s"] > 60 * t.max_minutes:
            log.info("wall-time budget of %.1f min reached after epoch %d", t.max_minutes, epoch)
            break
    batches.close()  # stops the loader workers
    model.load_state_dict(best_state)
    model.to("cpu").eval()  # export and evaluation run on the CPU
    result.best_epoch, result.wall_time_s = best_epoch, time.monotonic() - start
    return result


def save_fitted(
    path: Path, cfg: ExperimentConfig, result: TrainResult, train_digest: str, val_digest: str, real_digest: str
) -> Path:
    """A finished training (weights, per-epoch history, the config and the digests of the clips and of the real
    training recordings it used, ``recordings_digest``)."""
    device = torch.cuda.get_device_name() if cfg.train.device.startswith("cuda") else "cpu"
    payload = {
        "state": result.model.state_dict(),
        "history": result.history,
        "warm_start": result.warm_start,
        "best_epoch": result.best_epoch,
        "wall_time_s": result.wall_time_s,
        "config": cfg.model_dump(mode="json"),
        "train_digest": train_digest,
        "val_digest": val_digest,
        "real_digest": real_digest,
        "device": device,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


_WHERE_ONLY = {"train.device", "train.loader_workers", "train.threads"}  # where a run trained, not what


def _settings(config: dict) -> dict[str, object]:
    """Dotted keys → values of a dumped config, without ``_WHERE_ONLY``."""
    return {k: v for k, v in flatten(config).items() if k not in _WHERE_ONLY}


def load_fitted(
    path: Path, cfg: ExperimentConfig, train_digest: str, val_digest: str, real_digest: str
) -> tuple[TrainResult, dict[str, object]]:
    """The training saved by ``save_fitted``, checked against the run that will track it.

    The configs must agree except for where it ran (``train.device``, ``loader_workers``, ``threads``), and the
    training and validation clips and the real training recordings must be the same by digest; otherwise the
    tracked run would misdescribe it.
    Returns the result and the fitted config (for the run's record of where it trained).
    """
    payload = torch.load(path, weights_only=True)
    try:  # the fitted config with today's defaults for keys added since it was written
        fitted_cfg = ExperimentConfig.model_validate(payload["config"]).model_dump(mode="json")
    except ValueError:  # a key since removed: compared as written, so the message names it
        fitted_cfg = payload["config"]
    theirs, ours = _settings(fitted_cfg), _settings(cfg.model_dump(mode="json"))
    differ = sorted(k for k in theirs.keys() | ours.keys() if theirs.get(k) != ours.get(k))
    if differ:
        raise ValueError(
            f"{path} was fitted with another configuration: "
            + ", ".join(f"{k} {theirs.get(k)!r} there, {ours.get(k)!r} here" for k in differ)
        )
    if (payload["train_digest"], payload["val_digest"]) != (train_digest, val_digest):
        raise ValueError(
            f"{path} was fitted on other clips (train/val digests {payload['train_digest']}/{payload['val_digest']}, "
            f"here {train_digest}/{val_digest}): the kinematics or the data directory differ"
        )
    fitted_real = payload.get("real_digest", recordings_digest([]))  # files from before real data could travel
    if fitted_real != real_digest:
        raise ValueError(
            f"{path} was fitted on other real recordings (digest {fitted_real}, here {real_digest}; "
            f"data.real_train_recordings: {cfg.data.real_train_recordings}): the readers or the data directory differ"
        )
    model = build_model(cfg)
    model.load_state_dict(payload["state"])
    model.eval()
    result = TrainResult(
        model, payload["best_epoch"], payload["history"], payload["wall_time_s"], payload.get("warm_start")
    )
    return result, {"device": payload["device"], **payload["config"]["train"]}
