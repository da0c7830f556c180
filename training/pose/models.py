"""Pose networks: Zheng et al. 2021's Bi-LSTM, Vlutters 2016's LSTM and feed-forward network, and a streaming LSTM.

All map pelvis-relative features ``(B, T, F)`` (``service.core.calibration.pose_features``) to the pelvis-relative
orientations of the output segments as rotation matrices ``(B, T, S, 3, 3)``. Feature standardisation (training
mean and std) sits inside the graph, so the exported ONNX takes the features as the service computes them.

- ``bilstm`` (Zheng et al. 2021 §4.2, Fig. 2, after Huang et al. 2018, DIP): input dropout 0.2, a dense layer with ReLU,
  two bidirectional LSTM layers, a dense output. Fig. 2's numbers are missing from our copy of the paper; DIP
  uses 512 units, we use ``hidden`` (256 on two CPU cores). Trained on 300-frame sequences (150 past, 150 future).
- ``lstm`` (Vlutters 2016 §IV-C; unidirectional): the same without the backward direction. With
  ``look_ahead`` L > 0 it is the streaming model: at input frame t it outputs the pose of frame t − L, so it has
  seen L future frames (TransPose's online mode: 5 frames, 83 ms at 60 Hz).
- ``ffn`` (Vlutters 2016 §IV-C): one frame in, one hidden ReLU layer, dropout 0.5 on the input, linear out.

With ``anchors`` (``model.anchored``, ours) each output's rotation is a sensed neighbour's pelvis-relative rotation,
read from the input features, times the network's (``anchor_sensors``: a thigh from its shank).

Output representation: ``6d`` (the first two columns, Gram–Schmidt; Zhou et al. 2019) or ``axis_angle``
(Zheng et al. 2021's choice; Rodrigues' formula), both turned into matrices in the graph so the loss and the
service see the same thing.
"""

from __future__ import annotations

import torch
from torch import nn

from service.core.body import BODY_PARENT, other_side

REPRESENTATION_WIDTH = {"6d": 6, "axis_angle": 3}


def matrices_from_6d(x: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` → rotation matrices ``(..., 3, 3)`` whose first two columns are the Gram–Schmidt of x."""
    a, b = x[..., :3], x[..., 3:]
    c0 = a / torch.sqrt((a * a).sum(-1, keepdim=True) + 1e-12)
    b = b - (c0 * b).sum(-1, keepdim=True) * c0
    c1 = b / torch.sqrt((b * b).sum(-1, keepdim=True) + 1e-12)
    c2 = torch.linalg.cross(c0, c1, dim=-1)
    return torch.stack([c0, c1, c2], dim=-1)


def matrices_from_axis_angle(r: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ``(..., 3)`` axis × angle (rad) → ``(..., 3, 3)``; smooth at 0 through the eps."""
    theta = torch.sqrt((r * r).sum(-1, keepdim=True) + 1e-12)
    k = r / theta
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = torch.zeros_like(kx)
    K = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], dim=-1).reshape(*r.shape[:-1], 3, 3)
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(K)
    return eye + s * K + (1.0 - c) * (K @ K)


class Mirror(nn.Module):
    """The mirror image through the body's sagittal plane, M = diag(1, −1, 1) in the pelvis frame (x anterior, y left,
    z up), of a model's features and of its answers (``training.pose.data.mirrored`` does it to a clip).

    Features (``service.core.calibration.pose_features``): the pelvis's up and own acceleration turn into M v; each
    other sensor's pelvis-relative rotation into M R M and its acceleration into M a, read from its counterpart's
    place. Answers: each output segment's rotation is its counterpart's, M R M. Every sensor and output needs its
    counterpart among them."""

    def __init__(self, sensors: list[str], outputs: list[str]) -> None:
        super().__init__()
        for names, what in ((sensors, "sensors"), (outputs, "output segments")):
            lonely = [n for n in names if other_side(n) not in names]
            if lonely:
                raise ValueError(f"a mirror image needs each of the {what} with its other side; {lonely} have none")
        lateral = torch.tensor([1.0, -1.0, 1.0])
        flip = torch.outer(lateral, lateral)
        index, sign = [0, 1, 2, 3, 4, 5], [lateral, lateral]
        for name in sensors[1:]:
            start = 6 + 12 * (sensors.index(other_side(name)) - 1)
            index += list(range(start, start + 12))
            sign += [flip.reshape(9), lateral]
        self.register_buffer("feature_index", torch.tensor(index))
        self.register_buffer("feature_sign", torch.cat(sign))
        self.register_buffer("output_index", torch.tensor([outputs.index(other_side(n)) for n in outputs]))
        self.register_buffer("output_sign", flip)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, T, F)`` → the mirror image's features."""
        return x.index_select(-1, self.feature_index) * self.feature_sign

    def answers(self, R: torch.Tensor) -> torch.Tensor:
        """``(B, T, S, 3, 3)`` answered for the mirror image → the answers for the body itself."""
        return R.index_select(2, self.output_index) * self.output_sign


class PoseEnsemble(nn.Module):
    """The mean of several offline pose networks of one recipe (``train.ensemble_of``; not in Zheng et al. 2021):
    per frame and segment the members' rotation matrices are averaged and the mean's first two columns
    orthonormalised (Gram–Schmidt, as the 6D head does), a projection back onto the rotations that keeps the mean's
    direction. With ``mirror`` each member also answers the mirror image of the input, its answer mirrored back
    (``train.ensemble_mirror``): a network trained on both bodies then answers mirror-image motions mirror-image
    poses exactly, and what side-to-side habit its training people left in it averages out.
    ``(B, T, F)`` → ``(B, T, S, 3, 3)`` like a ``PoseNet``."""

    def __init__(self, members: list[PoseNet], mirror: Mirror | None = None) -> None:
        super().__init__()
        first = members[0]
        if len(members) < (1 if mirror else 2) or any(m.kind != "bilstm" for m in members):
            raise ValueError("an ensemble is two or more offline (bilstm) networks, or one with its mirror image")
        self.members = nn.ModuleList(members)
        self.mirror = mirror
        self.kind, self.look_ahead, self.hidden, self.layers = first.kind, first.look_ahead, first.hidden, first.layers

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        answers = [m(x) for m in self.members]
        if self.mirror is not None:
            x_mirror = self.mirror.features(x)
            answers += [self.mirror.answers(m(x_mirror)) for m in self.members]
        R = torch.stack(answers).mean(0)
        return matrices_from_6d(torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1))


def anchor_sensors(sensors: list[str], outputs: list[str]) -> list[int]:
    """For each output segment, the sensor (index into ``sensors``; 0, the pelvis, where none) whose orientation its
    answer is taken relative to (``model.anchored``): a sensed segment next to it in the body's tree, its child first
    (the knee's and elbow's hinge turn a thigh or upper arm about one axis from the shank or forearm below; the
    neck carries the head), else its parent (a hand on its forearm, a foot on its shank)."""
    anchors = []
    for name in outputs:
        children = [k for k, s in enumerate(sensors) if BODY_PARENT[s] == name]
        parent = BODY_PARENT[name]
        anchors.append(children[0] if children else sensors.index(parent) if parent in sensors else 0)
    return anchors


class PoseNet(nn.Module):
    def __init__(
        self,
        kind: str,
        n_features: int,
        n_segments: int,
        hidden: int = 256,
        layers: int = 2,
        input_dropout: float = 0.2,
        representation: str = "6d",
        look_ahead: int = 0,
        anchors: list[int] | None = None,
    ) -> None:
        super().__init__()
        if kind not in ("bilstm", "lstm", "ffn"):
            raise ValueError(f"kind must be bilstm, lstm or ffn, got {kind!r}")
        if representation not in REPRESENTATION_WIDTH:
            raise ValueError(f"representation must be one of {sorted(REPRESENTATION_WIDTH)}, got {representation!r}")
        self.kind, self.representation, self.look_ahead = kind, representation, look_ahead
        self.n_segments, self.hidden, self.layers = n_segments, hidden, layers
        if anchors is not None and (len(anchors) != n_segments or look_ahead):
            raise ValueError("anchors: one sensor index per output segment, for networks without look-ahead")
        # each output's answer turned by its anchor sensor's pelvis-relative rotation (the features' 9 numbers of
        # that sensor, ``service.core.calibration.pose_features``; the identity appended last for the pelvis)
        self.anchored = anchors is not None and any(anchors)

        def rows(a: int) -> range:  # the identity (appended after the features) for the pelvis, else sensor a's R
            return range(n_features, n_features + 9) if a == 0 else range(6 + 12 * (a - 1), 15 + 12 * (a - 1))

        index = [i for a in (anchors or [0] * n_segments) for i in rows(a)]
        self.register_buffer("anchor_index", torch.tensor(index), persistent=False)
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("std", torch.ones(n_features))
        self.dropout = nn.Dropout(input_dropout)
        self.embed = nn.Sequential(nn.Linear(n_features, hidden), nn.ReLU())
        width = REPRESENTATION_WIDTH[representation] * n_segments
        if kind == "ffn":
            self.rnn = None
            self.out = nn.Linear(hidden, width)
        else:
            self.rnn = nn.LSTM(hidden, hidden, layers, batch_first=True, bidirectional=kind == "bilstm")
            self.out = nn.Linear(hidden * (2 if kind == "bilstm" else 1), width)

    def set_normalisation(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        self.mean.copy_(mean)
        self.std.copy_(torch.clamp(std, min=1e-3))

    def _head(self, y: torch.Tensor) -> torch.Tensor:
        y = self.out(y).reshape(*y.shape[:2], self.n_segments, REPRESENTATION_WIDTH[self.representation])
        return matrices_from_6d(y) if self.representation == "6d" else matrices_from_axis_angle(y)

    def anchor_rotations(self, x: torch.Tensor) -> torch.Tensor:
        """Features ``(B, T, F)`` → each output's anchor rotation, pelvis-relative ``(B, T, S, 3, 3)``."""
        eye = torch.eye(3, dtype=x.dtype, device=x.device).reshape(1, 1, 9).expand(*x.shape[:2], 9)
        rows = torch.cat([x, eye], dim=-1).index_select(-1, self.anchor_index)
        return rows.reshape(*x.shape[:2], self.n_segments, 3, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, T, F)`` → ``(B, T, S, 3, 3)``."""
        h = self.embed(self.dropout((x - self.mean) / self.std))
        if self.rnn is not None:
            h, _ = self.rnn(h)
        R = self._head(h)
        return self.anchor_rotations(x) @ R if self.anchored else R

    def step(
        self, x: torch.Tensor, h0: torch.Tensor, c0: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Streaming (``lstm`` only): frames ``(B, T, F)`` with the state ``(layers, B, hidden)`` in and out."""
        if self.kind != "lstm":
            raise TypeError("only the unidirectional lstm streams")
        h = self.embed((x - self.mean) / self.std)
        h, (h1, c1) = self.rnn(h, (h0, c0))
        R = self._head(h)
        return (self.anchor_rotations(x) @ R if self.anchored else R), h1, c1


class StreamingExport(nn.Module):
    """The graph the service streams with: (features, h, c) → (rotations, h, c)."""

    def __init__(self, net: PoseNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor, h0: torch.Tensor, c0: torch.Tensor):
        return self.net.step(x, h0, c0)
