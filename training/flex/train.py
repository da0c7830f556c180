"""Training of one flex network (Chen et al. 2024 §3.4.1 and §3.4.3): Adam 1e-3 decaying by 0.1 every 10 epochs,
gradient clipping, batch 64, squared error over the short input sequence (eq. 3), the epoch best on the
validation subjects kept; it stops when the validation error fell by less than 0.1° over 10 epochs, or at the
time budget."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from service.core import flex as flex_core
from service.core.joint_angles import JOINT_COMPONENTS
from training.flex.config import CapacitiveConfig, FlexConfig
from training.flex.data import WindowSet
from training.flex.evaluate import predict_windows
from training.flex.models import FlexEnsemble, FlexNet, readings

log = logging.getLogger(__name__)


@dataclass
class FlexTrainResult:
    net: FlexNet | FlexEnsemble
    history: list[dict[str, float]]  # every member's epochs in turn, each row naming its ``member``
    best_epoch: int  # the first member's; ``member_best_epochs`` has each one's
    wall_s: float
    stopped: str
    member_best_epochs: list[int]


def build_net(cfg: FlexConfig, train: WindowSet) -> FlexNet:
    """A network with the training set's normalisation: counts min-max per channel (§3.4.3), targets
    standardised per output."""
    flat = train.counts.reshape(-1, train.counts.shape[-1])
    if cfg.model.input_norm in ("window_relative", "window_standardised"):
        ends = np.random.default_rng(cfg.seed).choice(train.ends, size=min(4000, len(train.ends)), replace=False)
        x, _ = train.batch(np.zeros(len(ends), int), ends, 1)
        flat = readings(torch.from_numpy(x), cfg.model.input_norm).numpy().reshape(-1, x.shape[-1])
    elif cfg.model.input_norm == "log_resistance":
        flat = readings(torch.from_numpy(flat).unsqueeze(0), cfg.model.input_norm).numpy()[0]
    y = train.angles.reshape(len(train.angles), -1)
    return FlexNet(
        cfg.model,
        flat.shape[1],
        len(cfg.joints),
        cfg.components,
        torch.from_numpy(flat.min(axis=0)),
        torch.from_numpy(flat.max(axis=0)),
        torch.from_numpy(y.mean(axis=0)),
        torch.from_numpy(y.std(axis=0)),
    )


def swing_about_mean(x: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
    """Windows ``(B, W, C)`` whose channels swing about their window mean by a factor per window and channel,
    log-uniform in [1 / (1 + gain), 1 + gain] (``FlexTrainConfig.channel_gain``)."""
    factor = np.exp(rng.uniform(-1.0, 1.0, size=(x.shape[0], 1, x.shape[2])) * np.log1p(gain))
    mean = x.mean(axis=1, keepdims=True)
    return (mean + factor * (x - mean)).astype(x.dtype)


def bent_further(
    x: np.ndarray, angles: np.ndarray, steps: int, deeper: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Windows ``(B, W, C)`` with their angles ``(B, W, 1)`` → the same strides bent further, and the targets of
    their last ``steps`` samples: readings and angle scaled about the window's least-flexed sample by a factor per
    window, log-uniform in [1, 1 + deeper] (``FlexTrainConfig.deeper``). A channel that moves in proportion to the
    flexion over the window reads what a deeper stride would give it."""
    if angles.shape[2] != 1:
        raise ValueError(f"bending further scales one joint's flexion; these windows have {angles.shape[2]} angles")
    factor = np.exp(rng.uniform(0.0, 1.0, size=(x.shape[0], 1, 1)) * np.log1p(deeper))
    rows = np.arange(x.shape[0])
    least = angles[:, :, 0].argmin(axis=1)
    x0, a0 = x[rows, least][:, None], angles[rows, least][:, None]
    return (x0 + factor * (x - x0)).astype(x.dtype), (a0 + factor * (angles - a0))[:, -steps:].astype(angles.dtype)


def validation_mae(net: FlexNet | FlexEnsemble, val: WindowSet, hop: int = 2, mask: np.ndarray | None = None) -> float:
    pred, truth = predict_windows(torch_predictor(net, mask), val, 0, net.latency_samples, hop)
    return float(np.abs(pred - truth).mean())


def answer_mask(cfg: FlexConfig | CapacitiveConfig) -> np.ndarray | None:
    """What the service answers a model of ``cfg`` through (``service.core.flex.answer_mask``, as
    ``service.inference.flex.FlexModel`` reads it from the manifest); None for a capacitive sleeve."""
    if not isinstance(cfg, FlexConfig):
        return None
    return flex_core.answer_mask(cfg.data.limb_twist, cfg.joints, JOINT_COMPONENTS)


def torch_predictor(net: FlexNet | FlexEnsemble, mask: np.ndarray | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """The network on raw windows, its answer times ``mask`` (``answer_mask``) where given: as the service answers."""

    def predict(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            y = net(torch.from_numpy(x)).numpy()
        return y if mask is None else y * mask

    return predict


def train_flex(
    cfg: FlexConfig, train: WindowSet, val: WindowSet, on_epoch: Callable[[int, dict], None] | None = None
) -> FlexTrainResult:
    """One network, or ``cfg.train.members`` of consecutive seeds answering as their mean. ``on_epoch`` gets a
    step that runs on over the members and the epoch's row (``member`` among its keys)."""
    t0 = time.monotonic()
    results = []
    for k in range(cfg.train.members):
        step0 = sum(len(r.history) for r in results)
        report = None if on_epoch is None else (lambda e, row, s=step0: on_epoch(s + e, row))
        results.append(_train_one(cfg.model_copy(update={"seed": cfg.seed + k}), train, val, report, k))
    if len(results) == 1:
        return results[0]
    return FlexTrainResult(
        FlexEnsemble([r.net for r in results]).eval(),
        [row for r in results for row in r.history],
        results[0].best_epoch,
        time.monotonic() - t0,
        "; ".join(f"member {k}: {r.stopped}" for k, r in enumerate(results)),
        [r.best_epoch for r in results],
    )


def _train_one(
    cfg: FlexConfig, train: WindowSet, val: WindowSet, on_epoch: Callable[[int, dict], None] | None, member: int
) -> FlexTrainResult:
    if cfg.train.deeper > 0 and train.angles.reshape(len(train.angles), -1).shape[1] != 1:
        raise ValueError(f"train.deeper bends one joint's flexion further; {cfg.name} answers {cfg.joints}")
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.train.threads)
    rng = np.random.default_rng(cfg.seed)
    net = build_net(cfg, train)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.train.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, cfg.train.lr_step_epochs, gamma=0.1)
    steps, bs = cfg.model.steps, cfg.train.batch_size
    n_suits = train.counts.shape[0]
    history: list[dict[str, float]] = []
    best, best_state, best_epoch, stopped = float("inf"), None, 0, "max_epochs"
    t0 = time.monotonic()
    for epoch in range(cfg.train.max_epochs):
        net.train()
        ends = rng.choice(train.ends, size=cfg.train.windows_per_epoch, p=train.weights)
        suits = rng.integers(0, n_suits, size=len(ends))
        losses = []
        bar = tqdm(range(0, len(ends), bs), desc=f"{cfg.name} epoch {epoch}", unit="batch", leave=False)
        for i in bar:
            x, y = train.batch(suits[i : i + bs], ends[i : i + bs], steps)
            if cfg.train.channel_gain > 0:
                x = swing_about_mean(x, cfg.train.channel_gain, rng)
            if cfg.train.deeper > 0:
                x, y = bent_further(x, train.window_angles(ends[i : i + bs]), steps, cfg.train.deeper, rng)
            x, y = torch.from_numpy(x), torch.from_numpy(y)
            target = (y - net.target_mean) / net.target_std
            loss = torch.mean((net.steps_standardised(x) - target) ** 2)  # eq. 3
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.train.grad_clip)
            opt.step()
            losses.append(loss.item())
        sched.step()
        net.eval()
        val_mae = validation_mae(net, val, mask=answer_mask(cfg))
        row = {
            "train_loss": float(np.mean(losses)),
            "val_mae_deg": val_mae,
            "wall_s": time.monotonic() - t0,
            "member": member,
        }
        history.append(row)
        if on_epoch:
            on_epoch(epoch, row)
        log.info(
            "%s (seed %d) epoch %d: loss %.4f, validation %.2f°", cfg.name, cfg.seed, epoch, row["train_loss"], val_mae
        )
        if val_mae < best:
            best, best_epoch = val_mae, epoch
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        p = cfg.train.patience
        if len(history) > p and min(h["val_mae_deg"] for h in history[:-p]) - best < cfg.train.min_improvement_deg:
            stopped = f"validation improved by less than {cfg.train.min_improvement_deg}° over {p} epochs"
            break
        if time.monotonic() - t0 > cfg.train.time_budget_s:
            stopped = f"time budget {cfg.train.time_budget_s:.0f} s"
            break
    if cfg.train.keep == "best":
        net.load_state_dict(best_state)
    else:
        best_epoch = len(history) - 1  # the epoch whose weights the run keeps
    net.eval()
    return FlexTrainResult(net, history, best_epoch, time.monotonic() - t0, stopped, [best_epoch])
