"""Warm-start an ``AssignmentNet`` from a shipped ONNX model (paper 000 §4.3 fine-tuning from any release), and
assemble an ``AssignmentEnsemble`` from shipped members.

The TorchScript exporter folds each BatchNorm into its Conv and stores the GRU in ONNX gate order
(z, r, h) where torch uses (r, z, n). The state dict is rebuilt accordingly (BatchNorm set to the
identity, so the fused convolutions carry the whole affine map), and the result must reproduce the
model's ``golden.npz`` before it is used.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from service.core.manifest import read_manifest
from training.models import AssignmentEnsemble, AssignmentNet


def _reorder_gates(w: np.ndarray, hidden: int) -> np.ndarray:
    """ONNX (z, r, h) blocks along axis 0 → torch (r, z, n)."""
    z, r, h = w[:hidden], w[hidden : 2 * hidden], w[2 * hidden :]
    return np.concatenate([r, z, h])


def assignment_state_from_onnx(onnx_path: Path, net: AssignmentNet) -> dict[str, torch.Tensor]:
    """``net``'s state dict filled from an exported assignment graph, plain or averaged over turns (every pass
    runs the same weights; the first is the window as it came, which the golden check covers)."""
    model = onnx.load(str(onnx_path))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    gru = next(n for n in model.graph.node if n.op_type == "GRU")
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
    hidden = net.rnn.hidden_size
    W, R, B = (inits[name][0] for name in gru.input[1:4])
    state["rnn.weight_ih_l0"] = torch.from_numpy(_reorder_gates(W, hidden))
    state["rnn.weight_hh_l0"] = torch.from_numpy(_reorder_gates(R, hidden))
    state["rnn.bias_ih_l0"] = torch.from_numpy(_reorder_gates(B[: 3 * hidden], hidden))
    state["rnn.bias_hh_l0"] = torch.from_numpy(_reorder_gates(B[3 * hidden :], hidden))
    state["head.weight"] = torch.from_numpy(inits["net.head.weight"].copy())
    state["head.bias"] = torch.from_numpy(inits["net.head.bias"].copy())
    return state


def averaging_options(exporter: dict) -> dict:
    """``AssignmentNet`` keyword arguments for the turn averages a shipped graph was exported with (manifest
    ``exporter``; absent keys: off)."""
    return {
        "quarter_turns": bool(exporter.get("quarter_turns", False)),
        "gravity_turns": int(exporter.get("gravity_turns", 1)),
        "gravity_turn_segments": exporter.get("gravity_turn_segments"),
    }


def warm_start_from_shipped(model_dir: Path, net: AssignmentNet, atol: float = 1e-4) -> dict[str, torch.Tensor]:
    """State dict rebuilt from ``model_dir/model.onnx``, verified against ``model_dir/golden.npz``."""
    manifest = read_manifest(model_dir / "manifest.json")
    if "quantization" in manifest.exporter:
        source = model_dir.parent / str(manifest.exporter.get("quantized_from", "?"))
        raise ValueError(f"{model_dir} is an int8 model; warm start needs the float32 file it came from: {source}")
    if "ensemble_of" in manifest.exporter:
        members = manifest.exporter["ensemble_of"]
        raise ValueError(f"{model_dir} is an ensemble; warm start from one of its members: {members}")
    state = assignment_state_from_onnx(model_dir / "model.onnx", net)
    probe = AssignmentNet(
        net.rnn.hidden_size,
        net.cnn.net[0].out_channels,
        net.cnn.net[0].kernel_size[0],
        canonical=net.canonical is not None,
        **averaging_options(manifest.exporter),
    )
    probe.load_state_dict(state)
    probe.eval()
    with np.load(model_dir / "golden.npz") as golden, torch.no_grad():
        got = torch.softmax(probe(torch.from_numpy(golden["imu"])), -1).numpy()
        err = float(np.max(np.abs(got - golden["expected"])))
    if err > atol:
        raise ValueError(f"weights rebuilt from {model_dir} differ from its golden output by {err:.2e} > {atol}")
    return state


def shipped_assignment_net(model_dir: Path, hidden: int, channels: int, kernel: int, keep_prob: float) -> AssignmentNet:
    """An untrained ``AssignmentNet`` with the turn averages a shipped float32 model was exported with."""
    exporter = read_manifest(model_dir / "manifest.json").exporter
    return AssignmentNet(hidden, channels, kernel, keep_prob, **averaging_options(exporter))


def assignment_ensemble(
    member_dirs: list[str], hidden: int, channels: int, kernel: int, keep_prob: float
) -> AssignmentEnsemble:
    """The architecture of an ensemble of shipped float32 assignment models (weights: ``ensemble_state``)."""
    return AssignmentEnsemble(
        [shipped_assignment_net(Path(d), hidden, channels, kernel, keep_prob) for d in member_dirs]
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
