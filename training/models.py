"""The networks of paper 000 §2.2 and Table A1: a shared CNN front end, a GRU for assignment and a
2-layer LSTM for alignment. Only the models live here; training is in ``training.train``.
"""

from __future__ import annotations

import torch
from torch import nn

from service.core.segments import SEGMENTS
from service.core.units import GRAVITY_MPS2

GYRO_SCALE_RADS = 3.14159


class InputScale(nn.Module):
    """Fixed per-channel scaling (acc / g, gyr / π rad/s), part of the exported graph (DESIGN.md §1)."""

    def __init__(self) -> None:
        super().__init__()
        scale = torch.tensor([1 / GRAVITY_MPS2] * 3 + [1 / GYRO_SCALE_RADS] * 3)
        self.register_buffer("scale", scale)

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        return imu * self.scale


class ConvFrontEnd(nn.Module):
    """3 × (Conv1d 64 kernels of 16, batch norm, ReLU), eq. 2–3; ``(B, T, 6)`` → ``(B, T, 64)``."""

    def __init__(self, channels: int = 64, kernel: int = 16, layers: int = 3, keep_prob: float = 0.8) -> None:
        super().__init__()
        self.input_dropout = nn.Dropout(1.0 - keep_prob)  # §2.2.4: input dropout, keep probability 0.8
        blocks: list[nn.Module] = []
        in_ch = 6
        for _ in range(layers):
            blocks += [nn.Conv1d(in_ch, channels, kernel, padding="same"), nn.BatchNorm1d(channels), nn.ReLU()]
            in_ch = channels
        self.net = nn.Sequential(*blocks)

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        x = self.input_dropout(imu).transpose(1, 2)
        return self.net(x).transpose(1, 2)


class AssignmentNet(nn.Module):
    """CNN → GRU(128) → linear → 7 logits in ``SEGMENTS`` order (paper 000 Fig. 2, Table A1)."""

    def __init__(self, hidden: int = 128, channels: int = 64, kernel: int = 16, keep_prob: float = 0.8) -> None:
        super().__init__()
        self.scale = InputScale()
        self.cnn = ConvFrontEnd(channels, kernel, 3, keep_prob)
        self.rnn = nn.GRU(channels, hidden, num_layers=1, batch_first=True)
        self.head = nn.Linear(hidden, len(SEGMENTS))

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        features, _ = self.rnn(self.cnn(self.scale(imu)))
        return self.head(features[:, -1])


class AlignmentNet(nn.Module):
    """CNN → 2-layer LSTM(128) → linear → stereographic projections, one per segment hypothesis.

    The alignment R_SI is only defined relative to a segment, so the head regresses 3 values for
    each of the 7 segments, ``(B, 7, 3)``; training supervises the row of the true segment and the
    service picks the row of the assigned (or declared) segment.
    """

    def __init__(self, hidden: int = 128, channels: int = 64, kernel: int = 16, keep_prob: float = 0.8) -> None:
        super().__init__()
        self.scale = InputScale()
        self.cnn = ConvFrontEnd(channels, kernel, 3, keep_prob)
        self.rnn = nn.LSTM(channels, hidden, num_layers=2, batch_first=True)
        self.head = nn.Linear(hidden, 3 * len(SEGMENTS))

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        features, _ = self.rnn(self.cnn(self.scale(imu)))
        return self.head(features[:, -1]).reshape(-1, len(SEGMENTS), 3)


def stereographic_to_quat(p: torch.Tensor) -> torch.Tensor:
    """q = (1 - |p|², 2p) / (1 + |p|²), then w ≥ 0 (ref. 56 of paper 000); ``(..., 3)`` → ``(..., 4)``."""
    n2 = (p * p).sum(-1, keepdim=True)
    q = torch.cat([1.0 - n2, 2.0 * p], dim=-1) / (1.0 + n2)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


class AlignmentExport(nn.Module):
    """Exported alignment graph: imu ``(B, 128, 6)`` → q_segment_imu ``(B, 7, 4)`` unit, w ≥ 0."""

    def __init__(self, net: AlignmentNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        return stereographic_to_quat(self.net(imu))


class AssignmentExport(nn.Module):
    """Exported assignment graph: imu ``(B, 128, 6)`` → class probabilities ``(B, 7)`` (softmax inside)."""

    def __init__(self, net: AssignmentNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.net(imu), dim=-1)
