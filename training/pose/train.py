"""Training a pose network on simulated sessions of the training clips, with early stopping on validation subjects.

Each epoch draws ``sequences_per_epoch`` clips (by frames, activities above ``activity_cap_frames`` drawn less
often), simulates a fresh session of each (new mounting, noise, world heading: ``simulate.simulate_session``) and
cuts a random ``sequence_frames`` stretch. Loss: mean squared error of the rotation matrices over the real frames
of each sequence (batches of similar length, no padding: ``_length_buckets``), with ``train.position_loss`` also
that of the joint positions the rotations put through each sequence's own skeleton (``_position_loss``). The
validation figure that selects the epoch is the mean geodesic angle of the output segments on fixed sessions of the
validation subjects.
"""

from __future__ import annotations

import copy
import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from service.core.body import BODY_SEGMENTS, PARENT_INDEX, BodyMotion, clip_body, resample_motion
from service.inference.pose import run_chunked
from training.data.catalog import is_bandai_namco
from training.pose.config import PoseConfig, served_chunks
from training.pose.data import OWN_SOURCE, MotionClip, mirrored
from training.pose.models import PoseNet, anchor_sensors
from training.pose.simulate import SensorNoise, Session, root_relative_targets, simulate_session

log = logging.getLogger(__name__)


def build_net(cfg: PoseConfig, n_features: int) -> PoseNet:
    m = cfg.model
    dropout = 0.5 if m.kind == "ffn" else m.input_dropout  # Vlutters 2016 §IV-C: 0.5 on the input of the FFNN
    hidden = 100 if m.kind == "ffn" and m.hidden == 256 else m.hidden  # Vlutters 2016: 100 hidden units
    anchors = anchor_sensors(cfg.sensors, cfg.outputs) if m.anchored else None
    return PoseNet(
        m.kind, n_features, len(cfg.outputs), hidden, m.layers, dropout, m.representation, m.look_ahead, anchors
    )


def session_of(
    clip: MotionClip, cfg: PoseConfig, rng: np.random.Generator, noise: SensorNoise = SensorNoise()
) -> Session:
    return simulate_session(clip.motion, cfg.sensors, cfg.outputs, rng, noise, cfg.train.acc_method)


def fixed_sessions(clips: list[MotionClip], cfg: PoseConfig, seed: int, draw: int = 0) -> list[Session]:
    """One session per clip, seeded by the clip's digest: the same evaluation data on every run. ``draw`` k > 0 is
    the k-th further session of each clip (other mountings and noise; draw 0 is the one every run scores)."""
    return [
        session_of(c, cfg, np.random.default_rng([seed, int(c.digest[:12], 16)] + ([draw] if draw else [])))
        for c in clips
    ]


def clip_weights(
    clips: list[MotionClip], cap_frames: int, bandai_share: float | None = None, own_share: float | None = None
) -> np.ndarray:
    """How often each clip is drawn: by its frames, less for activities beyond ``cap_frames``; with
    ``bandai_share``, Bandai-Namco's clips together get that share of the draws and the others the rest; with
    ``own_share``, the user's own clips (``data.own``) that share, the data directory's the rest (weighed among
    themselves as without them)."""
    own = np.array([c.source == OWN_SOURCE for c in clips])
    if own_share is not None and own.any() and not own.all():
        w = np.zeros(len(clips))
        w[~own] = (1.0 - own_share) * clip_weights(
            [c for c, o in zip(clips, own, strict=True) if not o], cap_frames, bandai_share
        )
        w[own] = own_share * clip_weights([c for c, o in zip(clips, own, strict=True) if o], cap_frames)
        return w
    frames = Counter()
    for c in clips:
        frames[c.activity] += c.motion.n_frames
    w = np.array([c.motion.n_frames * min(1.0, cap_frames / frames[c.activity]) for c in clips], dtype=np.float64)
    if bandai_share is not None:
        bandai = np.array([is_bandai_namco(c.source) for c in clips])
        if bandai.any() and (~bandai).any():
            w[bandai] *= bandai_share / w[bandai].sum()
            w[~bandai] *= (1.0 - bandai_share) / w[~bandai].sum()
    return w / w.sum()


def _batch(sessions: list[Session], look_ahead: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Padded features (B, T, F), targets (B, T, S, 3, 3) shifted by the look-ahead, lengths (B,)."""
    T = max(len(s.features) for s in sessions)
    B, F = len(sessions), sessions[0].features.shape[1]
    x = np.zeros((B, T, F), np.float32)
    lengths = np.zeros(B, np.int64)
    for i, s in enumerate(sessions):
        n = len(s.features)
        x[i, :n], lengths[i] = s.features, n
    return torch.from_numpy(x), _shifted([s.targets for s in sessions], T, look_ahead), torch.from_numpy(lengths)


def _shifted(arrays: list[np.ndarray], T: int, look_ahead: int) -> torch.Tensor:
    """Per-frame arrays (n_i, ...) as one zero-padded (B, T, ...) tensor, shifted by the look-ahead: with look-ahead
    L the output at frame t is the pose of frame t - L; the first L outputs have no target."""
    out = np.zeros((len(arrays), T, *arrays[0].shape[1:]), np.float32)
    for i, a in enumerate(arrays):
        out[i, look_ahead : len(a)] = a[: len(a) - look_ahead] if look_ahead else a
    return torch.from_numpy(out)


def _frame_mask(T: int, lengths: torch.Tensor, look_ahead: int) -> torch.Tensor:
    """(B, T): 1 on the frames a loss judges (within the sequence, after the look-ahead's first L)."""
    t = torch.arange(T)[None, :]
    return ((t < lengths[:, None]) & (t >= look_ahead)).float()


def _loss(pred: torch.Tensor, target: torch.Tensor, lengths: torch.Tensor, look_ahead: int) -> torch.Tensor:
    mask = _frame_mask(pred.shape[1], lengths, look_ahead)
    err = ((pred - target) ** 2).sum(dim=(-1, -2)).mean(-1)  # (B, T)
    return (err * mask).sum() / mask.sum().clamp(min=1.0)


def forward_kinematics(R_root: torch.Tensor, offsets_m: torch.Tensor) -> torch.Tensor:
    """Segment origins (B, T, S, 3) in the root's frame from root-relative orientations (B, T, S, 3, 3) of every
    body segment and each sequence's bones (B, S, 3): ``service.core.body.segment_origins`` in torch."""
    p = [R_root.new_zeros(R_root.shape[:2] + (3,))]
    for k in range(1, len(BODY_SEGMENTS)):
        parent = PARENT_INDEX[k]
        p.append(p[parent] + torch.einsum("btij,bj->bti", R_root[:, :, parent], offsets_m[:, k]))
    return torch.stack(p, dim=2)


def _position_loss(
    pred: torch.Tensor,
    full: torch.Tensor,
    offsets_m: torch.Tensor,
    output_index: list[int],
    lengths: torch.Tensor,
    look_ahead: int,
) -> torch.Tensor:
    """Mean squared distance (m²) of the non-root segment origins, the true body's against the same body with the
    model's answers in place of the true output segments (the sensed segments as they are, so only the answers
    are judged): each answer weighted by how far it moves the joints below it."""
    answered = full.clone()
    answered[:, :, output_index] = pred
    d = ((forward_kinematics(answered, offsets_m) - forward_kinematics(full, offsets_m)) ** 2).sum(-1)[..., 1:]
    mask = _frame_mask(pred.shape[1], lengths, look_ahead)
    return (d.mean(-1) * mask).sum() / mask.sum().clamp(min=1.0)


def geodesic_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of R_aᵀ R_b in degrees, elementwise over the leading axes."""
    tr = np.einsum("...ji,...ji->...", R_a, R_b)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def torch_predictor(net: PoseNet, chunks: tuple[int, int] | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """features (T, F) → R_root_segment (T, S, 3, 3), the pose of each frame (look-ahead undone as in serving);
    ``chunks`` (window, context): an offline model run chunk by chunk as the service runs it
    (``training.pose.config.served_chunks``), so that the figures of a run are the served model's."""

    def predict(features: np.ndarray) -> np.ndarray:
        L = net.look_ahead
        x = np.concatenate([features, np.repeat(features[-1:], L, axis=0)]) if L else features
        with torch.no_grad():
            return net(torch.from_numpy(x[None].astype(np.float32)))[0, L:].numpy()

    def predict_many(x: np.ndarray) -> np.ndarray:  # an offline model over stacked chunks, as the service runs them
        with torch.no_grad():
            return net(torch.from_numpy(x.astype(np.float32))).numpy()

    if chunks is None:
        return predict
    return lambda features: run_chunked(predict, features, *chunks, predict_many=predict_many)


def validation_angle(net: PoseNet, sessions: list[Session], chunks: tuple[int, int] | None = None) -> float:
    net.eval()
    predict = torch_predictor(net, chunks)
    errs, n = 0.0, 0
    for s in sessions:
        e = geodesic_deg(predict(s.features), s.targets)
        errs, n = errs + float(e.sum()), n + e.size
    return errs / max(n, 1)


@dataclass
class PoseTrainResult:
    net: PoseNet
    history: list[dict[str, float]] = field(default_factory=list)
    best_epoch: int = 0
    best_val_deg: float = float("inf")
    wall_s: float = 0.0
    stopped: str = ""


@dataclass
class BestEpoch:
    """Early stopping on a validation figure, lower better: keeps the best epoch's weights of ``net`` and says when
    to stop (``patience`` epochs without a gain, or ``time_budget_s`` spent)."""

    net: torch.nn.Module
    patience: int
    time_budget_s: float = float("inf")
    best: float = float("inf")  # a warm start sets its own figure here
    best_epoch: int = 0
    bad: int = 0  # epochs since the last gain
    state: dict[str, torch.Tensor] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.state = copy.deepcopy(self.net.state_dict())

    def record(self, epoch: int, val: float, elapsed_s: float) -> str:
        """Take an epoch's validation figure: "" to go on, else why training stops."""
        if val < self.best:
            self.best, self.best_epoch, self.bad = val, epoch, 0
            self.state = copy.deepcopy(self.net.state_dict())
        else:
            self.bad += 1
        if self.bad >= self.patience:
            return f"no validation gain for {self.bad} epochs"
        if elapsed_s > self.time_budget_s:
            return f"time budget {self.time_budget_s:.0f} s spent"
        return ""

    def restore(self) -> None:
        """The best epoch's weights back into the network, in evaluation mode."""
        self.net.load_state_dict(self.state)
        self.net.eval()


def feature_stats(
    clips: list[MotionClip], cfg: PoseConfig, rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    picks = rng.choice(len(clips), size=min(200, len(clips)), replace=False)
    x = np.concatenate([session_of(clips[i], cfg, rng).features for i in picks])
    return torch.from_numpy(x.mean(0)), torch.from_numpy(x.std(0))


def train_pose(
    cfg: PoseConfig,
    train_clips: list[MotionClip],
    val_sessions: list[Session],
    on_epoch: Callable[[int, dict[str, float]], None] | None = None,
    init_state: dict[str, torch.Tensor] | None = None,
) -> PoseTrainResult:
    """The network of the best validation epoch. ``init_state``: a warm start's weights and feature
    standardisation (``training.pose.warmstart``); its own validation figure is then epoch 0's (``on_epoch`` gets
    it, without training figures), and a run that never beats it returns it unchanged."""
    t0 = time.time()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.train.threads)
    rng = np.random.default_rng(cfg.seed)
    n_features = (
        val_sessions[0].features.shape[1] if val_sessions else session_of(train_clips[0], cfg, rng).features.shape[1]
    )
    net = build_net(cfg, n_features)
    if init_state is None:
        net.set_normalisation(*feature_stats(train_clips, cfg, rng))
    else:
        net.load_state_dict(init_state)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.train.lr)
    sched = (
        torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.train.max_epochs, eta_min=cfg.train.lr * cfg.train.lr_floor)
        if cfg.train.lr_schedule == "cosine"
        else None
    )
    own_share = cfg.data.own.share if cfg.data.own else None
    weights = clip_weights(train_clips, cfg.data.activity_cap_frames, cfg.data.bandai_share, own_share)
    output_index = [BODY_SEGMENTS.index(s) for s in cfg.outputs]
    result = PoseTrainResult(net)
    keeper = BestEpoch(net, cfg.train.patience, cfg.train.time_budget_s)
    if init_state is not None:
        keeper.best = validation_angle(net, val_sessions, served_chunks(cfg))
        log.info("%s warm start: validation %.2f°", cfg.name, keeper.best)
        if on_epoch:
            on_epoch(0, {"val_angle_deg": keeper.best})
    L, W = cfg.model.look_ahead, cfg.train.sequence_frames
    for epoch in range(1, cfg.train.max_epochs + 1):
        net.train()
        picks = rng.choice(len(train_clips), size=cfg.train.sequences_per_epoch, p=weights)
        batches = _length_buckets(picks, [c.motion.n_frames for c in train_clips], cfg.train.batch_size, rng)
        losses, rotation_losses = [], []  # the whole loss and its rotation term (the same without position_loss)
        bar = tqdm(batches, desc=f"{cfg.name} epoch {epoch}", unit="batch", leave=False, mininterval=5.0)
        for batch in bar:
            n = min(W, min(train_clips[i].motion.n_frames for i in batch))
            sessions, bodies = [], []
            for i in batch:
                clip = _drawn_sequence(train_clips[i], n, cfg.train.speed, cfg.train.size, rng)
                if cfg.train.mirror and rng.random() < cfg.train.mirror:  # no draw without it: older runs replay
                    clip = mirrored(clip)
                sessions.append(session_of(clip, cfg, rng))
                bodies.append(clip.motion)
            x, y, lengths = _batch(sessions, L)
            pred = net(x)
            loss = rotation_loss = _loss(pred, y, lengths, L)
            if cfg.train.position_loss:
                full = _shifted([root_relative_targets(m, BODY_SEGMENTS) for m in bodies], x.shape[1], L)
                offsets = torch.from_numpy(np.stack([clip_body(m).offsets_m for m in bodies]).astype(np.float32))
                loss = loss + cfg.train.position_loss * _position_loss(pred, full, offsets, output_index, lengths, L)
            rotation_losses.append(rotation_loss.item())
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            losses.append(loss.item())
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
        lr = opt.param_groups[0]["lr"]
        if sched:
            sched.step()
        val = validation_angle(net, val_sessions, served_chunks(cfg))
        row = {
            "epoch": epoch,
            "train_loss": float(np.mean(losses)),
            "train_rotation_loss": float(np.mean(rotation_losses)),
            "val_angle_deg": val,
            "lr": lr,
            "wall_s": time.time() - t0,
        }
        result.history.append(row)
        log.info("%s epoch %d: loss %.4f, validation %.2f°", cfg.name, epoch, row["train_loss"], val)
        if on_epoch:
            on_epoch(epoch, row)
        result.stopped = keeper.record(epoch, val, time.time() - t0)
        if result.stopped:
            break
    else:
        result.stopped = f"max_epochs {cfg.train.max_epochs} reached"
    keeper.restore()
    result.best_val_deg, result.best_epoch, result.wall_s = keeper.best, keeper.best_epoch, time.time() - t0
    return result


def _length_buckets(
    picks: np.ndarray, frames: list[int], batch_size: int, rng: np.random.Generator
) -> list[np.ndarray]:
    """Batches of clips of similar length (sorted, then cut), in random order: each batch is cropped to its
    shortest member, so no sequence is padded (padding would feed the Bi-LSTM's backward pass zeros first, and
    packing the padded batch is five times slower on the CPU)."""
    order = picks[np.argsort([frames[i] for i in picks], kind="stable")]
    batches = [order[i : i + batch_size] for i in range(0, len(order), batch_size)]
    return [batches[k] for k in rng.permutation(len(batches))]


def _drawn_sequence(
    clip: MotionClip, n: int, speed: tuple[float, float], size: tuple[float, float], rng: np.random.Generator
) -> MotionClip:
    """``n`` frames of ``clip`` from a random start; with a ``speed`` range, the motion of about ``n · s`` frames
    played in ``n`` (s uniform in the range, as far as the clip is long), with a ``size`` range, the body scaled
    about its first pelvis position. Ranges of (1, 1) draw nothing (older runs replay)."""
    frames = clip.motion.n_frames
    s = rng.uniform(*speed) if speed != (1.0, 1.0) else 1.0
    n_src = min(frames, max(n, int(round((n - 1) * s)) + 1))
    start = int(rng.integers(0, frames - n_src + 1))
    clip = _crop(clip, start, start + n_src)
    if n_src != n:  # n_src frames lasting what n frames last: resampled, exactly n at the model rate
        m = clip.motion
        rate = m.sample_rate_hz
        played = BodyMotion(m.R_world_segment, m.origin_m, m.midpoint_m, rate * (n_src - 1) / (n - 1))
        motion = resample_motion(played, rate)
        clip = MotionClip(clip.path, clip.source, clip.subject, clip.activity, motion.crop(0, n), clip.digest)
    if size != (1.0, 1.0):
        b, m = rng.uniform(*size), clip.motion
        pivot = m.origin_m[0, 0]
        motion = BodyMotion(
            m.R_world_segment, pivot + b * (m.origin_m - pivot), pivot + b * (m.midpoint_m - pivot), m.sample_rate_hz
        )
        clip = MotionClip(clip.path, clip.source, clip.subject, clip.activity, motion, clip.digest)
    return clip


def _crop(clip: MotionClip, start: int, stop: int) -> MotionClip:
    return MotionClip(clip.path, clip.source, clip.subject, clip.activity, clip.motion.crop(start, stop), clip.digest)
