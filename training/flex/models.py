"""The networks of Chen et al. 2024 Table 5 on windows of raw counts, with its dynamic calibration and median layer.

Every network takes ``(B, window, C)`` raw readings (counts) and does inside the graph what is stateless
(docs/conventions.md): min-max normalisation with the training set's per-channel bounds (§3.4.3; for real sleeves
optionally of each channel relative to its window's mean, or for the simulated strips of the log resistance read
back from the counts, ``input_norm``), the dynamic
calibration of eq. 2 where enabled, then only the last ``steps`` samples go to the network (§4.2.4). It predicts
one set of joint angles per step (the loss of eq. 3 is over the whole short sequence); with the median layer
(§3.4.4, kernel 3, padding 1) the steps' predictions are smoothed and the answer is the second-to-last step, the
last one whose median has a real neighbour on both sides: one sample (50 ms at 20 Hz) behind the newest reading.
Without it the answer is the last step.

Dimensions follow appendix B: Bi-LSTM Dense1-4 of 100, 512, 1024, 150 units around one bidirectional layer of
512 (§3.4.1); Transformer encoder of one layer and 4 heads (d_model 64, ours); FCN hidden 200 and 100; TCN
kernel 7, 64 channels, dilations 1 and 2 after a linear layer to 64.
"""

from __future__ import annotations

import torch
from torch import nn

from training.flex.config import FlexModelConfig
from training.flex.simulate import ADC_MAX, AMP_GAIN


def log_resistance(x: torch.Tensor) -> torch.Tensor:
    """Counts → log(R / R_i) through Chen et al. 2024 eq. 1 with the nominal read-out (``training.flex.simulate``):
    R / (R_i + R) = counts / (4096 G) + 1/2. Counts at 0 (R at or below R_i) read as R = R_i; the upper clamp only
    guards the logarithm (4095 counts is R ≈ 14 R_i)."""
    u = (x / ((ADC_MAX + 1) * AMP_GAIN) + 0.5).clamp(0.5 + 1e-4, 1.0 - 1e-4)
    return torch.log(u) - torch.log1p(-u)


def readings(x: torch.Tensor, input_norm: str) -> torch.Tensor:
    """``(B, T, C)`` raw readings → what the min-max bounds apply to (``FlexModelConfig.input_norm``)."""
    if input_norm in ("window_relative", "window_standardised"):
        relative = x / x.mean(dim=1, keepdim=True).clamp_min(1e-6) - 1.0
        if input_norm == "window_relative":
            return relative
        # each channel's swing over its window in units of its own spread: a sleeve that modulates by other amounts
        return relative / relative.std(dim=1, keepdim=True).clamp_min(1e-3)
    if input_norm == "log_resistance":
        return log_resistance(x)
    return x


class DynamicCalibration(nn.Module):
    """Chen et al. 2024 eq. 2, Y_out = Y_in − LN(ave(min(Y_in))), per channel over the window's time axis:
    min pooling (stride 1, no padding), average pooling (stride 1, padding ``avg_padding``), and a linear layer
    back to the window's length (the baseline per sample), shared by the channels."""

    def __init__(self, window: int, min_kernel: int, avg_kernel: int, avg_padding: int, init: str = "default") -> None:
        super().__init__()
        self.min_kernel, self.avg_kernel, self.avg_padding = min_kernel, avg_kernel, avg_padding
        pooled = window - min_kernel + 1
        pooled = pooled + 2 * avg_padding - avg_kernel + 1
        if pooled < 1:
            raise ValueError(f"window {window} is too short for kernels {min_kernel} and {avg_kernel}")
        self.linear = nn.Linear(pooled, window)
        if init == "baseline":
            # each sample's baseline starts as the mean of the pooled minima that no zero padding reached, so an
            # offset of every reading (a drifted baseline) is taken out exactly
            inner = pooled - 2 * avg_padding
            with torch.no_grad():
                self.linear.weight.zero_()
                self.linear.weight[:, avg_padding : avg_padding + inner] = 1.0 / inner
                self.linear.bias.zero_()

    def baseline(self, y: torch.Tensor) -> torch.Tensor:
        """``(B, T, C)`` → the baseline ``(B, T, C)`` that is subtracted."""
        z = y.transpose(1, 2)  # (B, C, T)
        z = -nn.functional.max_pool1d(-z, self.min_kernel, stride=1)
        # zero padding as count_include_pad would, done by hand: PyTorch pools pad at most half the kernel (5)
        z = nn.functional.avg_pool1d(nn.functional.pad(z, (self.avg_padding, self.avg_padding)), self.avg_kernel, 1)
        return self.linear(z).transpose(1, 2)

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        return y - self.baseline(y)


def median3(p: torch.Tensor) -> torch.Tensor:
    """Median pooling over the step axis of ``(B, S, O)``, kernel 3, padding 1 (replicating the end steps).
    The median of three as max(min(a, b), min(max(a, b), c)): plain Min/Max ops in ONNX."""
    padded = torch.cat([p[:, :1], p, p[:, -1:]], dim=1)
    a, b, c = padded[:, :-2], padded[:, 1:-1], padded[:, 2:]
    return torch.maximum(torch.minimum(a, b), torch.minimum(torch.maximum(a, b), c))


class BiLSTMNet(nn.Module):
    def __init__(self, channels: int, outputs: int, sizes: tuple[int, int, int, int, int]) -> None:
        super().__init__()
        d1, d2, hidden, d3, d4 = sizes
        self.pre = nn.Sequential(nn.Linear(channels, d1), nn.ReLU(), nn.Linear(d1, d2), nn.ReLU())
        self.lstm = nn.LSTM(d2, hidden, batch_first=True, bidirectional=True)
        self.post = nn.Sequential(nn.Linear(2 * hidden, d3), nn.ReLU(), nn.Linear(d3, d4), nn.ReLU())
        self.out = nn.Linear(d4, outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.lstm(self.pre(x))
        return self.out(self.post(h))


class TransformerNet(nn.Module):
    def __init__(self, channels: int, outputs: int, steps: int, d_model: int = 64) -> None:
        super().__init__()
        self.inp = nn.Linear(channels, d_model)
        self.position = nn.Parameter(torch.zeros(1, steps, d_model))
        layer = nn.TransformerEncoderLayer(d_model, 4, dim_feedforward=4 * d_model, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, 1, enable_nested_tensor=False)
        self.out = nn.Linear(d_model, outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.encoder(self.inp(x) + self.position))


class FCNNet(nn.Module):
    def __init__(self, channels: int, outputs: int, steps: int) -> None:
        super().__init__()
        self.steps, self.outputs = steps, outputs
        self.net = nn.Sequential(
            nn.Flatten(), nn.Linear(steps * channels, 200), nn.ReLU(), nn.Linear(200, 100), nn.ReLU()
        )
        self.out = nn.Linear(100, steps * outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.net(x)).view(-1, self.steps, self.outputs)


class _CausalConv(nn.Module):
    def __init__(self, channels: int, kernel: int, dilation: int) -> None:
        super().__init__()
        self.pad = (kernel - 1) * dilation
        self.conv = nn.Conv1d(channels, channels, kernel, dilation=dilation)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return z + torch.relu(self.conv(nn.functional.pad(z, (self.pad, 0))))


class TCNNet(nn.Module):
    def __init__(self, channels: int, outputs: int, hidden: int = 64, kernel: int = 7) -> None:
        super().__init__()
        self.inp = nn.Linear(channels, hidden)
        self.blocks = nn.Sequential(_CausalConv(hidden, kernel, 1), _CausalConv(hidden, kernel, 2))
        self.out = nn.Linear(hidden, outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.blocks(self.inp(x).transpose(1, 2)).transpose(1, 2)
        return self.out(z)


class FlexNet(nn.Module):
    """Raw counts ``(B, window, C)`` → joint angles in degrees ``(B, joints, components)`` (``forward``), or all
    steps' predictions ``(B, steps, joints·components)`` for the loss (``steps_out``)."""

    def __init__(
        self,
        cfg: FlexModelConfig,
        channels: int,
        joints: int,
        components: int,
        input_min: torch.Tensor,
        input_max: torch.Tensor,
        target_mean: torch.Tensor,
        target_std: torch.Tensor,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.joints, self.components = joints, components
        outputs = joints * components
        self.register_buffer("input_min", input_min.float().view(1, 1, channels))
        self.register_buffer("input_span", (input_max - input_min).clamp_min(1e-6).float().view(1, 1, channels))
        self.register_buffer("target_mean", target_mean.float().view(1, 1, outputs))
        self.register_buffer("target_std", target_std.clamp_min(0.5).float().view(1, 1, outputs))
        self.calibration = (
            DynamicCalibration(cfg.window, cfg.min_kernel, cfg.avg_kernel, cfg.avg_padding, cfg.calibration_init)
            if cfg.calibration
            else None
        )
        if cfg.kind == "bilstm":
            self.net: nn.Module = BiLSTMNet(channels, outputs, cfg.bilstm_sizes)
        elif cfg.kind == "transformer":
            self.net = TransformerNet(channels, outputs, cfg.steps)
        elif cfg.kind == "fcn":
            self.net = FCNNet(channels, outputs, cfg.steps)
        else:
            self.net = TCNNet(channels, outputs)
        self.linear_path = nn.Linear(channels, outputs) if cfg.linear_path else None

    @property
    def answer_step(self) -> int:
        return self.cfg.steps - 2 if self.cfg.median else self.cfg.steps - 1

    @property
    def latency_samples(self) -> int:
        return self.cfg.steps - 1 - self.answer_step

    def normalised(self, x: torch.Tensor) -> torch.Tensor:
        return (readings(x, self.cfg.input_norm) - self.input_min) / self.input_span

    def steps_standardised(self, x: torch.Tensor) -> torch.Tensor:
        """Predictions of every step in units of the training targets' standard deviation about their mean."""
        y = self.normalised(x)
        if self.calibration is not None:
            y = self.calibration(y)
        y = y[:, -self.cfg.steps :]
        p = self.net(y)
        if self.linear_path is not None:
            p = p + self.linear_path(y)
        return median3(p) if self.cfg.median else p

    def steps_deg(self, x: torch.Tensor) -> torch.Tensor:
        return self.steps_standardised(x) * self.target_std + self.target_mean

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.steps_deg(x)[:, self.answer_step]
        return p.view(-1, self.joints, self.components)


class FlexEnsemble(nn.Module):
    """The mean answer of several networks of one recipe trained from consecutive seeds (``train.members``; ours,
    not in Chen et al. 2024; docs/flex.md has what it does on the sleeves). Same input and output as a
    ``FlexNet``; every member answers the same sample (same window, steps and median layer)."""

    def __init__(self, members: list[FlexNet]) -> None:
        super().__init__()
        if len(members) < 2 or any(m.cfg != members[0].cfg for m in members):
            raise ValueError("an ensemble is two or more networks of one recipe")
        self.members = nn.ModuleList(members)
        self.cfg = members[0].cfg
        self.register_buffer("input_min", members[0].input_min.clone())

    @property
    def latency_samples(self) -> int:
        return self.members[0].latency_samples

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([m(x) for m in self.members]).mean(0)
