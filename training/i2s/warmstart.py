"""Warm-start an ``AssignmentNet`` or ``AlignmentNet`` from a shipped ONNX model (Zimmermann et al. 2018 §4.3
fine-tuning from any release, on a fresh clone whose restored runs carry no checkpoints), and assemble an
``AssignmentEnsemble`` from shipped members.

The TorchScript exporter folds each BatchNorm into its Conv and stores the recurrent weights in ONNX gate order
(``training.onnx_weights``). The state dict is rebuilt accordingly (BatchNorm set to the identity, so the fused
convolutions carry the whole affine map), and the result must reproduce the model's ``golden.npz`` before it is
used.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper
from torch import nn

from service.core.manifest import read_manifest
from training.i2s.models import AlignmentNet, AssignmentEnsemble, AssignmentNet, is_geometry_convolution
from training.onnx_weights import GRU_GATES, LSTM_GATES, recurrent_state


def state_from_onnx(onnx_path: Path, net: AssignmentNet | AlignmentNet) -> dict[str, torch.Tensor]:
    """``net``'s state dict filled from an exported graph of the same architecture: an assignment graph (GRU),
    plain or averaged over turns (every pass runs the same weights; the first is the window as it came, which the
    golden check covers), or an alignment graph (one ONNX LSTM node per layer of the 2-layer LSTM)."""
    model = onnx.load(str(onnx_path))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    convs = [n for n in model.graph.node if n.op_type == "Conv" and not is_geometry_convolution(n.name)]
    state = {k: v.clone() for k, v in net.state_dict().items()}
    conv_layers = [k for k in state if k.startswith("cnn.net.") and k.endswith(".weight") and state[k].dim() == 3]
    if not convs or len(convs) % len(conv_layers):
        raise ValueError(f"expected a multiple of {len(conv_layers)} Conv nodes, the ONNX graph has {len(convs)}")
    for key, node in zip(conv_layers, convs[: len(conv_layers)], strict=True):
        index = int(key.split(".")[2])
        state[key] = torch.from_numpy(inits[node.input[1]].copy())
        state[f"cnn.net.{index}.bias"] = torch.from_numpy(inits[node.input[2]].copy())
        bn = f"cnn.net.{index + 1}"
        eps = net.cnn.net[index + 1].eps
        state[f"{bn}.weight"] = torch.ones_like(state[f"{bn}.weight"])
        state[f"{bn}.bias"] = torch.zeros_like(state[f"{bn}.bias"])
        state[f"{bn}.running_mean"] = torch.zeros_like(state[f"{bn}.running_mean"])
        state[f"{bn}.running_var"] = torch.full_like(state[f"{bn}.running_var"], 1.0 - eps)
    op, order = ("GRU", GRU_GATES) if isinstance(net.rnn, torch.nn.GRU) else ("LSTM", LSTM_GATES)
    layers = [n for n in model.graph.node if n.op_type == op]
    if len(layers) < net.rnn.num_layers or len(layers) % net.rnn.num_layers:
        raise ValueError(f"expected {net.rnn.num_layers} {op} node(s) per pass, the ONNX graph has {len(layers)}")
    for layer, node in enumerate(layers[: net.rnn.num_layers]):
        state |= recurrent_state(node, inits, layer, net.rnn.hidden_size, order)
    head = next(name[: -len("weight")] for name in inits if name.endswith("head.weight"))
    state["head.weight"] = torch.from_numpy(inits[f"{head}weight"].copy())
    state["head.bias"] = torch.from_numpy(inits[f"{head}bias"].copy())
    return state


def averaging_options(exporter: dict) -> dict:
    """``AssignmentNet`` keyword arguments for the turn averages a shipped graph was exported with (manifest
    ``exporter``; absent keys: off)."""
    return {
        "quarter_turns": bool(exporter.get("quarter_turns", False)),
        "gravity_turns": int(exporter.get("gravity_turns", 1)),
        "gravity_turn_segments": exporter.get("gravity_turn_segments"),
    }


def warm_start_from_shipped(
    model_dir: Path, net: AssignmentNet | AlignmentNet, atol: float = 1e-4
) -> dict[str, torch.Tensor]:
    """State dict rebuilt from ``model_dir/model.onnx``, verified against ``model_dir/golden.npz``.

    The check runs a copy of the shipped graph (its turn averages, canonical frame and functional axes, from the
    manifest's ``exporter``); ``net`` itself may differ in those weight-free parts, e.g. an alignment network
    trained without the functional axes its warm start was shipped with.
    """
    manifest = read_manifest(model_dir / "manifest.json")
    if "quantization" in manifest.exporter:
        source = model_dir.parent / str(manifest.exporter.get("quantized_from", "?"))
        raise ValueError(f"{model_dir} is an int8 model; warm start needs the float32 file it came from: {source}")
    if "ensemble_of" in manifest.exporter:
        members = manifest.exporter["ensemble_of"]
        raise ValueError(f"{model_dir} is an ensemble; warm start from one of its members: {members}")
    task = "alignment" if isinstance(net, AlignmentNet) else "assignment"
    if manifest.task != f"i2s_{task}":
        raise ValueError(f"{model_dir} is an {manifest.task} model; this run trains i2s_{task}")
    state = state_from_onnx(model_dir / "model.onnx", net)
    sizes = (net.rnn.hidden_size, net.cnn.net[0].out_channels, net.cnn.net[0].kernel_size[0])
    probe = shipped_graph(model_dir, task, *sizes)
    probe.load_state_dict(state)
    probe.eval()
    with np.load(model_dir / "golden.npz") as golden, torch.no_grad():
        out = probe(torch.from_numpy(golden["imu"]))
        expected = golden["expected"]
        if task == "assignment":
            err = float(np.max(np.abs(torch.softmax(out, -1).numpy() - expected)))
        else:  # unit quaternions: q and −q are one rotation, so each is compared with the nearer sign
            got = out.numpy()
            same, flipped = (np.abs(got - sign * expected).max(-1) for sign in (1.0, -1.0))
            err = float(np.max(np.minimum(same, flipped)))
    if err > atol:
        raise ValueError(f"weights rebuilt from {model_dir} differ from its golden output by {err:.2e} > {atol}")
    return state


def shipped_graph(
    model_dir: Path,
    task: str,
    hidden: int,
    channels: int,
    kernel: int,
    keep_prob: float = 0.8,
    functional_axes: bool = True,
) -> AssignmentNet | AlignmentNet:
    """An untrained network with the weight-free parts of a shipped float32 graph: its turn averages or functional
    axes (manifest ``exporter``; ``functional_axes`` False: the alignment network alone, without them) and its
    canonical frame (read from the graph: older manifests do not record it)."""
    exporter = read_manifest(model_dir / "manifest.json").exporter
    graph = onnx.load(str(model_dir / "model.onnx")).graph
    canonical = any(node.name.startswith("/canonical/") for node in graph.node)
    if task == "alignment":
        return AlignmentNet(
            hidden,
            channels,
            kernel,
            keep_prob,
            canonical=canonical,
            functional_axes=exporter.get("functional_axes") if functional_axes else None,
            pelvis_half_turn=exporter.get("pelvis_half_turn") if functional_axes else None,
            rnn_stride=int(exporter.get("rnn_stride", 1)),
        )
    return AssignmentNet(hidden, channels, kernel, keep_prob, canonical=canonical, **averaging_options(exporter))


def assignment_ensemble(
    member_dirs: list[str], hidden: int, channels: int, kernel: int, keep_prob: float
) -> AssignmentEnsemble:
    """The architecture of an ensemble of shipped float32 assignment models (weights: ``ensemble_state``)."""
    return AssignmentEnsemble(
        [shipped_graph(Path(d), "assignment", hidden, channels, kernel, keep_prob) for d in member_dirs]  # type: ignore[misc]
    )


def ensemble_state(member_dirs: list[str], ensemble: AssignmentEnsemble) -> dict[str, torch.Tensor]:
    """The ensemble's state dict: each member's weights rebuilt and checked by ``warm_start_from_shipped``."""
    state = {}
    for i, (model_dir, member) in enumerate(zip(member_dirs, ensemble.members, strict=True)):
        member_state = warm_start_from_shipped(Path(model_dir), member)  # type: ignore[arg-type]
        state.update({f"members.{i}.{key}": value for key, value in member_state.items()})
    return state


def ensemble_members(exporter: dict, models_root: Path) -> list[str]:
    """The member model dirs an ensemble's manifest names (``models_root/<name>/<version>``)."""
    return [str(models_root / str(member)) for member in exporter.get("ensemble_of", [])]


class _LogProbabilities(nn.Module):
    """A network's output as log class probabilities (idempotent: an averaged net's output already is one)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, imu: torch.Tensor) -> torch.Tensor:
        return torch.log_softmax(self.net(imu), -1)


def network_sizes(model_dir: Path) -> tuple[int, int, int]:
    """(hidden, channels, kernel) of a shipped one-network float32 graph, read from its first convolution's and its
    recurrent layer's weights (the assignment's GRU, the alignment's LSTM)."""
    graph = onnx.load(str(model_dir / "model.onnx")).graph
    inits = {i.name: i for i in graph.initializer}
    conv = next(n for n in graph.node if n.op_type == "Conv")
    rnn = next(n for n in graph.node if n.op_type in ("GRU", "LSTM"))
    channels, _, kernel = inits[conv.input[1]].dims
    return int(inits[rnn.input[2]].dims[-1]), int(channels), int(kernel)


def teacher_from_shipped(model_dir: Path, keep_prob: float = 0.8) -> nn.Module:
    """A shipped float32 assignment model as a frozen torch network in evaluation mode that outputs log class
    probabilities: an ensemble (manifest ``exporter.ensemble_of``) from its members, each with its turn averages,
    or one network; its sizes read from its file, its weights checked against every golden output on the way."""
    exporter = read_manifest(model_dir / "manifest.json").exporter
    members = ensemble_members(exporter, model_dir.parent.parent)
    hidden, channels, kernel = network_sizes(Path(members[0]) if members else model_dir)
    if members:
        net: nn.Module = assignment_ensemble(members, hidden, channels, kernel, keep_prob)
        net.load_state_dict(ensemble_state(members, net))  # type: ignore[arg-type]
    else:
        net = shipped_graph(model_dir, "assignment", hidden, channels, kernel, keep_prob)
        net.load_state_dict(warm_start_from_shipped(model_dir, net))  # type: ignore[arg-type]
    teacher = _LogProbabilities(net).eval()
    for p in teacher.parameters():
        p.requires_grad_(False)
    with np.load(model_dir / "golden.npz") as golden, torch.no_grad():  # the whole, as the service runs it
        err = float(np.max(np.abs(torch.exp(teacher(torch.from_numpy(golden["imu"]))).numpy() - golden["expected"])))
    if err > 1e-4:
        raise ValueError(f"the teacher rebuilt from {model_dir} differs from its golden output by {err:.2e}")
    return teacher


def alignment_teacher_from_shipped(model_dir: Path, keep_prob: float = 0.8) -> AlignmentNet:
    """A shipped float32 alignment model's network as a frozen torch network in evaluation mode: its canonical
    frame and LSTM stride as shipped, without its functional axes (weight-free steps on the network's answer, which
    the student trains without too and is wrapped in afterwards), so that it answers what the network it teaches
    answers; its sizes read from its file, its weights checked against the whole graph's golden output on the way
    (``warm_start_from_shipped``)."""
    if "quantization" in read_manifest(model_dir / "manifest.json").exporter:  # its task: ``build_teacher``
        raise ValueError(f"an alignment teacher is a float32 alignment file; {model_dir} is an int8 one")
    net = shipped_graph(model_dir, "alignment", *network_sizes(model_dir), keep_prob, functional_axes=False)
    assert isinstance(net, AlignmentNet)
    net.load_state_dict(warm_start_from_shipped(model_dir, net))
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def real_recordings_seen(model_dir: Path) -> list[str]:
    """The real recordings a shipped model trained on, an ensemble's through its members (manifest
    ``training_data.real_train_recordings``)."""
    manifest = read_manifest(model_dir / "manifest.json")
    seen = set(manifest.training_data.get("real_train_recordings", []))
    for member in ensemble_members(manifest.exporter, model_dir.parent.parent):
        seen |= set(real_recordings_seen(Path(member)))
    return sorted(seen)


def check_real_recordings_declared(model_dirs: list[str], declared: list[str], role: str) -> None:
    """Models whose outputs a run builds on (ensemble members, a teacher) make the real recordings they trained
    on training data of the run too: the run must name them (``data.real_train_recordings``), so that no
    evaluation of it uses them."""
    for model_dir in model_dirs:
        if missing := sorted(set(real_recordings_seen(Path(model_dir))) - set(declared)):
            raise ValueError(
                f"{role} {model_dir} trained on the real recordings {missing}; add them to "
                f"data.real_train_recordings (now {declared}) so that no evaluation uses them"
            )
